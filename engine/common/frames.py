"""Unit and reference-frame conversions between MAVLink and ROS conventions.

MAVLink sends integers in scaled units (degE7, mm, cm/s, cdeg) and describes the world in
NED with an aircraft (FRD) body; ROS uses SI units, ENU and a FLU ``base_link`` body. The
math follows MAVROS (``ftf_frame_conversions.cpp``, ``ftf_quaternion_utils.cpp``) exactly,
so values published by the engine agree with what a MAVROS user already sees:

* vectors NED<->ENU are the reflection ``(x, y, z) -> (y, x, -z)``, aircraft<->base_link is
  ``(x, y, z) -> (x, -y, -z)``; both are their own inverse;
* orientations are ``q_enu_baselink = NED_ENU_Q * q_ned_aircraft * AIRCRAFT_BASELINK_Q``.

Quaternions are accepted as a mapping ``{x, y, z, w}`` (ROS ``geometry_msgs/Quaternion``) or
as a sequence ``[w, x, y, z]`` (MAVLink ``ATTITUDE_QUATERNION`` / ``q[4]`` order) and are
returned in the shape they came in. Vectors are ``{x, y, z}`` or ``[x, y, z]``, likewise.
Everything here is plain functions on floats, lists and dicts so that the route language
can call them as JMESPath functions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

Quat = tuple[float, float, float, float]
"""(w, x, y, z)"""

_HALF_SQRT2 = math.sqrt(0.5)
NED_ENU_Q: Quat = (0.0, _HALF_SQRT2, _HALF_SQRT2, 0.0)
"""quaternion_from_rpy(pi, 0, pi/2): +pi/2 about Down, then +pi about X."""
AIRCRAFT_BASELINK_Q: Quat = (0.0, 1.0, 0.0, 0.0)
"""quaternion_from_rpy(pi, 0, 0): FRD <-> FLU."""

HEADING_UNKNOWN = 65535
"""GLOBAL_POSITION_INT.hdg / VFR_HUD value meaning 'not known'."""


# -- scalar units -------------------------------------------------------------------------


def deg_e7_to_deg(value: float) -> float:
    return value / 1e7


def deg_to_deg_e7(value: float) -> int:
    return round(value * 1e7)


def mm_to_m(value: float) -> float:
    return value / 1e3


def m_to_mm(value: float) -> int:
    return round(value * 1e3)


def cm_to_m(value: float) -> float:
    """Also cm/s -> m/s (GLOBAL_POSITION_INT vx/vy/vz)."""
    return value / 1e2


def m_to_cm(value: float) -> int:
    """Also m/s -> cm/s."""
    return round(value * 1e2)


cmps_to_mps = cm_to_m
mps_to_cmps = m_to_cm


def cdeg_to_deg(value: float) -> float:
    return value / 1e2


def deg_to_cdeg(value: float) -> int:
    return round(value * 1e2)


def heading_cdeg_to_deg(value: float) -> float | None:
    """``hdg`` in cdeg, with UINT16_MAX meaning unknown (None rather than 655.35 deg)."""
    return None if value == HEADING_UNKNOWN else value / 1e2


def wrap_pi(angle: float) -> float:
    """Wrap to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


# -- vectors ------------------------------------------------------------------------------


def _vector(value: Any) -> tuple[float, float, float]:
    if isinstance(value, Mapping):
        return float(value["x"]), float(value["y"]), float(value["z"])
    x, y, z = value
    return float(x), float(y), float(z)


def _vector_like(template: Any, x: float, y: float, z: float) -> Any:
    if isinstance(template, Mapping):
        return {**template, "x": x, "y": y, "z": z}
    return [x, y, z]


def ned_to_enu(vector: Any) -> Any:
    """NED <-> ENU by reflection (MAVROS avoids the rotation so NaNs do not spread)."""
    x, y, z = _vector(vector)
    return _vector_like(vector, y, x, -z)


enu_to_ned = ned_to_enu


def aircraft_to_baselink(vector: Any) -> Any:
    """FRD <-> FLU body vectors: angular rates, body velocities, accelerations."""
    x, y, z = _vector(vector)
    return _vector_like(vector, x, -y, -z)


baselink_to_aircraft = aircraft_to_baselink


# -- quaternions --------------------------------------------------------------------------


def _quat(value: Any) -> Quat:
    if isinstance(value, Mapping):
        return float(value["w"]), float(value["x"]), float(value["y"]), float(value["z"])
    w, x, y, z = value
    return float(w), float(x), float(y), float(z)


def _quat_like(template: Any, q: Quat) -> Any:
    w, x, y, z = q
    if isinstance(template, Mapping):
        return {**template, "x": x, "y": y, "z": z, "w": w}
    return [w, x, y, z]


def quaternion_multiply(a: Sequence[float], b: Sequence[float]) -> Quat:
    """Hamilton product of (w, x, y, z) tuples."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quaternion_from_rpy(roll: float, pitch: float, yaw: float) -> dict[str, float]:
    """Rz(yaw) * Ry(pitch) * Rx(roll), as MAVROS/tf2; returned as ``{x, y, z, w}``."""
    return _quat_like({}, _quat_from_rpy(roll, pitch, yaw))


def _quat_from_rpy(roll: float, pitch: float, yaw: float) -> Quat:
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cy * cp * cr + sy * sp * sr,
        cy * cp * sr - sy * sp * cr,
        cy * sp * cr + sy * cp * sr,
        sy * cp * cr - cy * sp * sr,
    )


def rpy_from_quaternion(quaternion: Any) -> dict[str, float]:
    """ZYX Euler angles of a quaternion: roll, yaw in [-pi, pi], pitch in [-pi/2, pi/2]."""
    w, x, y, z = _quat(quaternion)
    norm = math.sqrt(w * w + x * x + y * y + z * z) or 1.0
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    sin_pitch = max(-1.0, min(1.0, 2.0 * (w * y - z * x)))
    return {
        "roll": math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y)),
        "pitch": math.asin(sin_pitch),
        "yaw": math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)),
    }


def quat_ned_aircraft_to_enu_baselink(quaternion: Any) -> Any:
    """Orientation of an FRD body in NED -> orientation of the FLU body in ENU."""
    q = quaternion_multiply(quaternion_multiply(NED_ENU_Q, _quat(quaternion)), AIRCRAFT_BASELINK_Q)
    return _quat_like(quaternion, q)


def quat_enu_baselink_to_ned_aircraft(quaternion: Any) -> Any:
    """Inverse of :func:`quat_ned_aircraft_to_enu_baselink`.

    Both static quaternions are involutions up to sign, so this is the same product; the
    result may differ from the original by an overall sign, which is the same rotation.
    """
    q = quaternion_multiply(quaternion_multiply(NED_ENU_Q, _quat(quaternion)), AIRCRAFT_BASELINK_Q)
    return _quat_like(quaternion, q)


def attitude_ned_to_enu(roll: float, pitch: float, yaw: float) -> dict[str, Any]:
    """ATTITUDE (aircraft body in NED, rad) -> ``{orientation: {x,y,z,w}, roll, pitch, yaw}``
    of base_link in ENU, as MAVROS ``imu/data`` would publish it.

    The ENU angles come from the quaternion rather than from shortcuts (roll, -pitch,
    pi/2 - yaw) so they stay consistent with the orientation at every attitude.
    """
    q = quaternion_multiply(quaternion_multiply(NED_ENU_Q, _quat_from_rpy(roll, pitch, yaw)), AIRCRAFT_BASELINK_Q)
    return {"orientation": _quat_like({}, q), **rpy_from_quaternion(q)}


FUNCTIONS = {
    name: globals()[name]
    for name in (
        "deg_e7_to_deg", "deg_to_deg_e7", "mm_to_m", "m_to_mm", "cm_to_m", "m_to_cm",
        "cmps_to_mps", "mps_to_cmps", "cdeg_to_deg", "deg_to_cdeg", "heading_cdeg_to_deg",
        "wrap_pi", "ned_to_enu", "enu_to_ned", "aircraft_to_baselink", "baselink_to_aircraft",
        "quaternion_from_rpy", "rpy_from_quaternion", "quat_ned_aircraft_to_enu_baselink",
        "quat_enu_baselink_to_ned_aircraft", "attitude_ned_to_enu",
    )
}
"""Name -> function, for registering them all as JMESPath functions."""
