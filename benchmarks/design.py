"""Calibration designs (issue 16) on simulated Jaco2, Panda and UR10e, candidates in a working box.

For K poses, on one candidate set per seed, it compares: K random poses from the volume,
kincal's designs (``kincal design`` defaults: D; and I for the volume), FIGAROH 1.0.2's posture
selection on the same candidates (its SOCP weights' K largest, and its Detmax exchange for K),
against 50 random poses. Every design is scored by one yardstick
(:class:`solver.design.prediction.Yardstick`): the parameter part of the predicted pose variance
(mean over held-out configurations in the volume) and the worst identifiable parameter's
standard error, both as ratios to 50 random poses (median over seeds); and by the held-out
position error of a simulated calibration (kincal defaults, truth perturbed per seed).

``bound`` rows: the relaxation of criterion I with repeats allowed (w ≤ 1) on the same
candidates — no K poses from them can have a lower variance (the argument of docs/design.md).

FIGAROH runs only if a separate interpreter with figaroh is given (``--figaroh-python``); it is
never a kincal dependency (``benchmarks/figaroh_posture_driver.py`` runs under it). Usage::

    python -m benchmarks.design [--seeds 10] [--poses 15,25,50] [--candidates 600]
        [--figaroh-python PATH] [--skip-timing | --timing-only] [--write-results]
    python -m benchmarks.design --volumes [--seeds 10] [--candidates 600] [--write-results]

``--volumes``: issue 16's bar (25 designed poses ≤ 50 random) in small sensor volumes at the
edge of the reach (:func:`sensor_volumes`: a 25 cm tracker box, a camera's view cone), full pose
and position-only, the calibration's default parameters.

``--write-results`` writes the tables docs/design.md includes, each with the command that
produced it: ``docs/results/design_poses.{json,md}`` (against random poses), or
``design_figaroh`` when FIGAROH ran, ``design_volumes`` (``--volumes``) and ``design_timing``
(the timing line: ``kincal design`` on 10⁴ candidates).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from benchmarks.results import Row, count_text, dash, markdown_table, write_results
from schemas.calibration import CalibrationOptions
from schemas.dataset import PoseDataset
from schemas.design import DesignOptions
from schemas.robots import RobotDescription, load_robot
from service.app import calibrate as pipeline
from service.app.design import run_design, volume_of
from service.render.result_json import predict_poses
from solver import lie
from solver.arrays import FloatArray
from solver.design.candidates import Volume, WorkspaceBox, sample_candidates, tip_poses
from solver.design.criteria import DesignProblem
from solver.design.prediction import Yardstick, task_root
from solver.design.relaxation import solve_first_order
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain, build_chain, gravity_loads
from solver.simulate import SimulationSpec, true_parameters

UR10E = Path(__file__).resolve().parents[1] / "data/real/figaroh_ur10_experiment/ur10e_robot.urdf"
DRIVER = Path(__file__).resolve().with_name("figaroh_posture_driver.py")
NOISE = np.r_[[5e-5] * 3, [np.radians(0.003)] * 3]  # kincal design's defaults (m, rad)
REFERENCE_POSES = 50


def robots() -> dict[str, RobotDescription]:
    return {
        "jaco2": load_robot("kinova"),
        "panda": load_robot("panda"),
        "ur10e": load_robot("ur10e", urdf_path=UR10E, base_frame="base_link", tip_frame="tool0"),
    }


def robot_chain(robot: RobotDescription) -> KinematicChain:
    return build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)


def working_box(chain: KinematicChain) -> tuple[FloatArray, FloatArray]:
    """The middle 40 % of the reachable tip positions along each base axis."""
    tips = tip_poses(chain, sample_candidates(chain, 4000, np.random.default_rng(0)))[:, :3, 3]
    return np.percentile(tips, 30, axis=0), np.percentile(tips, 70, axis=0)


def heldout_error_mm(
    robot: RobotDescription, q: FloatArray, heldout: FloatArray, seed: int
) -> float:
    """Simulate the true robot at q (noise as NOISE), calibrate with kincal's defaults (no
    covariance), return the mean translation error (mm) at ``heldout`` against the truth."""
    options = CalibrationOptions(covariance="none", heldout=False)
    chain = pipeline.check_calibration(robot, options).chain
    rng = np.random.default_rng(seed)
    params, _ = true_parameters(chain, SimulationSpec(n_samples=1, seed=seed), rng)
    truth = forward_kinematics(chain, params, q, gravity_loads(chain, q))
    measured = truth @ lie.se3_exp(rng.normal(size=(q.shape[0], 6)) * NOISE)
    dataset = PoseDataset(
        chain.joint_names, q, measured[:, :3, 3], lie.matrix_to_quaternion_xyzw(measured[:, :3, :3])
    )
    result = pipeline.calibrate(dataset, robot, options)
    predicted = predict_poses(result, heldout, None)
    expected = forward_kinematics(chain, params, heldout, gravity_loads(chain, heldout))
    return float(1e3 * np.mean(np.linalg.norm(predicted[:, :3, 3] - expected[:, :3, 3], axis=1)))


def figaroh_urdf(robot: RobotDescription, chain: KinematicChain) -> bytes:
    """The robot's URDF for FIGAROH: no meshes (none are shipped), and the chain's continuous
    joints made revolute within kincal's limits (FIGAROH's candidate loader writes one angle
    per joint into q, where Pinocchio's continuous joints take cos and sin). Same kinematics."""
    root = ET.fromstring(robot.urdf_xml)
    for link in root.findall("link"):
        for tag in ("visual", "collision"):
            for element in link.findall(tag):
                link.remove(element)
    for joint in root.findall("joint"):  # not the transmissions' joint references
        name = joint.get("name", "")
        if joint.get("type") != "continuous" or name not in chain.joint_names:
            continue
        i = chain.joint_names.index(name)
        joint.set("type", "revolute")
        limit = joint.find("limit")
        if limit is None:
            limit = ET.SubElement(joint, "limit", effort="1", velocity="1")
        limit.set("lower", repr(float(chain.lower_limits[i])))
        limit.set("upper", repr(float(chain.upper_limits[i])))
    return ET.tostring(root)


def figaroh_designs(
    python: str,
    robot: RobotDescription,
    chain: KinematicChain,
    candidates: FloatArray,
    poses: list[int],
    seed: int,
) -> dict:  # type: ignore[type-arg]
    """FIGAROH's posture selection on ``candidates`` through its own interpreter."""
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        (work / "robot.urdf").write_bytes(figaroh_urdf(robot, chain))
        # FIGAROH's candidate format (YAML; JSON is YAML).
        (work / "candidates.yaml").write_text(
            json.dumps(
                {
                    "calibration_joint_names": list(chain.joint_names),
                    "calibration_joint_configurations": candidates.tolist(),
                }
            )
        )
        request = {
            "urdf": str(work / "robot.urdf"),
            "base_frame": robot.base_frame,
            "tool_frame": robot.tip_frame,
            "candidates_yaml": str(work / "candidates.yaml"),
            "poses": poses,
            "seed": seed,
            "work_dir": str(work),
        }
        (work / "request.json").write_text(json.dumps(request))
        done = subprocess.run(
            [python, str(DRIVER), str(work / "request.json"), str(work / "answer.json")],
            capture_output=True, text=True, check=False, cwd=work,
        )  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(f"FIGAROH driver failed:\n{done.stderr[-4000:]}")
        answer: dict = json.loads((work / "answer.json").read_text())  # type: ignore[type-arg]
    return answer


@dataclass(frozen=True)
class Settings:
    seeds: int = 10
    poses: tuple[int, ...] = (15, 25, 50)
    candidates: int = 1000
    heldout: int = 300
    figaroh_python: str | None = None
    calibrate: bool = True


Values = tuple[float, float, float, float]
"""Per design: variance ratio, worst σ ratio (to 50 random poses), held-out mm, efficiency."""


def compare_robot(
    name: str, robot: RobotDescription, settings: Settings
) -> dict[tuple[int, str], list[Values]]:
    """Per (K, method): per seed (variance ratio, worst σ ratio to 50 random, held-out mm, the
    design's efficiency against its relaxation bound for kincal's designs)."""
    chain = robot_chain(robot)
    rows: dict[tuple[int, str], list[Values]] = defaultdict(list)
    for seed in range(settings.seeds):
        for key, values in compare_seed(robot, chain, settings, seed).items():
            rows[key].append(values)
    return rows


def compare_seed(
    robot: RobotDescription,
    chain: KinematicChain,
    settings: Settings,
    seed: int,
    methods: tuple[str, ...] = ("random", "kincal-D", "kincal-I", "bound"),
) -> dict[tuple[int, str], Values]:
    """:func:`compare_robot` for one seed; ``methods`` picks what to compute (a subset gives
    the same values: every draw is made whatever is computed)."""
    params = ChainParameters.nominal(chain)
    low, high = working_box(chain)
    volume = Volume(box=WorkspaceBox(low, high))
    box = {"low_m": tuple(low), "high_m": tuple(high)}
    rows: dict[tuple[int, str], Values] = {}
    rng = np.random.default_rng([seed, 7])
    heldout = sample_candidates(chain, settings.heldout, rng, volume)
    random_q = sample_candidates(chain, max(*settings.poses, REFERENCE_POSES), rng, volume)
    candidates = sample_candidates(chain, settings.candidates, rng, volume)
    loads = gravity_loads(chain, candidates)
    yardstick = Yardstick.on(chain, params, heldout, gravity_loads(chain, heldout), NOISE)
    reference = yardstick.score(
        random_q[:REFERENCE_POSES], gravity_loads(chain, random_q[:REFERENCE_POSES])
    )
    block = yardstick.block(candidates, loads)
    figaroh = (
        None
        if settings.figaroh_python is None
        else figaroh_designs(
            settings.figaroh_python, robot, chain, candidates, list(settings.poses), seed
        )
    )
    for k in settings.poses:
        designs: dict[str, FloatArray] = {}
        if "random" in methods:
            designs["random"] = random_q[:k]
        efficiency: dict[str, float] = {}
        for criterion in ("D", "I"):
            if f"kincal-{criterion}" not in methods:
                continue
            options = DesignOptions(
                n_poses=k, seed=seed, box=box, criterion=criterion,
                calibration=CalibrationOptions(covariance="none"),
            )  # fmt: skip
            document = run_design(robot, options, candidates=candidates)
            designs[f"kincal-{criterion}"] = candidates[[p.candidate for p in document.poses]]
            efficiency[f"kincal-{criterion}"] = document.criterion.efficiency
        if figaroh is not None:
            designs["figaroh-socp"] = candidates[figaroh["ranking"][:k]]
            designs["figaroh-detmax"] = candidates[figaroh["detmax"][str(k)]]
        for method, q in designs.items():
            variance, worst = yardstick.score(q, gravity_loads(chain, q))
            error = heldout_error_mm(robot, q, heldout, seed) if settings.calibrate else np.nan
            rows[(k, method)] = (
                variance / reference[0],
                worst / reference[1],
                error,
                efficiency.get(method, np.nan),
            )
        if "bound" in methods:
            relaxation = solve_first_order(
                DesignProblem(
                    (block,), "I", k, task_root=task_root(yardstick.task), distinct=False
                ),
                gap_tolerance=1e-6,
            )
            rows[(k, "bound")] = (-relaxation.upper_bound / reference[0], np.nan, np.nan, np.nan)
    if settings.calibrate and "random" in methods and REFERENCE_POSES not in settings.poses:
        q50 = random_q[:REFERENCE_POSES]
        rows[(REFERENCE_POSES, "random")] = (
            1.0, 1.0, heldout_error_mm(robot, q50, heldout, seed), np.nan,
        )  # fmt: skip
    if figaroh is not None:
        selection = candidates[figaroh["threshold_selection"]]
        rows[(len(figaroh["threshold_selection"]), "figaroh-threshold")] = (
            *_ratios(yardstick, chain, selection, reference), np.nan, np.nan,
        )  # fmt: skip
    return rows


def _ratios(
    yardstick: Yardstick, chain: KinematicChain, q: FloatArray, reference: tuple[float, float]
) -> tuple[float, float]:
    variance, worst = yardstick.score(q, gravity_loads(chain, q))
    return variance / reference[0], worst / reference[1]


def compare(
    settings: Settings, names: list[str] | None = None, echo: Callable[[str], None] = print
) -> tuple[list[str], list[Row]]:
    """The table of :func:`compare_robot` (medians over seeds) for every robot; printed line by
    line with ``echo``, and returned with its results rows (:func:`pose_rows`)."""
    lines = [
        "robot    K  method             variance/50rnd  worst-σ/50rnd  held-out mm  efficiency  "
        f"(median, {settings.seeds} seeds, {settings.candidates} candidates)"
    ]
    echo(lines[0])
    results: list[Row] = []
    for name, robot in robots().items():
        if names is not None and name not in names:
            continue
        rows = compare_robot(name, robot, settings)
        results += pose_rows(name, rows)
        for (k, method), values in sorted(rows.items(), key=lambda item: item[0]):
            v, s, e, f = (_median(column) for column in np.array(values).T)
            lines.append(
                f"{name:7} {k:3d}  {method:17}  {v:13.3f}  {s:13.3f}  {e:11.4f}  {f:10.4f}"
            )
            echo(lines[-1])
    return lines, results


def _median(values: FloatArray) -> float:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else float("nan")


TRACKER_SIDE_M = 0.25
"""Side of the tracker's measurement box (a cube)."""


def sensor_volumes(chain: KinematicChain) -> dict[str, dict[str, object]]:
    """Small sensor volumes at the edge of the reach, fixed before measuring anything in them:
    centre c = (0.8 R, 0, z_m), R the 95th percentile of the tip's horizontal distance from
    the base z axis and z_m the median tip height over 4000 random configurations;

    - ``tracker box``: a 25 cm cube centred at c;
    - ``camera cone``: a camera 1 m beyond c on +x looking along −x, half-angle 7°, depth
      0.85–1.15 m (about 25 cm across at c).

    Returned as :class:`DesignOptions` fields (``box`` / ``cone``)."""
    tips = tip_poses(chain, sample_candidates(chain, 4000, np.random.default_rng(0)))[:, :3, 3]
    reach = float(np.percentile(np.hypot(tips[:, 0], tips[:, 1]), 95))
    centre = np.array([0.8 * reach, 0.0, float(np.median(tips[:, 2]))])
    half = TRACKER_SIDE_M / 2
    return {
        "tracker box": {"box": {"low_m": tuple(centre - half), "high_m": tuple(centre + half)}},
        "camera cone": {
            "cone": {
                "apex_m": tuple(centre + np.array([1.0, 0.0, 0.0])),
                "axis": (-1.0, 0.0, 0.0),
                "half_angle_deg": 7.0,
                "near_m": 0.85,
                "far_m": 1.15,
            }
        },
    }


VOLUME_COLUMNS = (
    "bound", "random25", "random25-σ", "D", "D-σ", "D-eff", "I", "I-σ", "I-eff", "p",
)  # fmt: skip


def compare_volume(
    robot: RobotDescription,
    volume_fields: dict[str, object],
    measurement: str,
    settings: Settings,
    k: int = 25,
    seeds: Sequence[int] | None = None,
) -> list[dict[str, float]]:
    """Per seed, in one sensor volume with full-pose or position-only measurements and the
    calibration's default parameters (geometry + compliance): the I relaxation bound (repeats
    allowed), 25 random poses and kincal's D and I designs of 25 poses, as ratios to 50 random
    poses from the volume (variance; worst σ), scored on held-out configurations in it.
    ``seeds``: these seeds only (default ``range(settings.seeds)``)."""
    chain = robot_chain(robot)
    params = ChainParameters.nominal(chain)
    noise = NOISE if measurement == "pose" else NOISE[:3]
    runs = []
    for seed in range(settings.seeds) if seeds is None else seeds:
        options = DesignOptions(
            n_poses=k,
            seed=seed,
            measurement=measurement,
            **volume_fields,  # type: ignore[arg-type]
        )
        volume = volume_of(options)
        rng = np.random.default_rng([seed, 7])
        heldout = sample_candidates(chain, settings.heldout, rng, volume)
        random_q = sample_candidates(chain, REFERENCE_POSES, rng, volume)
        candidates = sample_candidates(chain, settings.candidates, rng, volume)
        yardstick = Yardstick.on(chain, params, heldout, gravity_loads(chain, heldout), noise)
        reference = yardstick.score(random_q, gravity_loads(chain, random_q))
        problem = DesignProblem(
            (yardstick.block(candidates, gravity_loads(chain, candidates)),),
            "I",
            k,
            task_root=task_root(yardstick.task),
            distinct=False,
        )
        bound = -solve_first_order(problem, gap_tolerance=1e-6).upper_bound
        run = {"bound": bound / reference[0], "p": float(yardstick.reference.dimension)}
        run["random25"], run["random25-σ"] = _ratios(yardstick, chain, random_q[:k], reference)
        for criterion in ("D", "I"):
            document = run_design(
                robot, options.model_copy(update={"criterion": criterion}), candidates=candidates
            )
            q = candidates[[p.candidate for p in document.poses]]
            run[criterion], run[f"{criterion}-σ"] = _ratios(yardstick, chain, q, reference)
            run[f"{criterion}-eff"] = document.criterion.efficiency
        runs.append(run)
    return runs


def compare_volumes(
    settings: Settings, names: list[str] | None = None, echo: Callable[[str], None] = print
) -> tuple[list[str], list[Row]]:
    """The table of :func:`compare_volume` (medians over seeds) for every robot, volume of
    :func:`sensor_volumes` and measurement; printed line by line with ``echo``, and returned
    with its results rows (:func:`volume_rows`)."""
    lines = [
        f"robot    volume       measured  {'  '.join(f'{c:>10}' for c in VOLUME_COLUMNS)}  "
        f"(median, {settings.seeds} seeds, {settings.candidates} candidates, K = 25, ratios "
        "to 50 random poses)"
    ]
    echo(lines[0])
    results: list[Row] = []
    for name, robot in robots().items():
        if names is not None and name not in names:
            continue
        for volume, fields in sensor_volumes(robot_chain(robot)).items():
            for measurement in ("pose", "position"):
                runs = compare_volume(robot, fields, measurement, settings)
                results.append(volume_rows(name, volume, measurement, runs))
                medians = [float(np.median([r[c] for r in runs])) for c in VOLUME_COLUMNS]
                lines.append(
                    f"{name:7}  {volume:11}  {measurement:8}  "
                    + "  ".join(f"{m:10.3f}" for m in medians)
                )
                echo(lines[-1])
    return lines, results


@dataclass(frozen=True)
class Timing:
    candidates: int
    poses: int
    total_s: float
    relaxation_s: float
    iterations: int
    efficiency: float

    def line(self) -> str:
        return (
            f"D-optimal, {self.candidates} candidates, K={self.poses}: {self.total_s:.1f} s "
            f"total (relaxation {self.relaxation_s:.1f} s, {self.iterations} iterations, "
            f"efficiency {self.efficiency:.3f})"
        )


def timing(n_candidates: int = 10_000, n_poses: int = 30) -> Timing:
    """``kincal design --robot kinova`` (D) on ``n_candidates`` sampled candidates, timed."""
    robot = load_robot("kinova")
    started = time.perf_counter()
    out = run_design(robot, DesignOptions(n_poses=n_poses, n_candidates=n_candidates))
    return Timing(
        n_candidates,
        n_poses,
        time.perf_counter() - started,
        out.criterion.elapsed_s,
        out.criterion.iterations,
        out.criterion.efficiency,
    )


ROBOT_TITLES = {"jaco2": "Jaco2", "panda": "Panda", "ur10e": "UR10e"}
METRICS = ("variance", "worst_sigma", "heldout_mm", "efficiency")
"""The fields of :data:`Values`, as the results files name them."""


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def pose_rows(name: str, rows: dict[tuple[int, str], list[Values]]) -> list[Row]:
    """Results rows of :func:`compare_robot`: per (K, method) each seed's values (``None`` where
    there is none: a random design's efficiency, a bound's σ) and their medians."""
    out = []
    for (k, method), values in sorted(rows.items()):
        columns = np.array(values, dtype=float).T
        out.append(
            {
                "robot": name,
                "poses": k,
                "method": method,
                "seeds": len(values),
                "median": {m: _finite(_median(c)) for m, c in zip(METRICS, columns, strict=True)},
                "per_seed": {
                    m: [_finite(v) for v in c] for m, c in zip(METRICS, columns, strict=True)
                },
            }
        )
    return out


def _cell(row: Row | None, fields: Sequence[str]) -> str:
    """The medians of ``fields`` of one design, "1.70 / 1.03 / 0.035 / 0.987"."""
    if row is None:
        return "–"
    digits = {"variance": 2, "worst_sigma": 2, "heldout_mm": 3, "efficiency": 3}
    return " / ".join(dash(row["median"][f], digits[f]) for f in fields)


def _by_key(rows: Sequence[Row]) -> dict[tuple[str, int, str], Row]:
    return {(r["robot"], r["poses"], r["method"]): r for r in rows}


def _pose_table(rows: Sequence[Row], columns: Sequence[tuple[str, str, tuple[str, ...]]]) -> str:
    keyed = _by_key(rows)
    cells = []
    for robot in dict.fromkeys(r["robot"] for r in rows):
        sizes = sorted({r["poses"] for r in rows if (r["robot"], r["method"]) == (robot, "bound")})
        for k in sizes:
            designs = (_cell(keyed.get((robot, k, m)), fields) for _, m, fields in columns)
            cells.append((ROBOT_TITLES.get(robot, robot), k, *designs))
    return markdown_table(("robot", "K", *(title for title, _, _ in columns)), cells)


def render_poses(rows: list[Row]) -> str:
    """The table of ``docs/results/design_poses.md``: per robot and number of poses K the
    medians over seeds of random poses and of kincal's D and I designs — variance and worst σ
    as ratios to 50 random poses (to 0.01), the held-out position error of a simulated
    calibration (mm, to 0.001), the design's efficiency (to 0.001) — and the I relaxation's
    bound on the variance."""
    return _pose_table(
        rows,
        (
            ("random: var / σ / mm", "random", ("variance", "worst_sigma", "heldout_mm")),
            ("kincal D: var / σ / mm / eff", "kincal-D", METRICS),
            ("kincal I: var / σ / mm / eff", "kincal-I", METRICS),
            ("bound (var)", "bound", ("variance",)),
        ),
    )


def render_figaroh(rows: list[Row]) -> str:
    """The table of ``docs/results/design_figaroh.md``: per robot and K the medians over seeds
    of variance / worst σ (ratios to 50 random poses, to 0.01) of random poses, kincal's D
    design, FIGAROH's SOCP weights' K largest and its Detmax, and the I relaxation's bound."""
    pair = ("variance", "worst_sigma")
    return _pose_table(
        rows,
        (
            ("random", "random", pair),
            ("kincal D", "kincal-D", pair),
            ("FIGAROH SOCP, K largest", "figaroh-socp", pair),
            ("FIGAROH Detmax", "figaroh-detmax", pair),
            ("bound (var)", "bound", ("variance",)),
        ),
    )


def volume_rows(name: str, volume: str, measurement: str, runs: list[dict[str, float]]) -> Row:
    """A results row of :func:`compare_volume`: each seed's values and their medians."""
    return {
        "robot": name,
        "volume": volume,
        "measurement": measurement,
        "seeds": len(runs),
        "median": {c: float(np.median([r[c] for r in runs])) for c in VOLUME_COLUMNS},
        "runs": runs,
    }


def render_volumes(rows: list[Row]) -> str:
    """The table of ``docs/results/design_volumes.md``: per robot, sensor volume and
    measurement the identifiable parameters p and the medians over seeds of 25 random poses,
    kincal's D and I designs of 25 poses (variance / worst σ as ratios to 50 random poses, to
    0.01; efficiency to 0.001) and the I relaxation's bound on the variance."""
    cells = []
    for r in rows:
        m = r["median"]
        cells.append(
            (
                ROBOT_TITLES.get(r["robot"], r["robot"]),
                r["volume"],
                r["measurement"],
                f"{m['p']:.0f}",
                f"{m['random25']:.2f} / {m['random25-σ']:.2f}",
                f"{m['D']:.2f} / {m['D-σ']:.2f}",
                f"{m['D-eff']:.3f}",
                f"{m['I']:.2f} / {m['I-σ']:.2f}",
                f"{m['I-eff']:.3f}",
                f"{m['bound']:.2f}",
            )
        )
    header = (
        "robot", "volume", "measured", "p", "25 random", "D", "D eff", "I", "I eff",
        "bound (var)",
    )  # fmt: skip
    return markdown_table(header, cells)


def render_timing(rows: list[Row]) -> str:
    """The table of ``docs/results/design_timing.md``: wall time of the whole design and of the
    relaxation (to 0.1 s), the first-order iterations and the efficiency (to 0.001)."""
    return markdown_table(
        ("candidates", "poses K", "total s", "relaxation s", "iterations", "efficiency"),
        [
            (
                count_text(r["candidates"]),
                r["poses"],
                f"{r['total_s']:.1f}",
                f"{r['relaxation_s']:.1f}",
                r["iterations"],
                f"{r['efficiency']:.3f}",
            )
            for r in rows
        ],
    )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--poses", default="15,25,50")
    parser.add_argument("--candidates", type=int, default=1000)
    parser.add_argument("--robots", default=None, help="comma-separated: jaco2,panda,ur10e")
    parser.add_argument("--figaroh-python", default=None)
    parser.add_argument("--no-calibrate", action="store_true", help="skip held-out errors")
    parser.add_argument("--skip-timing", action="store_true")
    parser.add_argument("--timing-only", action="store_true", help="only the timing line")
    parser.add_argument(
        "--volumes",
        action="store_true",
        help="instead: issue 16's bar in small sensor volumes at the reach's edge",
    )
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/design_{poses,figaroh,volumes,timing}.{json,md}: the tables "
        "of this run (poses without FIGAROH, figaroh with it, volumes with --volumes, timing)",
    )
    args = parser.parse_args(argv)
    settings = Settings(
        seeds=args.seeds,
        poses=tuple(int(v) for v in args.poses.split(",")),
        candidates=args.candidates,
        figaroh_python=args.figaroh_python,
        calibrate=not args.no_calibrate,
    )
    names = None if args.robots is None else args.robots.split(",")
    command = " ".join(["python -m benchmarks.design", *(argv or sys.argv[1:])])
    written: list[Path] = []
    if args.volumes:
        lines, volume_results = compare_volumes(settings, names)
        print("\n".join(lines), flush=True)
        if args.write_results:
            written += write_results("design_volumes", command, volume_results, render_volumes)
    elif not args.timing_only:
        lines, results = compare(settings, names)
        print("\n".join(lines), flush=True)
        if args.write_results:
            name, render = ("design_poses", render_poses)
            if settings.figaroh_python is not None:
                name, render = ("design_figaroh", render_figaroh)
            written += write_results(name, command, results, render)
    if not args.volumes and (args.timing_only or not args.skip_timing):
        measured = timing()
        print(measured.line())
        if args.write_results:
            written += write_results("design_timing", command, [asdict(measured)], render_timing)
    for path in written:
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
