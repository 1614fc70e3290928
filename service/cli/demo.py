"""``make demo``: a paper-like Jaco2 study end to end, through the HTTP service.

Simulates 154 camera measurements of a Kinova Jaco2 with geometric errors, elastic joints, a
flexing base plate, random joint perturbations and outliers (paper §V-A) and writes them in the
dataset contract. Then, like a lab tool would: starts the service on the embedded defaults
(SQLite and data under ``<output>/service``, one worker process, 127.0.0.1, no network
services), uploads the recording over HTTP with :class:`service.api.client.KincalClient`, runs a
calibration job printing its progress, fetches the result, URDF and HTML report, ranks candidate
configurations by their calibrated uncertainty, and compares everything with the truth.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import uvicorn

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dataset import PoseDataset, read_dataset, write_dataset
from schemas.ranking import RankingResult
from schemas.robots import load_robot
from service.api.app import create_app
from service.api.client import KincalClient
from service.app import simulate as scenarios
from service.render import result_json
from service.render.plots import residual_histograms
from service.render.text import summary, verdict_line
from service.settings import Settings
from solver.calibration import pose_errors
from solver.model import sample_configurations
from solver.simulate import SimulatedRecording

N_CANDIDATES = 20
SHOWN = 5


@contextlib.contextmanager
def embedded_service(data_dir: Path) -> Iterator[str]:
    """The HTTP service on the embedded defaults, in a background thread of this process (its
    jobs in one worker process); yields its base URL. Logs go to ``data_dir/service.log``."""
    data_dir.mkdir(parents=True, exist_ok=True)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = int(probe.getsockname()[1])
    settings = Settings(
        host="127.0.0.1",
        port=port,
        data_dir=data_dir,
        database_url=f"sqlite:///{data_dir / 'kincal.db'}",
        workers=1,
        instance_name="kincal-demo",
        log_format="text",
        log_level="WARNING",  # the worker process logs to the terminal: only what goes wrong
    )
    handler = logging.FileHandler(data_dir / "service.log", encoding="utf-8")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    level = root.level
    root.addHandler(handler)
    root.setLevel(logging.INFO)
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings),
            host="127.0.0.1",
            port=port,
            log_config=None,
            access_log=False,
            lifespan="on",
        )
    )
    thread = threading.Thread(target=server.run, name="kincal-demo-service", daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 60
        while not server.started:
            if not thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the service did not start; see {data_dir / 'service.log'}")
            time.sleep(0.05)
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=60)
        root.removeHandler(handler)
        root.setLevel(level)
        handler.close()


def _progress_printer(echo: Callable[[str], None]) -> Callable[[dict[str, Any]], None]:
    """One line per stage and per tenth of the way, not one per poll."""
    shown: set[tuple[str, int]] = set()

    def show(status: dict[str, Any]) -> None:
        step = (str(status["stage"]), int(10 * status["fraction"]))
        if step in shown:
            return
        shown.add(step)
        iteration = "" if status["iteration"] is None else f", step {status['iteration']}"
        echo(f"  [{status['fraction']:4.0%}] {status['state']}: {status['stage']}{iteration}")

    return show


def _print_ranking(
    ranking: RankingResult, candidates: list[list[float]], echo: Callable[[str], None]
) -> None:
    echo(
        f"ranked {ranking.n_configurations} candidate configurations over HTTP by the "
        "predicted task-relevant end-effector spread (Eq. 22-23, paper weights), best first:"
    )
    echo(f"  {'rank':>4} {'index':>5} {'score mm²':>10} {'σx mm':>7} {'σy mm':>7}  joints (rad)")
    entries = ranking.ranking
    for n, entry in enumerate(entries):
        if SHOWN <= n < len(entries) - 1:
            if n == SHOWN:
                echo("     ...")
            continue
        joints = " ".join(f"{v:+.2f}" for v in candidates[entry.index])
        echo(
            f"  {entry.rank:>4} {entry.index:>5} {entry.score * 1e6:>10.4f} "
            f"{entry.ee_std[0] * 1e3:>7.3f} {entry.ee_std[1] * 1e3:>7.3f}  {joints}"
        )
    echo(
        f"the best candidate's task uncertainty is {entries[0].score / entries[-1].score:.0%} "
        "of the worst's: a planner approaching with it expects a smaller positioning error"
    )


def run_demo(output_dir: Path, *, echo: Callable[[str], None] = print) -> dict[str, float]:
    """Run the demo, write its files into ``output_dir`` and return headline numbers."""
    output_dir.mkdir(parents=True, exist_ok=True)
    robot = load_robot("kinova")
    scn, recording = scenarios.simulate(
        robot,
        n_samples=154,
        seed=1,
        effects=scenarios.PAPER_EFFECTS,
        noise_translation_mm=0.3,
        noise_rotation_deg=0.2,
    )
    data_path = output_dir / "jaco2_recording.csv"
    write_dataset(scenarios.recording_dataset(recording, scn.chain, rotation=True), data_path)
    truth = scenarios.truth_document(scn, recording, robot)
    (output_dir / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    echo(f"simulated {scn.spec.n_samples} Jaco2 camera measurements -> {data_path}")
    echo("effects: " + "; ".join(scenarios.EFFECTS[e] for e in scn.effects))

    options = CalibrationOptions(virtual_axes_at=[scn.chain.joint_names[0]])
    with embedded_service(output_dir / "service") as url:
        echo(f"\nkincal service on {url} (SQLite and files in {output_dir / 'service'})")
        with KincalClient(url) as api:
            dataset = api.upload_dataset(data_path, robot="kinova")
            echo(f"uploaded {dataset['n_samples']} samples over HTTP: dataset {dataset['id']}")
            calibration = api.start_calibration(dataset["id"], options)
            echo(f"calibration job {calibration['id']}:")
            api.wait(calibration["id"], poll_s=0.1, on_progress=_progress_printer(echo))
            result = api.result(calibration["id"])
            urdf = api.urdf(calibration["id"])
            report = api.report(calibration["id"])
            ranking, candidates = _rank_candidates(api, calibration["id"], result)

    (output_dir / "result.json").write_text(result.model_dump_json(indent=1), encoding="utf-8")
    (output_dir / "jaco2_calibrated.urdf").write_text(urdf, encoding="utf-8")
    report_path = output_dir / "report.html"
    report_path.write_text(report, encoding="utf-8")
    (output_dir / "ranking.json").write_text(ranking.model_dump_json(indent=1), encoding="utf-8")
    frame = pd.DataFrame(candidates, columns=ranking.joint_names)  # `kincal rank` reads this
    frame.to_csv(output_dir / "candidates.csv", index=False, float_format="%.17g")
    chain = result_json.chain_for(robot, options)
    dataset_read = read_dataset(data_path, chain.joint_names)
    _residual_figure(result, dataset_read, output_dir / "residuals.png")

    echo("")
    echo(summary(result))
    echo("")
    model_vs_truth_mm = _compare_with_truth(result, truth, recording, scn.spec.n_samples, echo)
    echo("")
    _print_ranking(ranking, candidates, echo)
    echo(f"\nreport: {report_path.resolve()}")
    echo("wrote:")
    for path in sorted(p for p in output_dir.iterdir() if p.is_file()):
        echo(f"  {path}")
    echo(verdict_line(result.verdict))
    assert result.fit.after.heldout is not None and result.fit.before.heldout is not None
    return {
        "heldout_before_mm": result.fit.before.heldout.translation_mean_mm,
        "heldout_after_mm": result.fit.after.heldout.translation_mean_mm,
        "model_vs_truth_mm": model_vs_truth_mm,
        "best_score_m2": ranking.ranking[0].score,
        "worst_score_m2": ranking.ranking[-1].score,
    }


def _rank_candidates(
    api: KincalClient, calibration_id: str, result: CalibrationResult
) -> tuple[RankingResult, list[list[float]]]:
    """Rank random configurations within the joint limits over HTTP."""
    chain, _ = result_json.result_chain(result)
    q = sample_configurations(chain, N_CANDIDATES, np.random.default_rng(2), range_fraction=0.8)
    candidates = q.tolist()
    return api.rank(calibration_id, candidates), candidates


def _residual_figure(result: CalibrationResult, dataset: PoseDataset, path: Path) -> None:
    """Paper Fig. 4a for the samples kept after outlier removal (the report embeds it too)."""
    kept = dataset.subset(result.outliers.kept_indices())
    residual_histograms(
        result_json.residuals(result, kept, baseline=True),
        result_json.residuals(result, kept),
        path,
        title=f"Simulated Jaco2: end-effector-frame residuals of the {kept.n_samples} samples "
        f"kept after outlier removal, nominal robot vs calibrated",
    )


def _compare_with_truth(
    result: CalibrationResult,
    truth: dict[str, Any],
    recording: SimulatedRecording,
    n_samples: int,
    echo: Callable[[str], None],
) -> float:
    """Outliers found, compliance and the calibrated model against the truth; returns the mean
    translation error (mm) of the calibrated model against the true mean poses."""
    flagged = set(result.outliers.removed_rows)
    injected = set(truth["outlier_rows"])
    echo(
        f"outliers: {len(injected & flagged)} of {len(injected)} injected outliers removed, "
        f"{len(flagged - injected)} clean samples removed (outlier rule: "
        f"{result.outliers.rule})"
    )
    echo("compliance, calibrated vs true (rad/Nm):")
    for entry in result.compliance:
        true_value = truth["compliance_rad_per_nm"].get(entry.axis, 0.0)
        shown = (
            f"{entry.value_rad_per_nm: .2e}"
            if entry.estimated
            else "  (fixed at 0: not physical)"
            if entry.pruned
            else "  (not identifiable)"
        )
        echo(f"  {entry.axis:<28} {shown}   true {true_value: .2e}")
    clean = np.setdiff1d(np.arange(n_samples), recording.outliers)
    predicted = result_json.predict_poses(result, recording.joint_positions[clean])
    error_mm, error_deg = pose_errors(predicted, recording.true_mean_pose[clean], rotation=True)
    assert error_deg is not None
    echo(
        f"calibrated model vs the true robot's mean pose: {error_mm.mean():.3f} mm, "
        f"{error_deg.mean():.4f} deg (what is left is random perturbation + noise)"
    )
    return float(error_mm.mean())
