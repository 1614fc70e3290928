"""``kincal design --measurement TYPE`` and ``POST /api/v1/designs`` for the measurement types
other than pose and position (issue 16): plane contact, several markers, ball in socket.

Each design is checked against the solver computed here from the Jacobian of the
measurement model (the chain parameters' information with the model's own unknowns profiled
out as the inverse of the chain block of the full inverse, not the service's Schur complement).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationOptions
from schemas.design import DesignOptions
from schemas.robots import load_robot
from service.app import calibrate as pipeline
from service.app.design import volume_of
from solver.design.candidates import Volume, sample_candidates, tip_poses
from solver.design.criteria import DesignProblem
from solver.design.information import InformationBlock, model_information, model_noise_std
from solver.measurement import (
    FixedPoints,
    KnownDistance,
    MeasurementModel,
    MeasurementRows,
    MultiMarker,
)
from solver.measurement.models import EyeOnHead, ModelParameters, PoseComponents, RelativeBase
from solver.model import KinematicChain, build_chain, gravity_loads
from tests.service.api.conftest import assert_problem
from tests.service.cli_support import run

SOCKETS = Path(__file__).resolve().parents[3] / "data/real/platonics_ball_socket/panda_right"
OFFSETS_M = [[0.05, 0.0, 0.02], [-0.03, 0.04, 0.03], [0.0, -0.05, 0.06]]
NOISE_M, NOISE_RAD = 5e-5, np.radians(0.003)  # the design defaults (0.05 mm, 0.003 deg)
N_CANDIDATES, K = 60, 12


@functools.cache
def chain_of(name: str) -> KinematicChain:
    robot = load_robot(name)
    return build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)


def _loads(chain: KinematicChain, q: np.ndarray) -> np.ndarray:
    options = CalibrationOptions()
    return gravity_loads(
        chain, q, gravity_base=np.array(options.gravity_base_m_s2), payload_kg=options.payload_kg
    )


def solver_block(
    chain: KinematicChain,
    model: MeasurementModel,
    params: ModelParameters,
    q: np.ndarray,
    group: np.ndarray | None = None,
) -> InformationBlock:
    return model_information(
        chain,
        params,
        model,
        q,
        _loads(chain, q),
        model_noise_std(model, NOISE_M, NOISE_RAD),
        options=pipeline.fit_options(CalibrationOptions()),
        group=group,
    )


def chain_standard_errors(block: InformationBlock, chosen: np.ndarray) -> np.ndarray:
    """σ of the chain parameters with the nuisance unknown: the chain block of the inverse of
    the full (p+e)² information of the chosen rows, in the parameters' units."""
    flat = block.factors[chosen].reshape(-1, block.columns)
    covariance = np.linalg.inv(block.prior + flat.T @ flat)
    p = block.dimension
    return np.sqrt(np.diag(covariance)[:p]) / block.scale[:p]


def design_cli(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    *args: object,
) -> dict[str, Any]:
    out = tmp_path / f"design{len(list(tmp_path.iterdir()))}.json"
    code, stdout, stderr = run(["design", *args, "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    document: dict[str, Any] = json.loads(out.read_text())
    assert f"measurement {document['options']['measurement']}: standard errors" in stdout
    return document


def check_design(document: dict[str, Any], block: InformationBlock, criterion: str = "D") -> None:
    """The design's criterion is the solver's on its chosen candidates, below the relaxation's
    certified bound; its standard errors are the profiled ones (1e-9)."""
    chosen = np.array([p["candidate"] for p in document["poses"]])
    c = document["criterion"]
    value = DesignProblem((block,), criterion, chosen.size).set_value(chosen)
    assert c["value"] == pytest.approx(value, rel=1e-9, abs=1e-12)
    assert c["value"] <= c["upper_bound"] + 1e-12
    assert [p["name"] for p in document["parameters"]] == list(block.names)
    se = np.array([p["standard_error"] for p in document["parameters"]])
    np.testing.assert_allclose(se, chain_standard_errors(block, chosen), rtol=1e-9)
    assert document["measurement"]["nuisance_parameters"] == list(block.nuisance_names)


MARKER_FLAGS = ["--marker-offsets", ",".join(str(v) for o in OFFSETS_M for v in o)]


@pytest.mark.parametrize(
    ("measurement", "extra", "model"),
    [
        ("components:tz,rx,ry", [], PoseComponents(("tz", "rx", "ry"))),
        ("markers", MARKER_FLAGS, MultiMarker(3)),
        ("relative-base", ["--min-spacing", "0.8"], RelativeBase()),
        (
            "eye-on-head:j2s6s200_joint_2",
            ["--cone", "0,0,0,0,0,1,60,0.1,1.0", "--criterion", "A"],
            EyeOnHead(sensor_joint=1),
        ),
    ],
    ids=["plane-contact", "markers", "relative-base", "eye-on-head"],
)
def test_cli_designs_each_measurement_type(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    measurement: str,
    extra: list[str],
    model: MeasurementModel,
) -> None:
    """``kincal design --measurement TYPE`` on sampled candidates (defaults for the plane
    contact and three markers; spacing, a view cone and criterion A for the base marker and
    the sensor on the chain): the criterion and standard errors are the solver's, the bound
    holds, the constraints hold, the markers' offsets are listed as profiled-out unknowns and
    make auto choose the first-order method."""
    document = design_cli(
        tmp_path,
        capsys,
        monkeypatch,
        *("--robot", "kinova", "--measurement", measurement, *extra),
        *("--n-candidates", N_CANDIDATES, "--poses", K),
    )
    chain = chain_of("kinova")
    options = DesignOptions.model_validate(document["options"])
    q = sample_candidates(chain, N_CANDIDATES, np.random.default_rng(0), volume_of(options))
    chosen = np.array([p["candidate"] for p in document["poses"]])
    np.testing.assert_array_equal([p["joint_positions"] for p in document["poses"]], q[chosen])
    if options.min_spacing_rad:
        gaps = np.linalg.norm(q[chosen, None] - q[None, chosen], axis=2)
        assert gaps[np.triu_indices(K, 1)].min() >= options.min_spacing_rad
    if options.cone is not None:
        assert volume_of(options).contains(tip_poses(chain, q)).all()
    nominal = ModelParameters.nominal(chain)
    offsets = np.ravel(OFFSETS_M) if isinstance(model, MultiMarker) else np.zeros(0)
    params = ModelParameters(nominal.links, nominal.compliance_rad_per_nm, offsets)
    block = solver_block(chain, model, params, q)
    check_design(document, block, options.criterion)
    report = document["measurement"]
    assert report["type"] == measurement
    assert report["components"] == list(model.components)
    if isinstance(model, MultiMarker):
        assert block.nuisance == 9 and report["nuisance_parameters"][0] == "marker_1.x"
        # auto: the first-order method where Clarabel would need the nuisance LMI
        assert document["criterion"]["method"] == "first_order"
    else:
        assert report["nuisance_parameters"] == []
        assert document["criterion"]["method"] == "clarabel"


def socket_slice(folder: Path, rows: int = 20) -> Path:
    """The first ``rows`` configurations of each socket of the real platonics Panda folder."""
    for source in sorted(SOCKETS.glob("*/hole_?.csv")):
        target = folder / source.parent.name / source.name
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text("".join(source.read_text().splitlines(keepends=True)[:rows]))
    return folder


def test_ball_in_socket_design_beats_random_subsets(
    client: TestClient,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``--measurement point --candidates FOLDER --point-distance 0.05`` on a slice of a real
    platonics Panda recording (2 sockets × 20 configurations): which 16 to measure. The
    designed set's criterion is the solver's (sockets profiled out, the known distance as a
    prior) and beats the median of 200 random 16-subsets of the same candidates. The same
    candidates as a CSV with a socket column, and over HTTP with candidate_sockets, are
    designed alike."""
    folder = socket_slice(tmp_path / "panda")
    point = ("--robot", "panda", "--measurement", "point", "--poses", 16)
    args = (*point, "--point-distance", "0.05", "--candidates", folder)
    document = design_cli(tmp_path, capsys, monkeypatch, *args)
    assert document["candidates"] == 40 and document["candidate_source"] == "given"
    report = document["measurement"]
    assert report["sockets"] == ["world_frame/hole_0", "world_frame/hole_1"]
    assert report["known_distances"] == 1
    chain = chain_of("panda")
    q = np.concatenate([np.loadtxt(f, delimiter=",") for f in sorted(folder.glob("*/hole_?.csv"))])
    group = np.repeat([0, 1], 20)
    points = FixedPoints(2, (KnownDistance(0, 1, 0.05),))
    params = points.start(chain, MeasurementRows.of(q, _loads(chain, q), None, group))
    block = solver_block(chain, points, params, q, group)
    assert block.nuisance == 6 and block.prior.any()
    check_design(document, block)
    problem = DesignProblem((block,), "D", 16)
    rng = np.random.default_rng(0)
    randoms = [problem.set_value(rng.choice(40, 16, replace=False)) for _ in range(200)]
    assert document["criterion"]["value"] > np.median(randoms)
    # the same candidates as a CSV with a socket column (no known distance) are designed too
    table = pd.DataFrame(q, columns=chain.joint_names).assign(socket=group)
    table.to_csv(tmp_path / "sockets.csv", index=False)
    csv = design_cli(
        tmp_path, capsys, monkeypatch, *point, "--candidates", tmp_path / "sockets.csv"
    )
    assert csv["measurement"]["sockets"] == ["socket 0", "socket 1"]
    check_design(csv, solver_block(chain, FixedPoints(2), params, q, group))
    # and over HTTP: candidates_rad with the socket of each
    body = {
        "robot": "panda",
        "options": {"n_poses": 16, "measurement": "point"},
        "candidates_rad": q.tolist(),
        "candidate_sockets": group.tolist(),
    }
    response = client.post("/api/v1/designs", json=body)
    assert response.status_code == 200, response.text
    http = response.json()
    assert [p["candidate"] for p in http["poses"]] == [p["candidate"] for p in csv["poses"]]
    assert http["parameters"] == csv["parameters"]
    assert http["measurement"]["nuisance_parameters"] == [
        f"point_{g}.{a}" for g in (0, 1) for a in "xyz"
    ]


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--robot", "panda", "--measurement", "point"], "--candidates"),
        (["--robot", "kinova", "--measurement", "markers"], "marker_offsets_m"),
        (["--robot", "kinova", "--measurement", "markers", "--marker-offsets", "0,0"], "3 numbers"),
        (["--robot", "kinova", "--measurement", "relative-base", "--stage", "both"], "geometry"),
        (["--robot", "kinova", "--measurement", "eye-on-head:nope"], "not a joint"),
        (["--robot", "kinova", "--measurement", "auto"], "one measurement type"),
        (["--robot", "kinova", "--point-distance", "0.05"], "point_distance_m"),
    ],
)
def test_cli_refuses_bad_measurement_designs(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    fragment: str,
) -> None:
    """Exit 2 and one line naming the option and the fix (sampled candidates cannot be
    measured in a socket)."""
    code, _, stderr = run(["design", *args, "-o", tmp_path / "d.json"], capsys, monkeypatch)
    assert code == 2, stderr
    assert fragment in stderr and "Traceback" not in stderr


def test_http_designs_markers_like_the_cli(
    client: TestClient,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``POST /api/v1/designs`` with ``measurement: markers`` answers the CLI's design: same
    poses, criterion and standard errors, the offsets listed as profiled-out unknowns."""
    chain = chain_of("kinova")
    q = sample_candidates(chain, 40, np.random.default_rng(4), Volume())
    options = {"n_poses": 10, "measurement": "markers", "marker_offsets_m": OFFSETS_M}
    response = client.post(
        "/api/v1/designs",
        json={"robot": "kinova", "options": options, "candidates_rad": q.tolist()},
    )
    assert response.status_code == 200, response.text
    document = response.json()
    pd.DataFrame(q, columns=chain.joint_names).to_csv(tmp_path / "c.csv", index=False)
    cli = design_cli(
        tmp_path,
        capsys,
        monkeypatch,
        *("--robot", "kinova", "--measurement", "markers", *MARKER_FLAGS),
        *("--candidates", tmp_path / "c.csv", "--poses", 10),
    )
    assert [p["candidate"] for p in document["poses"]] == [p["candidate"] for p in cli["poses"]]
    assert document["criterion"]["value"] == pytest.approx(cli["criterion"]["value"], rel=1e-9)
    assert document["parameters"] == cli["parameters"]
    nominal = ModelParameters.nominal(chain)
    params = ModelParameters(nominal.links, nominal.compliance_rad_per_nm, np.ravel(OFFSETS_M))
    check_design(document, solver_block(chain, MultiMarker(3), params, q))


@pytest.mark.parametrize(
    ("options", "extra", "field"),
    [
        ({"measurement": "point"}, {}, "candidates_rad"),
        ({"measurement": "point"}, {"candidates_rad": [[0.0] * 6]}, "candidate_sockets"),
        ({"measurement": "markers"}, {}, "marker_offsets_m"),
        ({"measurement": "components:tz,rx,ry", "stage": "covariance"}, {}, "stage"),
        ({"measurement": "components:tq"}, {}, "measurement"),
        ({"measurement": "eye-on-head:nope"}, {}, "eye-on-head:nope"),
        (
            {"measurement": "pose", "marker_offsets_m": OFFSETS_M},
            {},
            "marker_offsets_m",
        ),
    ],
)
def test_http_bad_measurement_designs_are_422(
    client: TestClient, options: dict[str, Any], extra: dict[str, Any], field: str
) -> None:
    body = {"robot": "kinova", "options": {"n_poses": 8, "n_candidates": 50, **options}, **extra}
    assert_problem(client.post("/api/v1/designs", json=body), 422, field)
