"""The HTML report: self-contained, escaped, with σ per frame exactly when covariances exist."""

from __future__ import annotations

import base64
import functools
import re

import numpy as np

from schemas.calibration import (
    CalibrationOptions,
    CalibrationResult,
    CovarianceFrame,
    CovarianceIdentifiability,
    CovarianceResult,
    SolverReport,
)
from service.app import calibrate as pipeline
from service.render.report_html import render_report
from service.render.result_json import dataset_residuals
from tests.conftest import robot
from tests.service.api.conftest import recording

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@functools.cache
def _result() -> CalibrationResult:
    return pipeline.calibrate(recording(), robot("ur10"), CalibrationOptions(heldout=False))


def _frame(name: str, index: int | None, std: list[float]) -> CovarianceFrame:
    return CovarianceFrame(
        name=name,
        joint_index=index,
        matrix=np.diag(np.square(std)).tolist(),
        std=tuple(std),  # type: ignore[arg-type]
    )


def _with_covariance(result: CalibrationResult) -> CalibrationResult:
    joints = result.robot.joint_names
    frames = [_frame(n, i, [0, 0, 0, 1e-3 * (i + 1), 5e-4, 2e-4]) for i, n in enumerate(joints)]
    covariance = CovarianceResult(
        structure="diag",
        estimator="moment matching",
        solver=SolverReport(
            name="clarabel", status="optimal", iterations=12, time_s=0.1, objective=1.0
        ),
        noise=_frame("noise", None, [3e-4, 3e-4, 3e-4, 3e-3, 3e-3, 3e-3]),
        frames=frames,
        identifiability=CovarianceIdentifiability(
            rank=30,
            n_parameters=42,
            condition_number=240.0,
            null_directions=[],
            fixed=["wrist_3_joint.tz (no lever arm)"],
            warnings=["noise and <last frame> are nearly indistinguishable"],
        ),
    )
    return result.model_copy(update={"covariance": covariance})


def _images(page: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r'src="data:image/png;base64,([^"]+)"', page)]


def test_report_embeds_residual_histograms_and_fit_table() -> None:
    result = _result().model_copy(update={"covariance": None})
    page = render_report(result, dataset_residuals(result, recording()))
    images = _images(page)
    assert len(images) == 1 and images[0].startswith(PNG_SIGNATURE)
    assert f"{result.fit.before.train.translation_mean_mm:.3f}" in page
    assert f"{result.fit.after.train.translation_mean_mm:.3f}" in page
    assert "did not run" in page  # covariance stage switched off
    for name in result.identifiability.removed:
        assert name in page
    assert "<script" not in page


def test_calibrate_fills_the_covariance_and_the_report_shows_it() -> None:
    result = _result()
    assert result.covariance is not None
    page = render_report(result, dataset_residuals(result, recording()))
    assert len(_images(page)) == 2 and "did not run" not in page


def test_sigma_per_frame_chart_appears_with_covariances() -> None:
    result = _with_covariance(_result())
    page = render_report(result, dataset_residuals(result, recording()))
    images = _images(page)
    assert len(images) == 2 and all(i.startswith(PNG_SIGNATURE) for i in images)
    assert "&lt;last frame&gt;" in page and "<last frame>" not in page
    assert "wrist_3_joint.tz" in page


def test_user_supplied_names_are_escaped() -> None:
    result = _result()
    robot_info = result.robot.model_copy(update={"name": "<script>alert(1)</script>"})
    renamed = result.model_copy(update={"robot": robot_info})
    page = render_report(renamed, dataset_residuals(result, recording()))
    assert "<script>" not in page and "&lt;script&gt;" in page
