"""The body's attitude from an IMU sample, compiled with numba (``cache=True``).

Every IMU sample, the ESO node reads the body's pitch θ and yaw ϕ from the IMU's
orientation, after its mounting, and (gyro estimator) the Euler rates θ̇, ϕ̇ from its angular
velocity (``nodes/hardware_inputs.body_attitude``): a dozen Python calls on ten floats, the
largest piece of the ESO's IMU callback after the estimator. Compiled, it is one call.

Nothing is written twice: numba compiles the rotations of :mod:`wip_runtime.rotations`
themselves (``register_jitable``), and :func:`attitude` composes them as
``body_pitch_yaw`` and ``body_pitch_yaw_rates`` do, with the same checks as tests: a sample
any check refuses (no orientation, a value not finite, a quaternion norm off 1, no angular
velocity where the rates are wanted) is :data:`NOT_TAKEN`, and the interpreter reads it
again and raises what it raises. numba's cache knows only this file's date, not theirs:
:func:`warm_up` compiles afresh when a digest of the sources differs from the one kept
beside the cache, and ``hardware_inputs.use_compiled_attitude`` compares the kernel with the
interpreter before using it.
"""

from __future__ import annotations

import math

import numba
from numba.extending import register_jitable
from wip_runtime import rotations

from . import compiled

#: The interpreter's functions the kernel compiles; their files make its sources' digest.
COMPILED_FUNCTIONS = (rotations.quaternion_norm, rotations.pitch_yaw_of_quaternion,
                      rotations.quaternion_multiply, rotations.rotate_vector_into,
                      rotations.euler_rates)
for _function in COMPILED_FUNCTIONS:
    register_jitable(_function)

#: What :func:`attitude` did: read the sample, or left it to the interpreter.
TAKEN, NOT_TAKEN = 0, 1
#: What :func:`attitude` returns for a sample it leaves to the interpreter.
_LEFT = (NOT_TAKEN, math.nan, math.nan, math.nan, math.nan)
#: One signature, compiled once: arguments of another type are converted or refused, never
#: compiled anew in a control tick.
_SIGNATURE = numba.types.Tuple((numba.int64,) + (numba.float64,) * 4)(
    *(numba.float64,) * 11, numba.boolean, numba.boolean, *(numba.float64,) * 3)


@register_jitable
def _finite(a: float, b: float, c: float, d: float) -> bool:
    return math.isfinite(a) and math.isfinite(b) and math.isfinite(c) and math.isfinite(d)


@numba.njit(_SIGNATURE, cache=True, nogil=True)
def attitude(x, y, z, w, wx, wy, wz, mx, my, mz, mw, mounted, with_rates, orientation_cov0,
             rates_cov0, norm_tolerance):
    """Return (what it did, θ, ϕ [rad], θ̇, ϕ̇ [rad/s]; the rates NaN without ``with_rates``).

    The orientation (x, y, z, w) and angular velocity (wx, wy, wz) [rad/s] of the IMU's
    frame, ``orientation_cov0`` and ``rates_cov0`` the first element of their covariances
    (−1: absent, REP 145); ``mounted``: the IMU frame is not base_link, and (mx, my, mz, mw)
    is the mounting's inverse q_mount⁻¹.
    """
    if orientation_cov0 == -1.0 or not _finite(x, y, z, w):
        return _LEFT
    if mounted:
        # body_pitch_yaw: the IMU's own quaternion checked, then q_body = q_imu ⊗ q_mount⁻¹.
        if abs(rotations.quaternion_norm(x, y, z, w) - 1.0) > norm_tolerance:
            return _LEFT
        x, y, z, w = rotations.quaternion_multiply((x, y, z, w), (mx, my, mz, mw))
        if not _finite(x, y, z, w):
            return _LEFT
    # messages.pitch_yaw_from_quaternion's check and decomposition.
    norm = rotations.quaternion_norm(x, y, z, w)
    if abs(norm - 1.0) > norm_tolerance:
        return _LEFT
    pitch, yaw = rotations.pitch_yaw_of_quaternion(x, y, z, w, norm)
    if not with_rates:
        return (TAKEN, pitch, yaw, math.nan, math.nan)
    # body_pitch_yaw_rates: ω_body = R_mount ω_imu, then the Euler rates at θ.
    if rates_cov0 == -1.0 or not _finite(wx, wy, wz, 0.0):
        return _LEFT
    if mounted:
        wx, wy, wz = rotations.rotate_vector_into((mx, my, mz, mw), (wx, wy, wz))
        if not _finite(wx, wy, wz, 0.0):
            return _LEFT
    pitch_rate, yaw_rate = rotations.euler_rates(pitch, wx, wy, wz)
    return (TAKEN, pitch, yaw, pitch_rate, yaw_rate)


def warm_up() -> None:
    """Load :func:`attitude` from numba's cache (or compile it).

    Compiled afresh if the sources it compiles changed since numba's cache was filled
    (:data:`SOURCES_STAMP` beside the cache holds their digest).
    """
    attitude(0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, True, True, 0.0, 0.0,
             1e-3)
    compiled.refresh_if_sources_changed(attitude.stats.cache_path, SOURCES_STAMP,
                                        sources_digest(), refresh)


#: The file beside numba's cache with the digest of the sources the kernel was compiled from.
SOURCES_STAMP = 'attitude_kernel.sources'


def sources_digest() -> str:
    """SHA-256 of the files whose functions the kernel compiles, and of this one."""
    return compiled.sources_digest(COMPILED_FUNCTIONS, __name__)


def refresh() -> None:
    """Compile :func:`attitude` afresh, replacing numba's cache of it (stale, say)."""
    attitude.recompile()
