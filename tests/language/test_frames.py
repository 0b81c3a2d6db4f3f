"""engine.common.frames against values computed independently (rotation matrices, MAVROS rules)."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from engine.common import frames

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

ANGLES = [
    (0.0, 0.0, 0.0),
    (0.1, -0.2, 0.3),
    (-0.7, 0.4, 2.9),
    (1.2, -1.1, -2.5),
    (3.0, 0.05, -3.1),
    (0.0, 0.0, math.pi / 2),
]


def rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def matrix_of(q: dict) -> np.ndarray:
    w, x, y, z = q["w"], q["x"], q["y"], q["z"]
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


NED_TO_ENU = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1]])
FRD_TO_FLU = np.diag([1, -1, -1])


def angle_diff(a: float, b: float) -> float:
    return abs(math.remainder(a - b, 2 * math.pi))


def test_units_round_trip_and_rounding() -> None:
    assert frames.deg_e7_to_deg(473977418) == pytest.approx(47.3977418)
    assert frames.deg_to_deg_e7(47.3977418) == 473977418
    assert frames.deg_to_deg_e7(-122.0840575) == -1220840575
    assert frames.mm_to_m(488_123) == pytest.approx(488.123)
    assert frames.m_to_mm(1.2) == 1200 and isinstance(frames.m_to_mm(1.2), int)
    assert frames.cm_to_m(-153) == pytest.approx(-1.53)
    assert frames.m_to_cm(-2.5) == -250
    assert frames.cmps_to_mps(250) == pytest.approx(2.5)
    assert frames.cdeg_to_deg(35999) == pytest.approx(359.99)
    assert frames.deg_to_cdeg(90.0) == 9000
    assert frames.heading_cdeg_to_deg(65535) is None
    assert frames.heading_cdeg_to_deg(18000) == pytest.approx(180.0)


def test_vectors_match_mavros_rules_and_keep_shape() -> None:
    assert frames.ned_to_enu([1.0, 2.0, 3.0]) == [2.0, 1.0, -3.0]
    assert frames.enu_to_ned(frames.ned_to_enu([1.0, 2.0, 3.0])) == [1.0, 2.0, 3.0]
    assert frames.ned_to_enu({"x": 1, "y": 2, "z": 3, "frame": "n"}) == {"x": 2.0, "y": 1.0, "z": -3.0, "frame": "n"}
    assert frames.aircraft_to_baselink([0.1, 0.2, 0.3]) == [0.1, -0.2, -0.3]
    v = np.array([0.3, -1.2, 4.0])
    assert np.allclose(frames.ned_to_enu(list(v)), NED_TO_ENU @ v)
    assert np.allclose(frames.aircraft_to_baselink(list(v)), FRD_TO_FLU @ v)


def test_static_quaternions_are_the_mavros_ones() -> None:
    assert np.allclose(frames.NED_ENU_Q, tuple(frames._quat(frames.quaternion_from_rpy(math.pi, 0, math.pi / 2))))
    assert np.allclose(frames.AIRCRAFT_BASELINK_Q, tuple(frames._quat(frames.quaternion_from_rpy(math.pi, 0, 0))))


@pytest.mark.parametrize("rpy", ANGLES)
def test_quaternion_from_rpy_is_zyx(rpy: tuple[float, float, float]) -> None:
    roll, pitch, yaw = rpy
    expected = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    assert np.allclose(matrix_of(frames.quaternion_from_rpy(roll, pitch, yaw)), expected)


@pytest.mark.parametrize("rpy", ANGLES)
def test_rpy_round_trip(rpy: tuple[float, float, float]) -> None:
    got = frames.rpy_from_quaternion(frames.quaternion_from_rpy(*rpy))
    for key, value in zip(("roll", "pitch", "yaw"), rpy):
        assert angle_diff(got[key], value) < 1e-9, key


@pytest.mark.parametrize("rpy", ANGLES)
def test_attitude_to_enu_matches_rotation_matrices(rpy: tuple[float, float, float]) -> None:
    roll, pitch, yaw = rpy
    r_ned_frd = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
    r_enu_flu = NED_TO_ENU @ r_ned_frd @ FRD_TO_FLU
    out = frames.attitude_ned_to_enu(roll, pitch, yaw)
    assert np.allclose(matrix_of(out["orientation"]), r_enu_flu)
    assert angle_diff(out["roll"], roll) < 1e-9
    assert angle_diff(out["pitch"], -pitch) < 1e-9
    assert angle_diff(out["yaw"], math.pi / 2 - yaw) < 1e-9


def test_quaternion_frame_round_trip_in_both_shapes() -> None:
    rng = random.Random(7)
    for _ in range(50):
        rpy = (rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3))
        q = frames.quaternion_from_rpy(*rpy)
        enu = frames.quat_ned_aircraft_to_enu_baselink(q)
        back = frames.quat_enu_baselink_to_ned_aircraft(enu)
        assert np.allclose(matrix_of(back), matrix_of(q))
        as_list = [q["w"], q["x"], q["y"], q["z"]]
        enu_list = frames.quat_ned_aircraft_to_enu_baselink(as_list)
        assert isinstance(enu_list, list)
        assert np.allclose(enu_list, [enu["w"], enu["x"], enu["y"], enu["z"]])


def test_level_north_facing_vehicle_faces_90_degrees_in_enu() -> None:
    out = frames.attitude_ned_to_enu(0.0, 0.0, 0.0)
    assert out["yaw"] == pytest.approx(math.pi / 2)
    assert out["roll"] == pytest.approx(0.0, abs=1e-12)
    assert out["pitch"] == pytest.approx(0.0, abs=1e-12)


def test_functions_registry_lists_callables() -> None:
    assert frames.FUNCTIONS["deg_e7_to_deg"] is frames.deg_e7_to_deg
    assert all(callable(f) for f in frames.FUNCTIONS.values())
