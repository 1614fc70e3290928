"""The discovery HTML report on a findings document built by hand (no discovery run): what
the measurement cannot see (issue 32), its effects left out with the reason and its terms
whose effect cancels in what is measured, shown (escaped) only when there are any."""

from __future__ import annotations

from schemas.calibration import DatasetInfo
from schemas.discovery import (
    DiscoveredModel,
    DiscoveryMeasurement,
    DiscoveryOptions,
    ErrorPair,
    FindingsResult,
    Health,
    HealthPair,
    Heldout,
    NotCandidate,
    OutlierScreen,
    RobotRef,
)
from service.render.discovery_html import render_discovery_report

JOINTS = ["panda_joint1", "panda_joint2", "panda_joint3"]
HEADING = "What this measurement cannot see"


def _health() -> Health:
    return Health(
        n_samples=40,
        n_parameters=30,
        sigma_translation_mm=0.1,
        sigma_rotation_deg=None,
        rms_translation_mm=0.12,
        rms_rotation_deg=None,
        chi2_per_dof=None,
        dependences=[],
    )


def findings_with(measurement: DiscoveryMeasurement | None) -> FindingsResult:
    """A findings document that names nothing, measured by ``measurement``."""
    pair = ErrorPair(trans_mm=0.2, rot_deg=None)
    return FindingsResult(
        kincal_version="test",
        created_utc="2024-01-01T00:00:00+00:00",
        dataset=DatasetInfo(source="eye.csv", n_samples=40, measures_rotation=False),
        robot=RobotRef(
            name="panda",
            base_frame="panda_link0",
            tip_frame="panda_link8",
            joint_names=JOINTS,
            urdf_sha256="0" * 64,
        ),
        options=DiscoveryOptions(detectability=False),
        findings=[],
        ambiguous=[],
        unexplained=[],
        random_effects=[],
        heldout=Heldout(before=pair, after=pair),
        health=HealthPair(before=_health(), after=_health()),
        steps=[],
        outliers=OutlierScreen(level=None, removed_rows=[]),
        model=DiscoveredModel(
            terms=[],
            calibrate_compliant_joints=[],
            calibrate_virtual_axes_at=[],
            calibrate_gravity_base_m_s2=(0.0, 0.0, -9.81),
            calibrate_payload_kg=0.0,
            not_carried=[],
        ),
        n_candidates=12,
        measurement=measurement,
        elapsed_s=1.0,
    )


def _measurement(**sections: object) -> DiscoveryMeasurement:
    return DiscoveryMeasurement.model_validate(
        {"type": "point", "frame": "socket frame", "components": ["x", "y", "z"], **sections}
    )


def test_report_lists_what_the_measurement_cannot_see_with_the_reasons() -> None:
    unseen = NotCandidate(
        effect="joint_compliance",
        joint="panda_joint2",
        variant="",
        description="joint_compliance on panda_joint2",
        remaining_fraction=3e-13,
        reason="its effect cancels: a sensor riding on the body after <panda_joint2> moves with it",
    )
    measurement = _measurement(
        left_out=["depth_scale: a ball in a socket has no depth axis & no camera"],
        not_candidates=[unseen.model_dump()],
    )
    page = render_discovery_report(findings_with(measurement), {})
    assert HEADING in page
    assert "<code>depth_scale</code>" in page
    assert "a ball in a socket has no depth axis &amp; no camera" in page  # escaped
    assert "<code>joint_compliance on panda_joint2</code>" in page
    assert "after &lt;panda_joint2&gt; moves with it" in page  # escaped
    assert "3e-13" in page
    assert "<panda_joint2>" not in page


def test_report_shows_one_list_without_the_other() -> None:
    page = render_discovery_report(
        findings_with(_measurement(left_out=["depth_scale: not along a camera's axis"])), {}
    )
    assert HEADING in page and "Not candidates" not in page
    assert "not along a camera&#x27;s axis" in page


def test_report_says_nothing_of_it_when_the_measurement_sees_every_term() -> None:
    for measurement in (None, _measurement()):
        page = render_discovery_report(findings_with(measurement), {})
        assert HEADING not in page and "Not candidates" not in page
        assert "Smallest detectable effects" in page
