"""Tunables of the safety layer (``core/safety.py``) and the value checks against them.

Not part of the paper [1]_; the defaults and their margins: docs/decisions/safety-layer.md.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses

from wip_runtime.config import param


#: Tolerance of the time comparisons (ages, settle time) [s]: absorbs the rounding of
#: sums of float times (1e-13 s at 1e3 s) and is far below any period (>= 1 ms).
TIME_TOLERANCE = 1e-9
#: Verdicts of :func:`lateness`.
FRESH, LATE, STALE = 'fresh', 'late', 'stale'


#: The same verdicts as numbers (:func:`lateness_code`, for compiled code).
FRESH_CODE, LATE_CODE, STALE_CODE = 0, 1, 2


def lateness_code(age: float, max_age: float, bridge: float) -> int:
    """Return the ride-through's verdict on an input received ``age`` [s] ago, as a code.

    FRESH within ``max_age``; LATE within ``max_age + bridge`` (bridged: DEGRADED); STALE
    beyond (zero torque). The mixer's monitor and the MPC node's real-time tick judge
    lateness by this one rule (docs/decisions/safety-layer.md).
    """
    if age <= max_age + TIME_TOLERANCE:
        return FRESH_CODE
    return LATE_CODE if age <= max_age + bridge + TIME_TOLERANCE else STALE_CODE


def lateness(age: float, max_age: float, bridge: float) -> str:
    """Return :func:`lateness_code`'s verdict as FRESH, LATE or STALE."""
    return (FRESH, LATE, STALE)[lateness_code(age, max_age, bridge)]


@dataclasses.dataclass(frozen=True)
class SafetyParams:
    """Tunables of the safety layer (ROS section ``safety`` of the torque_mixer node).

    The defaults and their margins: docs/decisions/safety-layer.md.
    """

    max_estimate_age: float = param(
        0.05, 's', 'zero torque when the last valid /wip/state_estimate was received longer '
        'ago than this', minimum=0.0, exclusive_minimum=True)
    max_yaw_torque_age: float = param(
        0.05, 's', 'zero torque when the last valid /wip/yaw_torque (ARC) was received '
        'longer ago than this', minimum=0.0, exclusive_minimum=True)
    max_drive_torque_age: float = param(
        0.25, 's', 'zero torque when the last valid /wip/drive_torque (MPC, 10 Hz) was '
        'received longer ago than this', minimum=0.0, exclusive_minimum=True)
    bridge_time: float = param(
        0.3, 's', 'ride-through: a late input is bridged this much longer (DEGRADED) before '
        'zero torque; default ln 4 / lambda of model (1); 0: none '
        '(docs/decisions/safety-layer.md)', minimum=0.0, maximum=1.0)
    max_estop_age: float = param(
        0.0, 's', 'if > 0: a heartbeat (/wip/heartbeat, or any /wip/estop message) must be '
        'received at least this often (zero torque otherwise); 0: not required', minimum=0.0)
    estop_hold_time: float = param(
        1.0, 's', 'reset is refused while an e-stop true was received this recently, even '
        'after a later false (a held button that keeps publishing true)', minimum=0.0,
        maximum=60.0)
    fall_threshold: float = param(
        0.35, 'rad', 'zero torque when the estimated tilt |theta_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True, maximum=1.5)
    max_speed_estimate: float = param(
        5.0, 'm/s', 'ESO divergence: zero torque when |v_hat| exceeds this', minimum=0.0,
        exclusive_minimum=True)
    max_yaw_rate_estimate: float = param(
        10.0, 'rad/s', 'ESO divergence: zero torque when |omega_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True)
    max_tilt_rate_estimate: float = param(
        10.0, 'rad/s', 'ESO divergence: zero torque when |theta_dot_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True)
    max_yaw_disturbance_estimate: float = param(
        50.0, 'rad/s^2', 'ESO divergence: zero torque when |f1_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True)
    max_longitudinal_disturbance_estimate: float = param(
        50.0, 'm/s^2', 'ESO divergence: zero torque when |f2_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True)
    max_tilt_disturbance_estimate: float = param(
        100.0, 'rad/s^2', 'ESO divergence: zero torque when |f3_hat| exceeds this',
        minimum=0.0, exclusive_minimum=True)
    max_mpc_fallbacks: int = param(
        3, '1', 'consecutive MPC outputs with status FALLBACK_SHIFTED_PLAN tolerated; one '
        'more is a fault', minimum=0)
    settle_time: float = param(
        0.25, 's', 'start-up and re-arming: every input present and valid and the ESO '
        'settled for this long before torque is sent', minimum=0.0)
    shadow_mode: bool = param(
        False, '1', 'compute and report the torques (on /wip/wheel_torques) but send zero '
        'to the base (/effort_controller/commands)')
    latch_faults: bool = param(
        False, '1', 'a fault stays until an explicit reset (like the e-stop) instead of '
        'clearing when its cause does')
