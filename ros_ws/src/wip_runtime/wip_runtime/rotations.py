"""Rotations of REP 103 frames: unit quaternions (x, y, z, w) and ZYX Euler angles.

Orientation quaternions are the ZYX (yaw, pitch, roll) composition R = Rz(ϕ) Ry(θ) Rx(roll)
(REP 103, as tf2). Plain arithmetic on floats and tuples, no check of their values (the
readers of messages check them: :mod:`wip_runtime.messages`) and no import but
:mod:`math`, so that the controllers' compiled kernels compile these functions themselves
(``numba.extending.register_jitable``): one formula for both.
"""

from __future__ import annotations

import math
from typing import Sequence

Quaternion = tuple[float, float, float, float]


def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> Quaternion:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (REP 103, as tf2)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def quaternion_norm(x: float, y: float, z: float, w: float) -> float:
    """|q| of the quaternion (x, y, z, w)."""
    return math.sqrt(x * x + y * y + z * z + w * w)


def pitch_yaw_of_quaternion(x: float, y: float, z: float, w: float,
                            norm: float) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] of the ZYX decomposition of q / ``norm``; yaw in (−π, π].

    ``norm`` is :func:`quaternion_norm` of q. Inverse of :func:`quaternion_from_euler` for
    |pitch| < π/2 (the round trip is exact to about 1e-16 rad); the roll is ignored (the
    WIP does not roll).
    """
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    sin_pitch = 2.0 * (w * y - z * x)
    pitch = math.asin(max(-1.0, min(1.0, sin_pitch)))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return pitch, yaw


def quaternion_multiply(a: Sequence[float], b: Sequence[float]) -> Quaternion:
    """Hamilton product a ⊗ b of (x, y, z, w) quaternions (rotation b first, then a)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def quaternion_conjugate(q: Sequence[float]) -> Quaternion:
    """Inverse rotation of a unit quaternion (x, y, z, w)."""
    x, y, z, w = q
    return (-x, -y, -z, w)


def rotate_vector_into(q: Sequence[float], v: Sequence[float]) -> tuple[float, float, float]:
    """Coordinates in the rotated frame of a vector given in the parent frame: R(q)ᵀ v."""
    x, y, z, w = q
    # R(q)^T v = conj(q) v q
    p = quaternion_multiply(quaternion_multiply((-x, -y, -z, w), (v[0], v[1], v[2], 0.0)),
                            (x, y, z, w))
    return p[0], p[1], p[2]


def euler_rates(pitch: float, wx: float, wy: float, wz: float) -> tuple[float, float]:
    """(θ̇, ϕ̇) [rad/s] from the body angular velocity (base_link axes, roll 0) at pitch θ.

    The body of R = Rz(ϕ) Ry(θ) turns at ω_body = (−ϕ̇ sin θ, θ̇, ϕ̇ cos θ) (a gyro's
    reading), so θ̇ = ω_y and ϕ̇ = ω_z cos θ − ω_x sin θ.
    """
    return wy, wz * math.cos(pitch) - wx * math.sin(pitch)
