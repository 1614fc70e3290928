"""``make demo``: a paper-like Jaco2 study end to end on the embedded defaults.

Simulates 154 camera measurements of a Kinova Jaco2 with geometric errors, elastic joints, a
flexing base plate, random joint perturbations and outliers (paper §V-A), writes them in the
dataset contract, reads them back like a user file, calibrates, and compares with the truth.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from schemas.calibration import CalibrationOptions
from schemas.dataset import read_dataset, write_dataset
from service import pipeline, scenarios
from service.plots import residual_histograms
from service.report import summary
from service.robots import load_robot
from service.urdf_export import export_urdf
from solver.calibration import pose_errors


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
    write_dataset(scenarios.recording_dataset(recording, scn.chain, position_only=False), data_path)
    truth = scenarios.truth_document(scn, recording, robot)
    (output_dir / "truth.json").write_text(json.dumps(truth, indent=1), encoding="utf-8")
    echo(f"simulated {scn.spec.n_samples} Jaco2 camera measurements -> {data_path}")
    echo("effects: " + "; ".join(scenarios.EFFECTS[e] for e in scn.effects))

    first_joint = scn.chain.joint_names[0]
    options = CalibrationOptions(virtual_axes_at=[first_joint])
    chain = pipeline.chain_for(robot, options)
    dataset = read_dataset(data_path, chain.joint_names)
    result = pipeline.calibrate(dataset, robot, options)
    (output_dir / "result.json").write_text(result.model_dump_json(indent=1), encoding="utf-8")
    (output_dir / "jaco2_calibrated.urdf").write_text(export_urdf(result), encoding="utf-8")
    kept = dataset.subset(
        np.setdiff1d(np.arange(dataset.n_samples), np.array(result.outliers.removed_rows) - 1)
    )
    residual_histograms(
        pipeline.residuals(result, kept, baseline=True),
        pipeline.residuals(result, kept),
        output_dir / "residuals.png",
        title=f"Simulated Jaco2: end-effector-frame residuals of the {kept.n_samples} samples "
        f"kept after outlier removal, nominal robot vs calibrated",
    )
    echo("")
    echo(summary(result))

    flagged = set(result.outliers.removed_rows)
    injected = set(truth["outlier_rows"])
    echo("")
    echo(
        f"outliers: {len(injected & flagged)} of {len(injected)} injected outliers removed, "
        f"{len(flagged - injected)} clean samples removed by the 2-sigma rule"
    )
    echo("compliance, calibrated vs true (rad/Nm):")
    for entry in result.compliance:
        true_value = truth["compliance_rad_per_nm"].get(entry.axis, 0.0)
        shown = f"{entry.value_rad_per_nm: .2e}" if entry.estimated else "  (not identifiable)"
        echo(f"  {entry.axis:<28} {shown}   true {true_value: .2e}")
    clean = np.setdiff1d(np.arange(scn.spec.n_samples), recording.outliers)
    predicted = pipeline.predict_poses(result, recording.joint_positions[clean])
    error_mm, error_deg = pose_errors(
        predicted, recording.true_mean_pose[clean], position_only=False
    )
    assert error_deg is not None
    echo(
        f"calibrated model vs the true robot's mean pose: {error_mm.mean():.3f} mm, "
        f"{error_deg.mean():.4f} deg (what is left is random perturbation + noise)"
    )
    echo(f"\nfiles in {output_dir}: {', '.join(sorted(p.name for p in output_dir.iterdir()))}")
    assert result.fit.after.heldout is not None and result.fit.before.heldout is not None
    return {
        "heldout_before_mm": result.fit.before.heldout.translation_mean_mm,
        "heldout_after_mm": result.fit.after.heldout.translation_mean_mm,
        "model_vs_truth_mm": float(error_mm.mean()),
    }
