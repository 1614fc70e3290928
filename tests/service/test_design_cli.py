"""``kincal design`` through the CLI: the user's path with its defaults.

Acceptance (issue 16): simulated Jaco2, Panda and UR10e, candidates inside a sensor's working
volume; designed poses against random poses from the same volume, scored by the parameter part
of the predicted pose variance over held-out configurations in that volume and by the worst
identifiable parameter's standard error (each times its root-mean-square effect on a
measurement, so that m, rad and rad/N·m compare).
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
import pytest

from schemas.robots import load_robot
from solver.design.candidates import Volume, WorkspaceBox, sample_candidates, tip_poses
from solver.design.criteria import DesignProblem
from solver.design.prediction import Yardstick, task_root
from solver.design.relaxation import solve_first_order
from solver.kinematics import ChainParameters
from solver.model import KinematicChain, build_chain, gravity_loads
from tests.service.cli_support import run

UR10E = Path(__file__).resolve().parents[2] / "data/real/figaroh_ur10_experiment/ur10e_robot.urdf"
ROBOTS = {
    "kinova": ["--robot", "kinova"],
    "panda": ["--robot", "panda"],
    "ur10e": ["--urdf", UR10E, "--base", "base_link", "--tip", "tool0"],
}
NOISE = np.r_[[5e-5] * 3, [np.radians(0.003)] * 3]  # the CLI's defaults
SEEDS = range(10)
CANDIDATES = 600


@functools.cache
def robot_chain(name: str) -> KinematicChain:
    robot = (
        load_robot("ur10e", urdf_path=UR10E, base_frame="base_link", tip_frame="tool0")
        if name == "ur10e"
        else load_robot(name)
    )
    return build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)


@functools.cache
def working_box(name: str) -> tuple[float, ...]:
    """The middle 40 % of the reachable tip positions along each base axis."""
    chain = robot_chain(name)
    tips = tip_poses(chain, sample_candidates(chain, 4000, np.random.default_rng(0)))[:, :3, 3]
    return (*np.percentile(tips, 30, axis=0), *np.percentile(tips, 70, axis=0))


def design_cli(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    *args: object,
) -> dict:  # type: ignore[type-arg]
    out = tmp_path / f"design{len(list(tmp_path.iterdir()))}.json"
    code, stdout, stderr = run(["design", *args, "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    assert "efficiency" in stdout
    return json.loads(out.read_text())  # type: ignore[no-any-return]


@functools.cache
def volume_runs(name: str, tmp: Path) -> list[dict[str, float]]:
    """Per seed, as ratios to 50 random poses from the box (one yardstick: held-out
    configurations in the box): 25 designed poses (``kincal design`` defaults), 25 random
    poses, and the relaxation bound of criterion I (repeats allowed) on the design's own
    candidates — below it no 25 of those candidates can go."""
    chain = robot_chain(name)
    box = working_box(name)
    volume = Volume(box=WorkspaceBox(np.array(box[:3]), np.array(box[3:])))
    params = ChainParameters.nominal(chain)
    runs = []
    with pytest.MonkeyPatch.context() as monkeypatch:
        for seed in SEEDS:
            out = tmp / f"{name}-{seed}.json"
            monkeypatch.setattr(
                "sys.argv",
                [
                    "kincal", "design", *map(str, ROBOTS[name]),
                    "--box", ",".join(map(str, box)),
                    "--n-candidates", str(CANDIDATES), "--seed", str(seed), "-o", str(out),
                ],
            )  # fmt: skip
            from service import cli

            try:
                cli.main()
            except SystemExit as exc:
                assert exc.code in (0, None)
            document = json.loads(out.read_text())
            designed = np.array([p["joint_positions"] for p in document["poses"]])
            # The CLI's candidates: drawn in the box from its seed.
            candidates = sample_candidates(chain, CANDIDATES, np.random.default_rng(seed), volume)
            index = [p["candidate"] for p in document["poses"]]
            np.testing.assert_allclose(candidates[index], designed)
            rng = np.random.default_rng([seed, 7])
            heldout = sample_candidates(chain, 300, rng, volume)
            random50 = sample_candidates(chain, 50, rng, volume)
            yardstick = Yardstick.on(chain, params, heldout, gravity_loads(chain, heldout), NOISE)

            def score(q: np.ndarray, ys: Yardstick = yardstick) -> tuple[float, float]:
                return ys.score(q, gravity_loads(chain, q))

            reference = score(random50)
            problem = DesignProblem(
                (yardstick.block(candidates, gravity_loads(chain, candidates)),),
                "I",
                25,
                task_root=task_root(yardstick.task),
                distinct=False,
            )
            bound = -solve_first_order(problem, gap_tolerance=1e-4).upper_bound
            runs.append(
                {"bound": bound / reference[0], "efficiency": document["criterion"]["efficiency"]}
            )
            for key, q in (("designed", designed), ("random25", random50[:25])):
                variance, sigma = score(q)
                runs[-1][f"{key}_variance"] = variance / reference[0]
                runs[-1][f"{key}_sigma"] = sigma / reference[1]
    return runs


def _median(runs: list[dict[str, float]], key: str) -> float:
    return float(np.median([run[key] for run in runs]))


@pytest.mark.parametrize("name", list(ROBOTS))
def test_designed_poses_against_random_poses_in_a_working_volume(
    name: str, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """25 designed poses (kincal design, default D) against random poses from the box (median
    over 10 seeds of ratios to 50 random poses). Holds: lower predicted pose variance and
    worst standard error than 25 random poses, and the relaxation certifies the design within
    10 % of optimal. Issue 16's bar (≤ 50 random poses): if missed, the test proves it out of
    reach — the I relaxation (the lowest variance any 25 of the candidates can give, repeats
    allowed) must itself be above 50 random poses — and records an expected failure; a bar
    within reach but missed fails."""
    runs = volume_runs(name, tmp_path_factory.mktemp(name))
    assert _median(runs, "designed_variance") < 0.85 * _median(runs, "random25_variance")
    assert _median(runs, "designed_sigma") < _median(runs, "random25_sigma")
    assert min(run["efficiency"] for run in runs) > 0.9
    assert all(run["designed_variance"] >= run["bound"] * (1 - 1e-9) for run in runs)
    ratio, se_ratio = _median(runs, "designed_variance"), _median(runs, "designed_sigma")
    if ratio <= 1.0 and se_ratio <= 1.0:
        return
    bound = _median(runs, "bound")
    assert bound > 1.0, f"bar within reach (bound {bound:.2f}×) but missed ({ratio:.2f}×)"
    pytest.xfail(
        f"25 designed / 50 random: variance {ratio:.2f}×, worst σ {se_ratio:.2f}×; no 25 of "
        f"these candidates can go below {bound:.2f}× (I relaxation), so issue 16's bar (≤ 1) "
        "is out of reach in this volume (docs/design.md)"
    )


def test_clarabel_and_first_order_agree_through_the_cli(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    common = ["--robot", "kinova", "--poses", "8", "--n-candidates", "60", "--seed", "4"]
    clarabel = design_cli(tmp_path, capsys, monkeypatch, *common, "--method", "clarabel")
    first = design_cli(tmp_path, capsys, monkeypatch, *common, "--method", "first_order")
    for document in (clarabel, first):
        c = document["criterion"]
        assert c["value"] <= c["upper_bound"] + 1e-12
        assert len(document["poses"]) == 8
    assert clarabel["criterion"]["relaxation_value"] == pytest.approx(
        first["criterion"]["relaxation_value"], abs=1e-4
    )
    assert clarabel["criterion"]["method"] == "clarabel"
    assert first["criterion"]["method"] == "first_order"


def test_cone_spacing_and_positions(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A camera's view cone, a facing constraint, a minimum spacing, a 3-D sensor."""
    document = design_cli(
        tmp_path, capsys, monkeypatch,
        "--robot", "kinova", "--poses", "10", "--n-candidates", "300",
        "--cone", "1.2,0,0.4,-1,0,0,30,0.4,2.5,70", "--min-spacing", "0.5",
        "--measurement", "position", "--poses-csv", tmp_path / "poses.csv",
    )  # fmt: skip
    q = np.array([p["joint_positions"] for p in document["poses"]])
    distances = np.linalg.norm(q[:, None] - q[None], axis=2)
    assert np.all(distances[~np.eye(10, dtype=bool)] >= 0.5)
    apex = np.array([1.2, 0.0, 0.4])
    for pose in document["poses"]:
        sight = np.array(pose["tip_position_m"]) - apex
        assert sight @ np.array([-1.0, 0, 0]) >= np.cos(np.radians(30)) * np.linalg.norm(sight)
    assert not any(
        p["name"].endswith(".rx") and p["name"].startswith("j2s6s200_end")
        for p in document["parameters"]
    )
    assert (tmp_path / "poses.csv").read_text().startswith("j2s6s200_joint_1")


def test_small_tracker_box_at_the_edge_of_the_reach(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A 25 cm tracker box at the reach's edge keeps ~0.3 % of random configurations: the
    CLI's defaults still fill it (candidates and task), every chosen tip inside it."""
    from benchmarks.design import sensor_volumes

    box = sensor_volumes(robot_chain("kinova"))["tracker box"]["box"]
    low, high = np.array(box["low_m"]), np.array(box["high_m"])  # type: ignore[index]
    document = design_cli(
        tmp_path, capsys, monkeypatch,
        "--robot", "kinova", "--poses", "25", "--n-candidates", "600",
        "--box", ",".join(map(str, [*low, *high])), "--measurement", "position",
    )  # fmt: skip
    tips = np.array([p["tip_position_m"] for p in document["poses"]])
    assert len(tips) == 25 and np.all((tips >= low) & (tips <= high))
    assert document["task_configurations"] == 500


def test_covariance_and_combined_designs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Designs for the covariance stage identify what all candidates identify (no more sums
    than the candidates force), and do so better than random poses of the same number."""
    common = ["--robot", "kinova", "--poses", "12", "--n-candidates", "300"]
    covariance = design_cli(tmp_path, capsys, monkeypatch, *common, "--stage", "covariance")
    both = design_cli(tmp_path, capsys, monkeypatch, *common, "--stage", "both")
    for document in (covariance, both):
        report = document["covariance"]
        assert report["rank"] == report["candidate_rank"]
        assert document["criterion"]["value"] <= document["criterion"]["upper_bound"] + 1e-12
    geometry = design_cli(tmp_path, capsys, monkeypatch, *common)
    assert both["worst_relative_standard_error"] < 1.5 * geometry["worst_relative_standard_error"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--poses", "0"], "--poses"),
        (["--criterion", "F"], "--criterion"),
        (["--box", "1,1,1,0,0,0"], "--box"),
        (["--box", "1,2"], "--box"),
        (["--cone", "0,0,0,0,0,0,30,0.1,1"], "--cone"),
        (["--stage", "both", "--criterion", "A"], "stage 'both'"),
        (["--poses", "50", "--n-candidates", "20"], "n_poses"),
        (["--box", "5,5,5,6,6,6", "--n-candidates", "10"], "working volume"),
        (["--result", "r.json"], "--recording"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(
    args: list[str],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    code, _, stderr = run(
        ["design", "--robot", "kinova", *args, "-o", tmp_path / "d.json"], capsys, monkeypatch
    )
    assert code == 2
    assert message in stderr
    assert "Traceback" not in stderr
