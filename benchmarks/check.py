"""``kincal check`` on the real recordings (issue 33): false alarms, and changes concealed at
the size the check states, flagged and located.

Per recording and draw: ``kincal calibrate`` (its defaults plus the flags the recording needs,
:data:`benchmarks.evaluate_real.RECORDINGS`) on a random 80 % of the rows, then the check of
up to 10 of the other rows through the use case ``kincal check`` calls, at its default level
(5 %): once as recorded (a "drifted" verdict is a false alarm) and once per concealed change at
the size that check states for those poses, along its worst direction — each joint's offset
(the joint stands that much further than its reading, sign at random), the robot base moved in
its own frame, the tool bumped in its frame (translation and rotation each). A concealed change
is flagged when the verdict is drifted and located when the best candidate is that joint or
frame. Also the wall time of ``kincal check`` of 10 poses as a whole process.

Usage: ``python -m benchmarks.check [--draws 200] [--recordings NAME,...] [--write-results]``
(``--write-results``: ``docs/results/check.{json,md}``, the table docs/check.md includes).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import io
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.evaluate_real import DATA, RECORDINGS, _resolve
from benchmarks.results import Row, markdown_table, percent, write_results
from schemas.calibration import CalibrationResult
from schemas.check import CheckResult
from schemas.dataset import PoseDataset, read_dataset, write_dataset
from service import cli
from service.app.check import check_arrays, run_check
from service.render import result_json
from solver import check as checks
from solver import lie

CHECKED = {
    "FR3": "FR3 eye-in-hand camera (philnad)",
    "UR10e": "UR10e (FIGAROH UR10 experiment)",
    "TALOS": "TALOS torso + left arm (FIGAROH)",
    "positioner": "2-axis positioner, DH table (industrial_calibration)",
}
"""The recordings of :data:`benchmarks.evaluate_real.RECORDINGS` the check takes in this
phase (pose and position recordings). The platonics ball-in-socket recordings (measurement
'point') are refused by the check for now."""

TRAIN_FRACTION = 0.8
CHECK_POSES = 10


def kincal_calibrate(
    recording: str, source: Path, output: Path, extra: tuple[str, ...] = ()
) -> CalibrationResult:
    """``kincal calibrate SOURCE`` with the recording's flags, the CLI defaults and ``extra``."""
    flags = [_resolve(f) for f in RECORDINGS[recording].flags.split()]
    argv = ["kincal", "calibrate", str(source), *flags, *extra, "-o", str(output)]
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        old, sys.argv = sys.argv, argv
        try:
            cli.main()
        except SystemExit as exc:
            if exc.code not in (0, None, 3) or not output.exists():
                raise RuntimeError(f"{recording}: calibrate exited {exc.code}") from exc
        finally:
            sys.argv = old
    return CalibrationResult.model_validate_json(output.read_bytes())


def calibrate(recording: str, train: PoseDataset, folder: Path) -> CalibrationResult:
    """``kincal calibrate`` of ``train`` with the recording's flags and the CLI defaults."""
    write_dataset(train, folder / "train.csv")
    return kincal_calibrate(recording, folder / "train.csv", folder / "calibration.json")


def conceal_joint(dataset: PoseDataset, joint: int, offset: float) -> PoseDataset:
    """The joint stands ``offset`` further than its reading: the reading is ``q − offset``."""
    readings = dataset.joint_positions.copy()
    readings[:, joint] -= offset
    return dataclasses.replace(dataset, joint_positions=readings)


def with_poses(dataset: PoseDataset, poses: np.ndarray) -> PoseDataset:
    quaternion = (
        None
        if dataset.quaternion_xyzw is None
        else (lie.matrix_to_quaternion_xyzw(poses[:, :3, :3]))
    )
    return dataclasses.replace(dataset, position_m=poses[:, :3, 3], quaternion_xyzw=quaternion)


def measured(dataset: PoseDataset) -> np.ndarray:
    quaternion = dataset.quaternion_xyzw
    if quaternion is None:
        quaternion = np.tile([0.0, 0.0, 0.0, 1.0], (dataset.n_samples, 1))
    return lie.pose_matrix(dataset.position_m, quaternion)


def conceal_frame(
    result: CalibrationResult, dataset: PoseDataset, kind: str, twist: np.ndarray
) -> PoseDataset:
    """The robot base moved by ``twist`` in its own frame (``T_mb ← T_mb Exp(δ)``, with
    ``T_mb = L_1 N_1⁻¹`` of the calibrated chain), or the tool bumped in its frame
    (``X ← X Exp(δ)``; a recording of positions has no measured tool orientation: there the
    tool frame is the calibrated model's at each pose, as the check's tool candidate takes it,
    and the bump moves the marker by ``R(q) δ_t``)."""
    poses = measured(dataset)
    if kind == "tool":
        if dataset.quaternion_xyzw is None:
            predicted = result_json.predict_poses(
                result, dataset.joint_positions, dataset.payload_kg
            )
            poses[:, :3, :3] = predicted[:, :3, :3]
        return with_poses(dataset, poses @ lie.se3_exp(twist))
    chain, params = result_json.result_chain(result)
    base = params.links[0] @ lie.inverse(chain.nominal_links[0])
    moved = base @ lie.se3_exp(twist) @ lie.inverse(base)
    return with_poses(dataset, moved @ poses)


def concealed_changes(
    result: CalibrationResult, dataset: PoseDataset, clean: CheckResult, rng: np.random.Generator
) -> list[tuple[str, str, PoseDataset]]:
    """(change, the candidate that should be located, the check recording with it) at the
    sizes the ``clean`` check of these poses states (worst direction, a random sign)."""
    arrays = check_arrays(result, dataset)
    stated = {s.name: s for s in clean.stated_sizes}
    white = checks.whitening(arrays.covariance)
    chain, _ = result_json.result_chain(result)
    out = []
    for j, name in enumerate(chain.joint_names):
        size = stated[f"{name} offset"].size
        if size is not None:
            sign = rng.choice([-1.0, 1.0])
            out.append((f"{name} offset", f"{name} offset", conceal_joint(dataset, j, sign * size)))
    for candidate in arrays.candidates:
        if candidate.kind not in ("base", "tool"):
            continue
        n, d, _ = candidate.jacobian.shape
        for part, axes in (("translation", slice(0, 3)), ("rotation", slice(3, 6))):
            size = stated[f"{candidate.kind} {part}"].size
            if size is None:
                continue
            columns = white @ candidate.jacobian[:, :, axes].reshape(n * d, 3)
            twist = np.zeros(6)
            twist[axes] = rng.choice([-1.0, 1.0]) * size * checks.worst_direction(columns)
            changed = conceal_frame(result, dataset, candidate.kind, twist)
            out.append((f"{candidate.kind} {part}", candidate.name, changed))
    return out


def draw_once(
    recording: str, dataset: PoseDataset, seed: int, folder: Path
) -> tuple[bool, dict[str, tuple[bool, bool, bool]]]:
    """One draw: (false alarm?, change -> (flagged?, located?, named?)); named: located or
    among the candidates the check poses cannot tell apart from the located one."""
    rng = np.random.default_rng(seed)
    order = rng.permutation(dataset.n_samples)
    n_train = int(np.ceil(TRAIN_FRACTION * dataset.n_samples))
    train = dataset.subset(np.sort(order[:n_train]))
    check_rows = dataset.subset(np.sort(order[n_train:][:CHECK_POSES]))
    result = calibrate(recording, train, folder)
    clean = run_check(result, check_rows)
    outcomes = {}
    for change, expected, changed in concealed_changes(result, check_rows, clean, rng):
        out = run_check(result, changed)
        named = [] if out.located is None else [out.located.name]
        named += [] if out.located is None else out.located.indistinguishable_from
        outcomes[change] = (out.verdict == "drifted", named[:1] == [expected], expected in named)
    return clean.verdict == "drifted", outcomes


def whole_process_seconds(recording: str, folder: Path, repeats: int = 5) -> float:
    """Median wall time of ``kincal check`` of 10 held-out poses as a separate process."""
    dataset = read_recording(recording)
    rng = np.random.default_rng(0)
    order = rng.permutation(dataset.n_samples)
    n_train = int(np.ceil(TRAIN_FRACTION * dataset.n_samples))
    calibrate(recording, dataset.subset(np.sort(order[:n_train])), folder)
    write_dataset(dataset.subset(np.sort(order[n_train:][:CHECK_POSES])), folder / "check.csv")
    kincal = Path(sys.executable).with_name("kincal")
    command = [str(kincal), "check", str(folder / "calibration.json"), str(folder / "check.csv")]
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        subprocess.run([*command, "-o", str(folder / "check.json")], capture_output=True)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def read_recording(recording: str) -> PoseDataset:
    """The whole recording, read for its chain (from a quick calibration of it: no held-out
    splits, no covariances)."""
    with tempfile.TemporaryDirectory() as folder:
        probe = kincal_calibrate(
            recording,
            DATA / RECORDINGS[recording].path,
            Path(folder) / "probe.json",
            ("--no-heldout", "--covariance", "none"),
        )
    chain, _ = result_json.result_chain(probe)
    return read_dataset(
        DATA / RECORDINGS[recording].path,
        chain.joint_names,
        other_joint_names=chain.other_joint_names,
    )


def check_count(n_rows: int) -> int:
    """Check poses of a draw: up to :data:`CHECK_POSES` of the rows not calibrated on."""
    return min(CHECK_POSES, n_rows - int(np.ceil(TRAIN_FRACTION * n_rows)))


def run(name: str, draws: int, *, timing: bool = True) -> Row:
    """The row of recording ``name`` (a key of :data:`CHECKED`) over ``draws`` draws."""
    recording = CHECKED[name]
    dataset = read_recording(recording)
    alarms = 0
    flagged: dict[str, int] = {}
    located: dict[str, int] = {}
    named: dict[str, int] = {}
    with tempfile.TemporaryDirectory() as folder:
        for seed in range(draws):
            alarm, outcomes = draw_once(recording, dataset, seed, Path(folder))
            alarms += alarm
            for change, (hit, right, among) in outcomes.items():
                flagged[change] = flagged.get(change, 0) + hit
                located[change] = located.get(change, 0) + right
                named[change] = named.get(change, 0) + among
        seconds = whole_process_seconds(recording, Path(folder)) if timing else None
    return {
        "recording": name,
        "rows": dataset.n_samples,
        "check_poses": check_count(dataset.n_samples),
        "draws": draws,
        "false_alarms": alarms,
        "changes": {
            c: {"flagged": flagged[c], "located": located[c], "named": named[c]} for c in flagged
        },
        "check_seconds": seconds,
    }


def render(rows: list[Row]) -> str:
    """Per recording: false alarms, and per change flagged / located shares."""
    header = (
        "Recording",
        "Check poses",
        "Draws",
        "False alarms",
        "Change at the stated size",
        "Flagged",
        "Located",
        "Located or not told apart",
        "10-pose check, whole process",
    )
    lines = []
    for row in rows:
        draws = row["draws"]
        first = True
        for change, counts in row["changes"].items():
            seconds = row["check_seconds"]
            lines.append(
                (
                    row["recording"] if first else "",
                    row["check_poses"] if first else "",
                    draws if first else "",
                    percent(row["false_alarms"] / draws, 1) if first else "",
                    change,
                    percent(counts["flagged"] / draws, 0),
                    percent(counts["located"] / draws, 0),
                    percent(counts["named"] / draws, 0),
                    (f"{seconds:.2f} s" if seconds is not None else "–") if first else "",
                )
            )
            first = False
    return markdown_table(header, lines)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--draws", type=int, default=200)
    parser.add_argument("--recordings", default=",".join(CHECKED))
    parser.add_argument("--write-results", action="store_true")
    args = parser.parse_args(argv)
    rows = []
    for name in args.recordings.split(","):
        started = time.perf_counter()
        rows.append(run(name, args.draws))
        print(f"{name}: {time.perf_counter() - started:.0f} s", file=sys.stderr)
    print(render(rows))
    if args.write_results:
        command = f"python -m benchmarks.check --draws {args.draws} --recordings {args.recordings}"
        for path in write_results("check", command, rows, render):
            print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    main()
