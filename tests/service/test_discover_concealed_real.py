"""Issue 14 acceptance through the user's path: ``kincal discover`` on the shipped FR3 and
UR10e recordings, unmodified (nothing named) and with one effect concealed by the mechanism
simulator (:mod:`solver.mechanisms`, no library formula) at twice the detectability the
unmodified recording's report states (named, right joint, size within 25 %)."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks import concealed_real
from schemas.discovery import DetectableSize, FindingsResult
from schemas.robots import example_robot_data_dir
from solver.discovery import DiscoveryOptions, DiscoveryResult, discover
from solver.mechanisms import (
    CameraWarmup,
    Concealment,
    DeadBand,
    ElasticJoint,
    EncoderWarmup,
    conceal,
)
from tests.conftest import computed_once
from tests.service.cli_support import discover_ok, write_recording

ROBOT_FLAGS: dict[str, list[object]] = {
    "fr3": ["--robot", "panda"],
    "ur10e": [
        "--urdf",
        concealed_real.DATA / "figaroh_ur10_experiment" / "ur10e_robot.urdf",
        "--base",
        "base_link",
        "--tip",
        "wrist_3_link",
    ],
}


SIZE_PARAMETER = {
    "backlash": "backlash_rad",
    "joint_compliance": "compliance_rad_per_nm",
    "joint_scale": "scale_error",
}


def _discover(path: Path, name: str, sizes: bool = True) -> FindingsResult:
    """``kincal discover`` with its defaults; ``sizes=False`` adds ``--no-detectability``
    (most of a run's time; the sizes change nothing discovery names:
    test_discovery_is_deterministic_given_a_seed)."""
    return discover_ok(path, [*ROBOT_FLAGS[name], *([] if sizes else ["--no-detectability"])])


def stated_size(result: FindingsResult, effect: str, variant: str, joint: str) -> DetectableSize:
    """The detectability ``result`` states for one term (effect, variant, joint)."""
    assert result.detectability is not None
    (size,) = [
        s
        for s in result.detectability.sizes
        if (s.effect, s.variant, s.joint) == (effect, variant, joint)
    ]
    return size


@pytest.fixture(scope="module")
def unmodified(tmp_path_factory: pytest.TempPathFactory) -> dict[str, FindingsResult]:
    """The shipped recordings as they are (rewritten in the CSV contract), discovered."""
    folder = tmp_path_factory.mktemp("real")
    out = {}
    for name in ROBOT_FLAGS:
        _, data, _ = concealed_real.recording(name)
        path = folder / f"{name}.csv"
        write_recording(path, data.joint_positions, data.measured_pose)
        out[name] = _discover(path, name)
    return out


def test_unmodified_real_recordings_name_nothing(unmodified: dict[str, FindingsResult]) -> None:
    for result in unmodified.values():
        assert result.findings == []
        assert result.detectability is not None


def test_no_term_is_driven_by_a_moment_the_geometry_makes_zero(
    unmodified: dict[str, FindingsResult],
) -> None:
    """The UR10e's upper arm has no gravity moment about its own length (5e-8 N·m of
    round-off against 222 N·m at the shoulder): its bending is not a candidate (a fit to that
    round-off named a bending of 7e4 rad/N·m), while the forearm's is."""
    detectability = unmodified["ur10e"].detectability
    assert detectability is not None
    bending = {s.joint for s in detectability.sizes if s.effect == "link_bending"}
    assert "shoulder_lift_joint" not in bending
    assert "elbow_joint" in bending


def test_no_bending_size_where_the_structure_would_tilt_beyond_first_order(
    unmodified: dict[str, FindingsResult],
) -> None:
    """Issue 32: the UR10e's wrist_2 carries a moment of a few N·m, so the bending the test
    would detect there was ~0.5 rad/N·m — a tilt near a radian at twice it, which the
    first-order term (tilt c·τ, τ where the structure stands unbent) is not: concealed there,
    discovery named a bending plus a gear error. No size is stated there, with the reason. On
    wrist_1 a bending about the weakest axis is detected at 0.03 rad/N·m, but the promise at
    twice the size holds about every axis only at 0.29 rad/N·m, beyond first order too. The
    FR3's bendings (at most 0.01 rad/N·m under moments of a few N·m) keep their sizes."""
    detectability = unmodified["ur10e"].detectability
    assert detectability is not None
    bending = {s.joint: s for s in detectability.sizes if s.effect == "link_bending"}
    for joint in ("wrist_1_joint", "wrist_2_joint"):
        assert bending[joint].smallest is None
        assert "beyond the first-order bending" in (bending[joint].reason or "")
    fr3 = unmodified["fr3"].detectability
    assert fr3 is not None
    assert all(s.smallest is not None for s in fr3.sizes if s.effect == "link_bending")


@pytest.mark.parametrize(
    ("name", "effect_name", "effect", "variant", "joint", "seed", "multiple"),
    [
        ("fr3", "backlash_direction", "backlash", "direction", "panda_joint4", 0, 2.0),
        ("ur10e", "backlash_load", "backlash", "load", "elbow_joint", 1, 2.0),
        ("ur10e", "backlash_direction", "backlash", "direction", "elbow_joint", 3, 2.0),
        # reported ambiguous (held-out ties with 0.97–0.99-correlated candidates) until the
        # stated size included the separation from the hardest rival
        ("fr3", "joint_compliance", "joint_compliance", "", "panda_joint3", 0, 2.0),
        ("fr3", "joint_scale", "joint_scale", "", "panda_joint7", 5, 2.0),
        # named as a gear error on the same joint at twice the third round's stated size
        # (5.8 mrad); the unmodified report now states 7.0 mrad (its final fit keeps one more
        # sample), and at twice that the backlash is named.
        ("fr3", "backlash_load", "backlash", "load", "panda_joint5", 0, 2.0),
        # "nothing larger went unseen": at four times, 28 mrad, nothing was named — the first
        # screen dropped all six samples on one side of the joint's load sign, so the term was
        # not testable on the samples kept, until samples that a candidate's model brings back
        # and that vouch for one another came back (solver.discovery.validation.corroborated)
        ("fr3", "backlash_load", "backlash", "load", "panda_joint5", 0, 4.0),
        # reported ambiguous with the geometry (97.0 % absorbed at the geometry the effect had
        # bent) until the absorbed share was judged at the fit that models it
        ("ur10e", "joint_scale", "joint_scale", "", "shoulder_lift_joint", 1, 2.0),
    ],
)
def test_effect_concealed_at_twice_the_stated_detectability_or_more_is_named(
    unmodified: dict[str, FindingsResult],
    tmp_path: Path,
    name: str,
    effect_name: str,
    effect: str,
    variant: str,
    joint: str,
    seed: int,
    multiple: float,
) -> None:
    stated = stated_size(unmodified[name], effect, variant, joint).smallest
    assert stated is not None and np.isfinite(stated)
    chain, data, frame = concealed_real.recording(name)
    index = chain.joint_names.index(joint)
    rng = np.random.default_rng(seed)
    mechanism, truth = concealed_real.concealment(name, effect_name, index, multiple * stated, rng)
    readings, poses = conceal(
        chain, data.joint_positions, data.measured_pose, data.clock()[0], frame, mechanism
    )
    path = tmp_path / f"{name}_{effect_name}.csv"
    write_recording(path, readings, poses)
    result = _discover(path, name, sizes=False)  # the sizes stated are the unmodified ones
    named = [
        f
        for f in result.findings
        if (f.effect, f.joint) == (effect, joint) and f.variant.startswith(variant)
    ]
    assert named, [(f.effect, f.joint, f.variant) for f in result.findings]
    size = named[0].parameters[SIZE_PARAMETER[effect]]
    assert abs(size) == pytest.approx(truth, rel=0.25)  # a scale error has either sign


def _issue_32_concealment(case: str) -> Concealment:
    """The effects issue 32 concealed in the FR3, each alone."""
    if case == "gear":  # the reading is q - 2.5 mrad * sin(2q + phase) on panda_joint3
        gear, _ = concealed_real.concealment("fr3", "gear_h2", 2, 2.5e-3, np.random.default_rng(0))
        return gear
    if case.startswith("spring"):  # c = 2e-4 rad/N*m (up to ~10 mrad), and a softer one
        compliance = {"spring": 2e-4, "spring_small": 1e-4}[case]
        return Concealment(joints=(ElasticJoint("panda_joint2", compliance),))
    assert case == "board_drift"  # the board creeps 6 mm along its z over the recording
    return Concealment(camera_warmup=CameraWarmup(np.r_[0.0, 0.0, 6e-3, 0.0, 0.0, 0.0]))


@pytest.mark.parametrize(
    ("case", "named"),
    [
        ("gear", {("gear_periodic", "panda_joint3", "h2")}),
        ("spring", {("joint_compliance", "panda_joint2", "")}),
        ("spring_small", {("joint_compliance", "panda_joint2", "")}),
        ("board_drift", {("thermal_drift", None, "measurement_frame:linear")}),
    ],
)
def test_one_concealed_effect_is_all_that_is_named(
    tmp_path: Path, case: str, named: set[tuple[str, str | None, str]]
) -> None:
    """Issue 32: with one effect concealed in the real FR3, discovery named it and also the
    arm's own background (a thermal drift after the gear; a gravity tilt and a panda_joint6
    drift after the spring; link bending after the board drift), which the unmodified
    recording does not name. A name must mean the same whether or not another effect was
    found first."""
    chain, data, frame = concealed_real.recording("fr3")
    readings, poses = conceal(
        chain,
        data.joint_positions,
        data.measured_pose,
        data.clock()[0],
        frame,
        _issue_32_concealment(case),
    )
    path = tmp_path / f"fr3_{case}.csv"
    write_recording(path, readings, poses, data.clock()[0])
    result = _discover(path, "fr3", sizes=False)
    assert {(f.effect, f.joint, f.variant) for f in result.findings} == named


# --- a ball in socket (issue 14: "nothing larger went unseen" on a measurement of its own) -----

PLATONICS = concealed_real.DATA / "platonics_ball_socket" / "panda_right"
POINT_FLAGS: list[object] = [
    "--robot",
    "panda",
    "--measurement",
    "point",
    "--point-distance",
    "0.05",
]


@pytest.fixture(scope="module")
def ball_in_socket(tmp_path_factory: pytest.TempPathFactory) -> FindingsResult:
    """The shipped platonics Panda folder (two sockets 50 mm apart), discovered as it is."""
    output = tmp_path_factory.mktemp("socket") / "unmodified.json"
    return discover_ok(PLATONICS, POINT_FLAGS, output)


def _socket_folder(folder: Path, readings: np.ndarray) -> Path:
    """A copy of the platonics folder whose joint files hold ``readings`` (hole_0's rows
    first, as kincal reads them)."""
    copy = folder / "panda_right"
    shutil.copytree(PLATONICS, copy)
    start = 0
    for joints in sorted((copy / "world_frame").glob("hole_[0-9].csv")):
        n = np.loadtxt(joints, delimiter=",", ndmin=2).shape[0]
        np.savetxt(joints, readings[start : start + n], delimiter=",", fmt="%.17g")
        start += n
    assert start == readings.shape[0]
    return copy


def _concealed_socket_folder(folder: Path, effect: str, joint: int, size: float, seed: int) -> Path:
    """:func:`_socket_folder` of the platonics readings with ``effect`` concealed on chain joint
    ``joint`` at ``size`` as the semi-real benchmark's seed ``seed`` conceals it."""
    chain, data, frame = concealed_real.recording("platonics")
    rng = np.random.default_rng([seed, len(effect)])
    mechanism, _ = concealed_real.concealment("platonics", effect, joint, size, rng)
    readings, _ = conceal(
        chain, data.joint_positions, data.measured_pose, data.clock()[0], frame, mechanism
    )
    return _socket_folder(folder, readings)


def test_a_load_backlash_whose_link_would_float_gets_no_size(
    ball_in_socket: FindingsResult, unmodified: dict[str, FindingsResult]
) -> None:
    """Issue 32: the platonics Panda's panda_joint7 carries under 0.02 N·m of gravity load, so
    the tests alone would detect a load backlash only at ~0.44 rad, and at twice that a link
    turned by half its dead band reverses its load on 10 % of the samples: the link floats
    there, and concealed at twice the size the backlash was named in none of 2 runs. No size
    is promised there, with the reason; the FR3's load backlashes (no sample reverses) keep
    theirs."""
    size = stated_size(ball_in_socket, "backlash", "load", "panda_joint7")
    assert size.smallest is None
    assert "beyond the load-sign backlash" in (size.reason or ""), size.reason
    fr3 = unmodified["fr3"].detectability
    assert fr3 is not None
    load = [s for s in fr3.sizes if (s.effect, s.variant) == ("backlash", "load")]
    assert load and all(s.smallest is not None for s in load), [(s.joint, s.reason) for s in load]


def test_load_backlash_on_three_samples_of_a_ball_in_socket_gets_no_size(
    ball_in_socket: FindingsResult, tmp_path: Path
) -> None:
    """A load backlash on panda_joint4 of the platonics Panda: only three of its 60 samples
    have a positive load there, so its effect rests on those three. Concealed at 2 mrad (twice
    the size the score test alone would detect) it lowers the held-out error from 0.234 to
    0.170 mm, but a paired test over samples confirms it only at p = 0.012, not at the
    search's family-wise level (issue 32). So no size is promised there, with the reason, and
    nothing else is named in its place."""
    assert ball_in_socket.findings == []  # the unmodified recording: nothing named
    size = stated_size(ball_in_socket, "backlash", "load", "panda_joint4")
    assert size.smallest is None
    assert "too few samples to be confirmed on held-out ones" in (size.reason or "")
    folder = _concealed_socket_folder(tmp_path, "backlash_load", 3, 2e-3, seed=1)
    result = discover_ok(folder, [*POINT_FLAGS, "--no-detectability"], tmp_path / "found.json")
    named = {(f.effect, f.joint, f.variant) for f in result.findings}
    assert named <= {("backlash", "panda_joint4", "load")}, named


def test_another_shape_of_a_doubted_joint_structure_is_ambiguous_not_named(
    ball_in_socket: FindingsResult, tmp_path: Path
) -> None:
    """Issue 32: the platonics Panda's own panda_joint3 structure is a spring that the
    recording alone reports ambiguous with a bending of the next link. With a gear error (3rd
    harmonic, 2.0 mrad: twice its stated size, the benchmark's seed 1) concealed on
    panda_joint2, the gear is named first; the panda_joint3 spring is then significant but not
    confirmed on held-out, and a 2nd-harmonic gear error of panda_joint3 — the same joint's
    structure in another shape — was named in its place. A doubted candidate of the best
    one's joint is its rival: that shape is named only where the held-out error prefers it,
    else both are reported ambiguous, as the unmodified recording reports its structure."""
    assert ball_in_socket.findings == []
    (own,) = ball_in_socket.ambiguous
    assert ("joint_compliance", "panda_joint3") in {(c.effect, c.joint) for c in own.candidates}
    folder = _concealed_socket_folder(tmp_path, "gear_h3", 1, 2.0052e-3, seed=1)
    flags = [*POINT_FLAGS, "--no-detectability", "--seed", "1"]
    result = discover_ok(folder, flags, tmp_path / "found.json")
    named = [(f.effect, f.joint, f.variant) for f in result.findings]
    assert named == [("gear_periodic", "panda_joint2", "h3")], named
    candidates = {(c.effect, c.joint) for a in result.ambiguous for c in a.candidates}
    assert ("joint_compliance", "panda_joint3") in candidates, result.ambiguous


# --- a spring the first-order term is not (issue 14: no size where it cannot hold) -----------


@pytest.fixture(scope="module")
def talos(tmp_path_factory: pytest.TempPathFactory) -> FindingsResult:
    """``kincal discover`` of the shipped TALOS recording with its defaults, once per test run
    however many xdist workers its tests land on (:func:`tests.conftest.computed_once`)."""
    recording = concealed_real.RECORDINGS["talos"]
    assert recording.urdf is not None
    urdf = example_robot_data_dir() / recording.urdf.removeprefix(concealed_real.ERD)
    flags: list[object] = ["--urdf", urdf, "--base", "base_link", "--tip", "gripper_left_base_link"]

    def run(folder: Path) -> FindingsResult:
        return discover_ok(concealed_real.DATA / recording.relative, flags, folder / "talos.json")

    return computed_once(tmp_path_factory, "discover-talos", run)


def test_a_wrist_spring_beyond_the_first_order_model_gets_no_size(talos: FindingsResult) -> None:
    """TALOS's wrist joints carry only the gripper: their gravity torque varies by 1–2 N·m, so
    the size the test would detect is a very soft spring (0.08–0.09 rad/N·m) whose own gravity
    stiffness (|∂τ/∂q| ≈ 1 N·m/rad) changes its deflection by 16–19 % at twice that size. A
    spring concealed there was never named at 1×, 2× or 4× (the first-order term is not the
    mechanism), so the report states no size there, with the reason (the FR3's and UR10e's
    springs, gain ≤ 0.042 at twice their size, keep theirs: the tests above)."""
    assert talos.detectability is not None
    springs = {s.joint: s for s in talos.detectability.sizes if s.effect == "joint_compliance"}
    for joint in ("arm_left_6_joint", "arm_left_7_joint"):
        assert springs[joint].smallest is None, springs[joint]
        assert "beyond the first-order spring" in (springs[joint].reason or "")


def test_a_gear_harmonic_whose_joint_would_be_reported_unexplained_gets_no_size(
    talos: FindingsResult,
) -> None:
    """Issue 32: TALOS's arm_left_4 already carries angle structure the library's family
    barely covers (discovery's lack-of-fit test there: p = 0.006 unmodified). A third gear
    harmonic concealed at twice its stated 22 mrad was named in three runs of five and reported
    unexplained — the joint's structure beyond the library — in the other two. A size is now
    stated only where that test, on the model refit with the effect at twice the size in the
    readings, does not reject at discovery's level: none there, with the reason."""
    gear = stated_size(talos, "gear_periodic", "h3", "arm_left_4_joint")
    assert gear.smallest is None
    assert "would be reported beyond the library" in (gear.reason or "")


def _discover_concealed_tiago(mechanism: Concealment, seed: int, **options: Any) -> DiscoveryResult:
    """Discovery (no detectability; ``options`` more :class:`DiscoveryOptions`) of the real
    TIAGo recording with ``mechanism`` concealed in it, the effects its measurement sees."""
    chain, data, frame = concealed_real.recording("tiago")
    _, _, effects = concealed_real.read("tiago")
    readings, poses = conceal(
        chain, data.joint_positions, data.measured_pose, data.clock()[0], frame, mechanism
    )
    concealed = dataclasses.replace(data, joint_positions=readings, measured_pose=poses)
    settings = DiscoveryOptions(seed=seed, detectability=False, **options)
    if effects is not None:
        settings = dataclasses.replace(settings, effects=effects)
    return discover(chain, concealed, settings)


def test_a_joint_scale_the_joint_test_cannot_tell_from_a_gear_harmonic_gets_no_size(
    tmp_path: Path,
) -> None:
    """Issue 32, through ``kincal discover`` with its defaults: on the real TIAGo (21 samples)
    arm_6's scale error was stated detectable from 15 %, its separation from the first gear
    harmonic there calibrated on the model linearised at the fit. Concealed at twice that
    (the benchmark's seed 4), the refit took up part of the 30 % scale and the joint test
    with the harmonic in the model gave p = 0.11: reported ambiguous, not named. The size is
    now stated only where that joint test, on the model refit with the effect at twice the
    size in the readings, rejects at discovery's level: none here, with the reason."""
    tiago = concealed_real.RECORDINGS["tiago"]
    assert tiago.urdf is not None
    urdf = example_robot_data_dir() / tiago.urdf.removeprefix(concealed_real.ERD)
    flags: list[object] = [
        "--urdf", urdf, "--base", "base_footprint", "--tip", "arm_tool_link",
        "--measurement", "relative-base",
    ]  # fmt: skip
    result = discover_ok(concealed_real.DATA / tiago.relative, flags, tmp_path / "tiago.json")
    scale = stated_size(result, "joint_scale", "", "arm_6_joint")
    assert scale.smallest is None
    assert "not told from gear_periodic (h1) on arm_6_joint at twice the size" in (
        scale.reason or ""
    )
    joint = concealed_real.recording("tiago")[0].joint_names.index("arm_6_joint")
    mechanism, _ = concealed_real.concealment(
        "tiago", "joint_scale", joint, 0.3052, np.random.default_rng([4, len("joint_scale")])
    )
    found = _discover_concealed_tiago(mechanism, seed=4, bootstrap=0)
    assert all(f.estimate.term.effect != "joint_scale" for f in found.findings)
    first = found.ambiguous[0]
    assert sorted(c.term.key for c in first.candidates) == ["gear_periodic:6:h1", "joint_scale:6:"]


def test_a_candidate_that_refits_below_zero_gives_its_step_to_the_next_one() -> None:
    """Issue 32: a load backlash of 75 mrad concealed on the real TIAGo's arm_4_joint (twice
    its first stated size). The best-ranked candidate, a bending of the next link, has a
    bending axis that refits below zero: it was accepted at step 1 (held-out 26 → 13 mm),
    pruned from the final model as no spring bends against its load, and the search had
    ended — nothing named. The step now rejects it and tries the next candidate."""
    joint = concealed_real.recording("tiago")[0].joint_names.index("arm_4_joint")
    mechanism = Concealment(joints=(DeadBand("arm_4_joint", 0.0753),))
    result = _discover_concealed_tiago(mechanism, seed=1)
    refused = [s for s in result.steps if s.action == "rejected_sign"]
    assert refused and refused[0].candidate.startswith("link_bending:5")
    named = [(f.estimate.term.effect, f.estimate.term.joint_index) for f in result.findings]
    assert named == [("backlash", joint)]
    assert all(s.action != "pruned" for s in result.steps)


def test_the_ur10es_wrist_1_states_no_gear_size_it_could_not_name(
    unmodified: dict[str, FindingsResult],
) -> None:
    """Issue 32: the UR10e's only second-harmonic gear size was wrist_1's. The promise at
    twice the size (every replicate rejects there) first raised it from 8.6 to 10.0 mrad, where
    the semi-real benchmark's seed 4 named the gear; later rules raised it to 228 mrad, beyond
    what the gear mechanism can build (a lobe of 0.9 pitch radii), and at 20 mrad the run now
    names nothing. At twice 228 mrad discovery's lack-of-fit test there rejects (p = 0.001):
    the step would report the joint's structure beyond the library, so no size is stated, with
    that reason."""
    gear = stated_size(unmodified["ur10e"], "gear_periodic", "h2", "wrist_1_joint")
    assert gear.smallest is None
    assert "would be reported beyond the library" in (gear.reason or "")


def test_a_linear_drift_is_named_linear_whichever_shape_ranked_first() -> None:
    """Issue 32: a steady encoder drift (5.9 mrad per sample, twice its stated size) concealed
    on the real TIAGo's arm_5_joint was named a warm-up drift: the library's warm-up variant
    happened to rank first, and its time constant was refined without asking whether the
    linear shape does as well. A warm-up is now named only where it beats the linear drift by
    a likelihood-ratio test. Anything else named is the recording's own: the unmodified
    recording names it at the same seed (TIAGo's arm_4 load backlash)."""
    joint = concealed_real.recording("tiago")[0].joint_names.index("arm_5_joint")
    mechanism, _ = concealed_real.concealment(
        "tiago",
        "joint_drift",
        joint,
        5.88585251774134e-3,  # twice arm_5's stated size: the benchmark's seed-3 run
        np.random.default_rng([3, len("joint_drift")]),
    )

    def names(result: DiscoveryResult) -> list[tuple[str, int | None, str]]:
        return [
            (f.estimate.term.effect, f.estimate.term.joint_index, f.estimate.term.variant)
            for f in result.findings
        ]

    named = names(_discover_concealed_tiago(mechanism, seed=3, bootstrap=0))
    assert named[0] == ("thermal_drift", joint, "linear")
    own = names(_discover_concealed_tiago(Concealment(), seed=3, bootstrap=0))
    refined = {(e, j, v.split(":")[0]) for e, j, v in own}  # load:<floating zone> is load
    assert {(e, j, v.split(":")[0]) for e, j, v in named[1:]} <= refined


def test_a_warmup_drift_keeps_its_warmup_shape(tmp_path: Path) -> None:
    """The other side of the shape rule, through ``kincal discover`` with its defaults: an
    encoder zero settling by 10 mrad with a time constant of 15 samples, concealed on the real
    FR3's panda_joint4, beats the linear drift by far and is named a warm-up with its time
    constant (refined to within 10 %)."""
    chain, data, frame = concealed_real.recording("fr3")
    mechanism = Concealment(joints=(EncoderWarmup("panda_joint4", 0.01, 15.0),))
    readings, poses = conceal(
        chain, data.joint_positions, data.measured_pose, data.clock()[0], frame, mechanism
    )
    path = tmp_path / "fr3_warmup.csv"
    write_recording(path, readings, poses)
    result = _discover(path, "fr3", sizes=False)
    drifts = [f for f in result.findings if f.effect == "thermal_drift"]
    assert [(f.joint, f.variant.split(":")[0]) for f in drifts] == [("panda_joint4", "warmup")]
    assert float(drifts[0].variant.split(":")[1]) == pytest.approx(15.0, rel=0.1)
