"""Dataset reading, validation and writing (the schemas/dataset package)."""

from __future__ import annotations

import importlib.util
import json
import math
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from schemas.dataset import (
    QUATERNION_NORM_TOL,
    PoseDataset,
    dataset_from_frame,
    dataset_to_frame,
    read_dataset,
    rpy_to_quaternion_xyzw,
    write_dataset,
)
from schemas.limits import (
    MAX_JOINT_POSITION,
    MAX_PAYLOAD_KG,
    MAX_POSITION_M,
    MAX_TIME_S,
    TEMPERATURE_RANGE_C,
)
from solver.errors import DatasetError
from solver.measurement import FullPose, Position

REPO = Path(__file__).parents[2]
FR3_DIR = REPO / "data/real/philnad_fr3_eye_in_hand"
UR10_CSV = REPO / "data/real/figaroh_ur10_experiment/calibration.csv"
UR10_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
PANDA_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
J3 = ("base_joint", "elbow", "wrist")  # small robot for hand-written files


def valid_frame(n: int = 4, joints: tuple[str, ...] = J3, quat: bool = True) -> pd.DataFrame:
    rng = np.random.default_rng(0)
    data = {name: rng.uniform(-1, 1, n) for name in joints}
    data |= {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n)}
    if quat:
        q = Rotation.random(n, rng=1).as_quat()
        data |= {"qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]}
    return pd.DataFrame(data)


def write_text(tmp_path: Path, text: str, name: str = "data.csv") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def error_of(call, *args, **kwargs) -> str:
    """The DatasetError message of call(*args, **kwargs); always exactly one line."""
    with pytest.raises(DatasetError) as info:
        call(*args, **kwargs)
    message = str(info.value)
    assert "\n" not in message and message.strip() == message
    return message


def frame_error(frame: pd.DataFrame, joints: tuple[str, ...] = J3, **kwargs) -> str:
    return error_of(dataset_from_frame, frame, joints, source="data.csv", **kwargs)


# --------------------------------------------------------------------------- round trips


def _within(low: float, high: float) -> st.SearchStrategy[float]:
    return st.floats(low, high, allow_nan=False, allow_infinity=False, width=64)


EXTRA_RANGES = {
    "time_s": _within(-MAX_TIME_S, MAX_TIME_S),
    "temperature_c": _within(*TEMPERATURE_RANGE_C),
    "payload_kg": _within(0.0, MAX_PAYLOAD_KG),
}


def datasets(draw_k: int | None = None) -> st.SearchStrategy[PoseDataset]:
    """Any dataset the contract accepts: every number anywhere in its accepted range."""
    finite = _within(
        -min(MAX_JOINT_POSITION, MAX_POSITION_M), min(MAX_JOINT_POSITION, MAX_POSITION_M)
    )

    @st.composite
    def build(draw: st.DrawFn) -> PoseDataset:
        n = draw(st.integers(1, 6))
        k = draw_k or draw(st.integers(1, 7))
        arrays = st.lists(finite, min_size=n * k, max_size=n * k)
        joints = np.array(draw(arrays)).reshape(n, k)
        position = np.array(draw(st.lists(finite, min_size=3 * n, max_size=3 * n))).reshape(n, 3)
        quat = None
        if draw(st.booleans()):
            quat = Rotation.random(n, rng=draw(st.integers(0, 2**32 - 1))).as_quat()
        ids = draw(
            st.one_of(
                st.none(),
                st.lists(st.integers(-(2**62), 2**62), min_size=n, max_size=n, unique=True),
                st.lists(
                    st.from_regex(r"[a-z][a-z0-9_]{0,6}", fullmatch=True).filter(
                        lambda s: s.lower() not in {"nan", "null", "na", "n_a", "none", "true"}
                    ),
                    min_size=n,
                    max_size=n,
                    unique=True,
                ),
            )
        )
        extras = {}
        for name in ("time_s", "temperature_c", "payload_kg"):
            if draw(st.booleans()):
                values = st.lists(EXTRA_RANGES[name], min_size=n, max_size=n)
                extras[name] = np.array(draw(values))
        if "time_s" in extras:
            extras["time_s"] = np.sort(extras["time_s"])
        return PoseDataset(
            joint_names=tuple(f"joint_{i}" for i in range(k)),
            joint_positions=joints,
            position_m=position,
            quaternion_xyzw=quat,
            sample_id=None if ids is None else np.array(ids, dtype=object),
            **extras,
        )

    return build()


def assert_same_dataset(a: PoseDataset, b: PoseDataset) -> None:
    assert a.joint_names == b.joint_names
    for name in ("joint_positions", "position_m", "quaternion_xyzw", "time_s"):
        left, right = getattr(a, name), getattr(b, name)
        assert (left is None) == (right is None), name
        if left is not None:
            np.testing.assert_array_equal(left, right, err_msg=name)
    for name in ("temperature_c", "payload_kg"):
        left, right = getattr(a, name), getattr(b, name)
        assert (left is None) == (right is None), name
        if left is not None:
            np.testing.assert_array_equal(left, right, err_msg=name)
    if a.sample_id is None:
        assert b.sample_id is None
    else:
        assert list(a.sample_id) == list(b.sample_id)


@pytest.mark.parametrize("suffix", [".csv", ".parquet", ".json"])
@pytest.mark.parametrize("style", ["names", "q"])
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(ds=datasets())
def test_write_then_read_gives_identical_arrays(ds: PoseDataset, suffix: str, style: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"data{suffix}"
        write_dataset(ds, path, joint_column_style=style)
        back = read_dataset(path, ds.joint_names)
    assert back.source == path.name
    assert back.measures_rotation == ds.measures_rotation
    assert_same_dataset(ds, back)


def test_round_trip_of_real_fr3_file_is_exact(tmp_path: Path) -> None:
    ds = read_dataset(FR3_DIR / "fr3_poses.csv", PANDA_JOINTS)
    for suffix in (".csv", ".parquet", ".json"):
        write_dataset(ds, tmp_path / f"fr3{suffix}")
        assert_same_dataset(ds, read_dataset(tmp_path / f"fr3{suffix}", PANDA_JOINTS))


def test_json_object_with_samples_key_is_accepted(tmp_path: Path) -> None:
    rows = valid_frame().to_dict(orient="records")
    path = write_text(tmp_path, json.dumps({"samples": rows, "note": "lab 3"}), "data.json")
    ds = read_dataset(path, J3)
    np.testing.assert_array_equal(ds.joint_positions, valid_frame()[list(J3)].to_numpy())


def test_written_columns_follow_the_contract_order() -> None:
    ds = dataset_from_frame(valid_frame().assign(sample_id=[1, 2, 3, 4], t=0.5), J3, source="m")
    assert list(dataset_to_frame(ds, joint_column_style="q").columns) == [
        "sample_id", "q1", "q2", "q3", "x", "y", "z", "qx", "qy", "qz", "qw", "t",
    ]  # fmt: skip


# --------------------------------------------------------------------------- quaternion order


def test_quaternion_columns_are_scalar_last_whatever_their_file_order(tmp_path: Path) -> None:
    # 60 deg about x: xyzw = (sin 30, 0, 0, cos 30); reading w first gives (cos 30, sin 30, 0, 0).
    text = "qw,qz,base_joint,elbow,wrist,x,y,z,qy,qx\n0.8660254037844386,0,0,0,0,1,2,3,0,0.5\n"
    ds = read_dataset(write_text(tmp_path, text), J3)
    np.testing.assert_allclose(ds.quaternion_xyzw[0], [0.5, 0, 0, math.sqrt(3) / 2], atol=1e-15)
    expected = Rotation.from_euler("x", 60, degrees=True).as_matrix()
    np.testing.assert_allclose(
        Rotation.from_quat(ds.quaternion_xyzw).as_matrix()[0], expected, atol=1e-12
    )
    np.testing.assert_array_equal(ds.position_m[0], [1, 2, 3])


def test_written_quaternion_is_scalar_last(tmp_path: Path) -> None:
    q_xyzw = np.array([[0.5, 0.0, 0.0, math.sqrt(3) / 2]])
    ds = PoseDataset(("a",), np.zeros((1, 1)), np.zeros((1, 3)), q_xyzw)
    write_dataset(ds, tmp_path / "out.csv")
    frame = pd.read_csv(tmp_path / "out.csv")
    assert list(frame.columns[-4:]) == ["qx", "qy", "qz", "qw"]
    assert frame.loc[0, "qx"] == 0.5 and frame.loc[0, "qw"] == pytest.approx(0.8660254)


# --------------------------------------------------------------------------- FIGAROH adapter


def test_figaroh_yaw_quarter_turn_is_z_quaternion() -> None:
    s = math.sin(math.pi / 4)
    np.testing.assert_allclose(rpy_to_quaternion_xyzw([[0, 0, math.pi / 2]]), [[0, 0, s, s]])


@pytest.mark.parametrize(
    ("rpy", "xyzw"),
    [
        ((math.pi / 3, 0, 0), (0.5, 0, 0, math.sqrt(3) / 2)),  # roll only: w-first would fail
        ((0, math.pi / 3, 0), (0, 0.5, 0, math.sqrt(3) / 2)),
        ((0, 0, math.pi / 3), (0, 0, 0.5, math.sqrt(3) / 2)),
    ],
)
def test_figaroh_single_axis_angles(rpy: tuple[float, ...], xyzw: tuple[float, ...]) -> None:
    np.testing.assert_allclose(rpy_to_quaternion_xyzw([rpy])[0], xyzw, atol=1e-15)


def test_figaroh_rpy_is_rz_ry_rx_product() -> None:
    roll, pitch, yaw = 0.3, -0.7, 2.1

    cr, sr, cp, sp, cy, sy = (f(a) for a in (roll, pitch, yaw) for f in (math.cos, math.sin))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    expected = rz @ ry @ rx
    quat = rpy_to_quaternion_xyzw([[roll, pitch, yaw]])
    np.testing.assert_allclose(Rotation.from_quat(quat).as_matrix()[0], expected, atol=1e-14)


def test_figaroh_file_loads_marker_one(tmp_path: Path) -> None:
    text = "x1,y1,z1,phix1,phiy1,phiz1,base_joint,elbow,wrist\n1,2,3,0,0,1.5707963267948966,4,5,6\n"
    ds = read_dataset(write_text(tmp_path, text), J3)
    np.testing.assert_array_equal(ds.position_m, [[1, 2, 3]])
    np.testing.assert_array_equal(ds.joint_positions, [[4, 5, 6]])
    s = math.sin(math.pi / 4)
    np.testing.assert_allclose(ds.quaternion_xyzw, [[0, 0, s, s]])


def test_figaroh_positions_with_time(tmp_path: Path) -> None:
    text = "t,x1,y1,z1,base_joint,elbow,wrist\n0.5,1,2,3,4,5,6\n0.7,1,2,3,4,5,6\n"
    ds = read_dataset(write_text(tmp_path, text), J3)
    assert not ds.measures_rotation and list(ds.time_s) == [0.5, 0.7]


def test_figaroh_several_markers_need_a_choice(tmp_path: Path) -> None:
    text = "x1,y1,z1,x2,y2,z2,base_joint,elbow,wrist\n1,2,3,7,8,9,4,5,6\n"
    path = write_text(tmp_path, text)
    message = error_of(read_dataset, path, J3)
    assert "data.csv" in message and "markers (1,2)" in message
    assert "marker=N" in message and "split the file" in message
    np.testing.assert_array_equal(read_dataset(path, J3, marker=2).position_m, [[7, 8, 9]])
    assert "marker 3 not in the file" in error_of(read_dataset, path, J3, marker=3)


def test_figaroh_partial_rpy_is_rejected(tmp_path: Path) -> None:
    path = write_text(tmp_path, "x1,y1,z1,phix1,base_joint,elbow,wrist\n1,2,3,0,4,5,6\n")
    message = error_of(read_dataset, path, J3)
    assert "phix1" in message and "phiy1,phiz1" in message


def test_figaroh_mixed_with_contract_pose_is_rejected(tmp_path: Path) -> None:
    path = write_text(tmp_path, "x,y,z,x1,y1,z1,base_joint,elbow,wrist\n1,2,3,1,2,3,4,5,6\n")
    assert "x,y,z" in error_of(read_dataset, path, J3)


# --------------------------------------------------------------------------- errors


def test_unknown_suffix(tmp_path: Path) -> None:
    message = error_of(read_dataset, write_text(tmp_path, "x", "data.xlsx"), J3)
    assert "'.xlsx'" in message and ".csv, .parquet, .json" in message


def test_missing_file(tmp_path: Path) -> None:
    assert "file not found" in error_of(read_dataset, tmp_path / "nope.csv", J3)


def test_empty_file(tmp_path: Path) -> None:
    assert "data.csv: file is empty" in error_of(read_dataset, write_text(tmp_path, ""), J3)


def test_header_without_rows(tmp_path: Path) -> None:
    path = write_text(tmp_path, "base_joint,elbow,wrist,x,y,z\n")
    assert "no data rows" in error_of(read_dataset, path, J3)


@pytest.mark.parametrize("text", ["[]", '{"samples": []}'])
def test_json_without_rows(tmp_path: Path, text: str) -> None:
    assert "no data rows" in error_of(read_dataset, write_text(tmp_path, text, "d.json"), J3)


def test_malformed_json(tmp_path: Path) -> None:
    message = error_of(read_dataset, write_text(tmp_path, '[{"x": 1,}]', "d.json"), J3)
    assert message.startswith("d.json: malformed JSON") and "line 1" in message


def test_json_of_wrong_shape(tmp_path: Path) -> None:
    message = error_of(read_dataset, write_text(tmp_path, '{"rows": []}', "d.json"), J3)
    assert "'samples'" in message
    message = error_of(read_dataset, write_text(tmp_path, '[{"x": 1}, 3]', "d.json"), J3)
    assert "data row 2 is not a JSON object" in message


def test_json_duplicate_key(tmp_path: Path) -> None:
    path = write_text(tmp_path, '[{"x": 1, "x": 2}]', "d.json")
    assert "'x' appears twice" in error_of(read_dataset, path, J3)


def test_garbage_parquet(tmp_path: Path) -> None:
    path = tmp_path / "data.parquet"
    path.write_bytes(b"not a parquet file at all")
    message = error_of(read_dataset, path, J3)
    assert message.startswith("data.parquet: cannot read as parquet")


def test_ragged_csv_row(tmp_path: Path) -> None:
    path = write_text(tmp_path, "base_joint,elbow,wrist,x,y,z\n1,2,3,4,5,6\n1,2,3,4,5,6,7\n")
    assert "data row 2 (line 3) has 7 values but the header has 6" in error_of(
        read_dataset, path, J3
    )


def test_not_utf8(tmp_path: Path) -> None:
    path = tmp_path / "data.csv"
    path.write_bytes(b"base_joint,elbow,wrist,x,y,z\n\xff\xfe,1,2,3,4,5\n")
    assert "not UTF-8" in error_of(read_dataset, path, J3)


@pytest.mark.parametrize(("bad", "problem"), [(math.nan, "missing"), (math.inf, "infinite")])
@pytest.mark.parametrize("column", ["elbow", "y", "qw"])
def test_nan_or_inf_names_row_and_column(column: str, bad: float, problem: str) -> None:
    frame = valid_frame()
    frame.loc[2, column] = bad
    message = frame_error(frame)
    assert f"data.csv: data row 3, column {column}: value is {problem}" in message


@pytest.mark.parametrize(
    ("column", "value", "bounds"),
    [
        ("elbow", 1e308, "-10000 to 10000 rad"),
        ("elbow", -2e244, "-10000 to 10000 rad"),
        ("y", 1e5, "-10000 to 10000 m"),
        ("t", 1e300, "s"),
        ("temperature_c", -300.0, "-273.15 to 10000 °C"),
        ("payload_kg", -1.0, "0 to 100000 kg"),
    ],
)
def test_numbers_out_of_range_are_refused_naming_row_column_and_range(
    column: str, value: float, bounds: str
) -> None:
    """The ranges of schemas.limits, the same as rankings'; 1e308 used to be accepted and to
    fail the calibration job later (SVD did not converge)."""
    frame = valid_frame().assign(t=0.0, temperature_c=20.0, payload_kg=0.0)
    frame[column] = frame[column].astype(float)
    frame.loc[1, column] = value
    message = frame_error(frame)
    assert f"data row 2, column {column}: value {value:g} is out of range" in message
    assert bounds in message


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_an_integer_beyond_a_float_is_a_dataset_error(tmp_path: Path, suffix: str) -> None:
    """A 400-digit integer was an OverflowError (HTTP 500, CLI 'internal error')."""
    frame = valid_frame().astype(object)
    frame.loc[0, "wrist"] = 10**400
    path = tmp_path / f"big{suffix}"
    if suffix == ".csv":
        path.write_text(frame.to_csv(index=False))
    else:
        path.write_text(json.dumps(frame.to_dict(orient="records")))
    message = error_of(read_dataset, path, J3)
    assert "data row 1, column wrist: value is infinite or beyond a float (1000000" in message


def test_empty_csv_cell_is_missing(tmp_path: Path) -> None:
    path = write_text(tmp_path, "base_joint,elbow,wrist,x,y,z\n1,2,3,4,5,6\n1,,3,4,5,6\n")
    assert "data row 2, column elbow: value is missing" in error_of(read_dataset, path, J3)


def test_nan_in_an_ignored_column_is_fine() -> None:
    frame = valid_frame().assign(gripper=np.nan)
    ds = dataset_from_frame(frame, J3, source="m", other_joint_names=["gripper"])
    assert ds.n_samples == 4


def test_non_numeric_value_names_row_and_column(tmp_path: Path) -> None:
    path = write_text(tmp_path, "base_joint,elbow,wrist,x,y,z\n1,2,3,4,5,6\n1,2,3,4,5 mm,6\n")
    message = error_of(read_dataset, path, J3)
    assert "data.csv: data row 2, column y: '5 mm' is not a number" in message


def test_non_numeric_json_value(tmp_path: Path) -> None:
    rows = valid_frame().to_dict(orient="records")
    rows[1]["wrist"] = [1, 2]
    path = write_text(tmp_path, json.dumps(rows), "d.json")
    assert "data row 2, column wrist: [1, 2] is not a number" in error_of(read_dataset, path, J3)


def test_non_unit_quaternion_names_row_and_columns() -> None:
    frame = valid_frame()
    frame.loc[1, ["qx", "qy", "qz", "qw"]] *= 1.31
    message = frame_error(frame)
    assert "data row 2, columns qx,qy,qz,qw: quaternion is not unit-norm (|q| = 1.31" in message


def test_zero_quaternion_is_rejected() -> None:
    frame = valid_frame()
    frame.loc[0, ["qx", "qy", "qz", "qw"]] = 0.0
    assert "data row 1, columns qx,qy,qz,qw" in frame_error(frame)


def test_nearly_unit_quaternion_is_renormalised() -> None:
    frame = valid_frame()
    frame.loc[0, ["qx", "qy", "qz", "qw"]] *= 1 + 0.9 * QUATERNION_NORM_TOL
    ds = dataset_from_frame(frame, J3, source="m")
    np.testing.assert_allclose(np.linalg.norm(ds.quaternion_xyzw, axis=1), 1.0, atol=1e-15)


def test_missing_joint_columns() -> None:
    message = frame_error(valid_frame().drop(columns=["elbow"]))
    assert "missing joint column(s) elbow" in message
    assert "base_joint,elbow,wrist" in message and "q1..q3" in message


def test_misspelt_joint_is_reported_with_the_missing_one() -> None:
    message = frame_error(valid_frame().rename(columns={"elbow": "elbw"}))
    assert "missing joint column(s) elbow" in message and "elbw" in message


def test_unknown_column() -> None:
    message = frame_error(valid_frame().assign(gripper=0.0, comment="ok"))
    assert "unknown column(s) gripper,comment" in message
    assert "base_joint,elbow,wrist" in message and "other_joint_names" in message


def test_saved_index_column_gets_a_hint(tmp_path: Path) -> None:
    valid_frame().to_csv(tmp_path / "data.csv")  # index=True: leading unnamed column
    assert "saved with its index" in error_of(read_dataset, tmp_path / "data.csv", J3)


def test_other_joint_columns_are_ignored() -> None:
    frame = valid_frame().assign(finger_joint1=0.01, finger_joint2=0.02)
    ds = dataset_from_frame(
        frame, J3, source="m", other_joint_names=["finger_joint1", "finger_joint2"]
    )
    assert ds.joint_names == J3 and ds.joint_positions.shape == (4, 3)


def test_mixing_urdf_names_and_q_style() -> None:
    frame = valid_frame().rename(columns={"wrist": "q3"})
    message = frame_error(frame)
    assert "mixes URDF joint columns (base_joint,elbow) with q-style columns (q3)" in message


@pytest.mark.parametrize(
    ("columns", "expected"),
    [
        (["q1", "q2"], "missing q3"),
        (["q1", "q2", "q3", "q4"], "q4 beyond the last joint"),
        (["q2", "q3", "q4"], "missing q1; q4 beyond the last joint"),
    ],
)
def test_q_style_must_be_exactly_q1_to_qk(columns: list[str], expected: str) -> None:
    frame = pd.DataFrame({c: [0.1] for c in [*columns, "x", "y", "z"]})
    message = frame_error(frame)
    assert expected in message and "write exactly q1..q3" in message


def test_q_style_six_joint_robot_given_five_or_seven() -> None:
    five = pd.DataFrame({c: [0.0] for c in ["q1", "q2", "q3", "q4", "q5", "x", "y", "z"]})
    assert "missing q6" in frame_error(five, UR10_JOINTS)
    seven = five.assign(q6=0.0, q7=0.0)
    assert "q7 beyond the last joint" in frame_error(seven, UR10_JOINTS)


def test_q_style_reads_chain_order() -> None:
    frame = pd.DataFrame({"q3": [3.0], "q1": [1.0], "q2": [2.0], "x": [0], "y": [0], "z": [0]})
    ds = dataset_from_frame(frame, J3, source="m")
    np.testing.assert_array_equal(ds.joint_positions, [[1, 2, 3]])
    assert ds.joint_names == J3


def test_duplicate_csv_header_is_detected_before_pandas_renames(tmp_path: Path) -> None:
    path = write_text(tmp_path, "base_joint,elbow,wrist,x,y,z,x\n1,2,3,4,5,6,7\n")
    message = error_of(read_dataset, path, J3)
    assert "data.csv: duplicate column name(s) x" in message


def test_duplicate_frame_columns() -> None:
    frame = valid_frame()
    frame.columns = ["base_joint", "elbow", "elbow", "x", "y", "z", "qx", "qy", "qz", "qw"]
    assert "duplicate column name(s) elbow" in frame_error(frame)


@pytest.mark.parametrize("column", ["x", "z"])
def test_missing_position_column(column: str) -> None:
    message = frame_error(valid_frame().drop(columns=[column]))
    assert f"missing position column(s) {column}" in message and "x,y,z" in message


def test_partial_quaternion() -> None:
    message = frame_error(valid_frame().drop(columns=["qw"]))
    assert "qx,qy,qz present but qw missing" in message and "all four" in message


def test_a_dataset_without_quaternions_measures_positions() -> None:
    ds = dataset_from_frame(valid_frame(quat=False), J3, source="m")
    assert not ds.measures_rotation and ds.quaternion_xyzw is None
    assert ds.measurement_model == Position()
    assert dataset_from_frame(valid_frame(), J3, source="m").measurement_model == FullPose()


def test_time_must_not_decrease() -> None:
    frame = valid_frame().assign(t=[0.0, 1.0, 0.5, 2.0])
    message = frame_error(frame)
    assert "data row 3, column t: time goes backwards (0.5 after 1.0 in data row 2)" in message


def test_equal_times_are_allowed() -> None:
    ds = dataset_from_frame(valid_frame().assign(t=[0.0, 1.0, 1.0, 2.0]), J3, source="m")
    np.testing.assert_array_equal(ds.time_s, [0, 1, 1, 2])


def test_duplicate_sample_id() -> None:
    message = frame_error(valid_frame().assign(sample_id=["a", "b", "c", "a"]))
    assert "data row 4, column sample_id: 'a' already used in data row 1" in message


def test_missing_sample_id() -> None:
    message = frame_error(valid_frame().assign(sample_id=["a", None, "c", "d"]))
    assert "data row 2, column sample_id: value is missing" in message


def test_optional_columns_are_read() -> None:
    frame = valid_frame().assign(sample_id=[5, 6, 7, 8], temperature_c=21.5, payload_kg=1.2)
    ds = dataset_from_frame(frame, J3, source="m")
    assert list(ds.sample_id) == [5, 6, 7, 8]
    assert ds.temperature_c.tolist() == [21.5] * 4 and ds.payload_kg.tolist() == [1.2] * 4
    assert ds.time_s is None


# --------------------------------------------------------------------------- container


def test_subset_keeps_execution_order() -> None:
    ds = dataset_from_frame(valid_frame().assign(sample_id=[10, 11, 12, 13]), J3, source="m")
    assert list(ds.subset([3, 0, 2]).sample_id) == [10, 12, 13]
    part = ds.subset(np.array([True, False, True, False]))
    assert list(part.sample_id) == [10, 12] and part.n_samples == 2 and part.n_joints == 3
    np.testing.assert_array_equal(part.quaternion_xyzw, ds.quaternion_xyzw[[0, 2]])
    with pytest.raises(ValueError, match="duplicate"):
        ds.subset([1, 1])


def test_shape_mismatch_is_reported() -> None:
    with pytest.raises(DatasetError, match=r"position_m has shape \(2, 3\), expected \(3, 3\)"):
        PoseDataset(("a", "b"), np.zeros((3, 2)), np.zeros((2, 3)), None)
    with pytest.raises(DatasetError, match="3 joint names"):
        PoseDataset(("a", "b", "c"), np.zeros((3, 2)), np.zeros((3, 3)), None)


def test_unknown_suffix_on_write(tmp_path: Path) -> None:
    ds = PoseDataset(("a",), np.zeros((1, 1)), np.zeros((1, 3)), None)
    assert "'.txt'" in error_of(write_dataset, ds, tmp_path / "out.txt")


# --------------------------------------------------------------------------- real recordings


def test_fr3_converted_file_loads() -> None:
    ds = read_dataset(FR3_DIR / "fr3_poses.csv", PANDA_JOINTS)
    assert ds.source == "fr3_poses.csv"
    assert (ds.n_samples, ds.n_joints, ds.measures_rotation) == (114, 7, True)
    assert list(ds.sample_id) == list(range(114))
    assert np.all(ds.quaternion_xyzw[:, 3] >= 0)
    np.testing.assert_allclose(np.linalg.norm(ds.quaternion_xyzw, axis=1), 1.0, atol=1e-12)


def test_fr3_converted_file_is_reproducible() -> None:
    spec = importlib.util.spec_from_file_location("fr3_convert", FR3_DIR / "convert.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    raw = pd.read_csv(FR3_DIR / "fr3_calib_data.csv")
    text = module.to_csv_text(module.convert(raw))
    assert text == (FR3_DIR / "fr3_poses.csv").read_text(encoding="utf-8")
    cam = raw[[f"cam_T{r}{c}" for r in range(3) for c in range(3)]].to_numpy().reshape(-1, 3, 3)
    ds = read_dataset(FR3_DIR / "fr3_poses.csv", PANDA_JOINTS)
    np.testing.assert_allclose(Rotation.from_quat(ds.quaternion_xyzw).as_matrix(), cam, atol=1e-12)


def test_ur10_figaroh_file_loads() -> None:
    ds = read_dataset(UR10_CSV, UR10_JOINTS)
    assert (ds.n_samples, ds.n_joints, ds.measures_rotation) == (23, 6, True)
    raw = pd.read_csv(UR10_CSV)
    np.testing.assert_array_equal(ds.joint_positions, raw[list(UR10_JOINTS)].to_numpy())
    np.testing.assert_array_equal(ds.position_m, raw[["x1", "y1", "z1"]].to_numpy())
    rpy = raw[["phix1", "phiy1", "phiz1"]].to_numpy()
    back = Rotation.from_quat(ds.quaternion_xyzw).as_euler("xyz")
    np.testing.assert_allclose(back, rpy, atol=1e-12)


@pytest.mark.parametrize("bad", [10**400, [1], {"a": 1}, True, "x" * 300])
def test_sample_ids_are_integers_or_short_texts(bad: object) -> None:
    """A 400-digit id passed validation and was a 500 when the upload was stored."""
    frame = valid_frame()
    frame["sample_id"] = pd.Series([bad, *range(1, len(frame))], dtype=object)
    message = frame_error(frame)
    assert "data row 1, column sample_id" in message and "is not a sample id" in message
