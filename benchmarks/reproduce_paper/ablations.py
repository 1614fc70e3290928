"""Where the gap to the oracle comes from: the first recording's candidates re-scored with other
covariance models."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

from benchmarks.reproduce_paper.manipulation import RecordingStudy
from benchmarks.reproduce_paper.selection import Comparison
from benchmarks.reproduce_paper.settings import StudySettings
from benchmarks.reproduce_paper.simulation import calibration_options, simulate_study_recording
from service.app import calibrate as pipeline
from service.app import rank as service_ranking
from solver.ranking import UncertaintyModel


@dataclasses.dataclass(frozen=True)
class Ablation:
    """The first recording's candidates re-scored with another covariance model in place of
    ours; ``comparison`` as in :func:`compare` (its "ours" is this model) with the paper's W,
    ``docking`` with the docking task's own score."""

    label: str
    comparison: Comparison
    docking: Comparison


def ablation_models(
    settings: StudySettings, first: RecordingStudy, *, echo: Callable[[str], None] = print
) -> dict[str, UncertaintyModel]:
    """Covariance models to compare with ours on the first recording's candidates.

    The paper's estimator (moment matching solved by PGD, Eq. 14–15) on the same data; the
    product's estimator with rotational perturbations only (``covariance_axes='rotation'``) on
    the same data and on larger recordings of the same true robot; and the true Σ on the
    calibrated geometry (what a perfect covariance calibration would give). The product's
    estimator told Σ_n is the known-noise variant (:class:`KnownNoise`).
    """
    recording = first.recording
    options = calibration_options(recording, settings, heldout=False)
    models: dict[str, UncertaintyModel] = {}
    if settings.paper_estimator_ablation:
        paper = options.model_copy(
            update={"covariance_estimator": "moment", "covariance_solver": "pgd"}
        )
        models[f"paper estimator (moment matching + PGD), N = {settings.n_samples}"] = (
            service_ranking.uncertainty_model(
                pipeline.calibrate(recording.dataset, recording.robot, paper)
            )
        )
        echo("  ablation: paper estimator")
    rotation = options.model_copy(update={"covariance_axes": "rotation"})
    label = "ours, rotational perturbations only (`--covariance-axes rotation`)"
    models[f"{label}, N = {settings.n_samples}"] = service_ranking.uncertainty_model(
        pipeline.calibrate(recording.dataset, recording.robot, rotation)
    )
    echo("  ablation: rotational perturbations only")
    for n in settings.ablation_samples:
        larger = simulate_study_recording(
            dataclasses.replace(settings, n_samples=n), recording.seed
        )
        calibrated = pipeline.calibrate(larger.dataset, larger.robot, options)
        models[f"ours, N = {n} samples of the same robot"] = service_ranking.uncertainty_model(
            calibrated
        )
        echo(f"  ablation: N = {n}")
    ours = first.scorers.ours
    models["true Σ on the calibrated geometry"] = UncertaintyModel.build(
        ours.chain, ours.params, recording.true_robot.effects(), ours.gravity_base
    )
    return models
