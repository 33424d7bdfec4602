"""Pass criteria of a run: physical limits checked on its record, for campaigns and tests.

A :class:`Criteria` holds thresholds; ``None`` switches a criterion off. The defaults are
the hard limits every run must meet (the paper's constraints, eqs. (16)–(23)): no fall,
|τl|, |τr| ≤ 15 N·m, |Δτυ| ≤ 10 N·m per MPC step, no QP failure. Scenario files of the
robustness suite and campaign files add the physical criterion of their class (a speed
limit after a push, a holding offset, a tracking error, a decaying oscillation).

What is measured (true states, SI units):

- **path error**: distance from the true position to the reference *path* — the
  polyline of the reference positions of the run (sampled at the control rate, so
  the polyline's vertices are at most υr/200 apart: ≤ 7.5 mm at 1.5 m/s, and the
  nearest-vertex distance used here overestimates the distance to the path by at
  most half of that). This is what a user sees: how far the robot is off the path,
  whatever the time parametrisation of the reference (a reference that slows down
  when a limit binds is not penalised for being late).
- **position error**: distance to the reference *point* at the same time (eq. (9)'s
  ‖(x_e, y_e)‖), for stop-and-hold, where the point does not move.
- **pulse windows**: [t0, t0 + width + ``pulse_recovery_time``] of every pulse
  disturbance; tilt and speed limits are checked outside them ("back within
  ``pulse_recovery_time`` after a push").
- **final window**: the last ``final_window`` seconds of the run.
- **outcome** at an obstacle of the terrain (a bump or a kerb): ``fell``; ``refused``
  (the obstacle monitor named it and the trajectory generator's reference stepped back to
  the back-off point, core/obstacle_refusal.py); ``crossed`` (the axle passed it);
  ``stopped`` (none of these); '' without an obstacle. With ``refusal_passes`` a refused
  run is judged on the refusal (holding near the point held) instead of the path and
  the end of the reference, which the obstacle puts out of reach.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Optional

import numpy as np
from scipy.spatial import cKDTree

from wip_runtime.config import from_mapping, param, to_mapping
from wip_control.core.obstacle_refusal import back_off_point
from wip_control.core.runaway import RunawayGuard
from wip_sim.core.record import RunRecord

#: Numerical slack on hard limits: the QP is solved to 1e-6 and the mixer clips in
#: floating point, so a limit may be met to ~1e-9 but never exceeded by more.
HARD_LIMIT_TOLERANCE = 1e-6


@dataclasses.dataclass(frozen=True)
class Criteria:
    """Thresholds a run must meet; ``null`` (None) switches a criterion off."""

    no_fall: bool = param(True, '1', '|theta| must stay below the scenario fall_threshold')
    no_runaway_alarm: bool = param(True, '1', "the safety layer's runaway guard, fed the run's "
                                   'estimate and reference, must never fault (docs/safety.md)')
    max_wheel_torque: Optional[float] = param(
        15.0, 'N m', 'limit of |tau_l|, |tau_r| (commanded)', minimum=0.0)
    max_delta_tau_v: Optional[float] = param(
        None, 'N m', 'limit of |delta tau_v| between two MPC steps (eq. (23)); null: the '
        "controller's own, mpc.max_delta_torque or, where larger, mpc.impact_delta_torque",
        minimum=0.0)
    max_qp_failures: Optional[int] = param(
        0, '1', 'MPC ticks that used the fallback (QP not solved)', minimum=0)
    max_abs_theta: Optional[float] = param(
        None, 'rad', 'limit of |theta| over the whole run', minimum=0.0)
    max_abs_theta_outside_pulses: Optional[float] = param(
        None, 'rad', 'limit of |theta| outside the pulse windows', minimum=0.0)
    max_speed_outside_pulses: Optional[float] = param(
        None, 'm/s', 'limit of |v| outside the pulse windows (no run-away: back under the '
        'limit within pulse_recovery_time after a push)', minimum=0.0)
    max_speed: Optional[float] = param(
        None, 'm/s', 'limit of |v| over the whole run', minimum=0.0)
    pulse_recovery_time: float = param(
        3.0, 's', 'time after the end of a pulse disturbance during which the '
        '*_outside_pulses criteria are not checked', minimum=0.0)
    max_convergence_time: Optional[float] = param(
        None, 's', 'the path error must first reach convergence_radius by this time',
        minimum=0.0)
    convergence_radius: float = param(0.1, 'm', 'path error that counts as converged',
                                      minimum=0.0, exclusive_minimum=True)
    settle_time: float = param(10.0, 's', 'start of the window of the *_after_settle '
                               'criteria', minimum=0.0)
    max_rms_path_error_after_settle: Optional[float] = param(
        None, 'm', 'RMS distance to the path for t >= settle_time', minimum=0.0)
    max_path_error_after_settle: Optional[float] = param(
        None, 'm', 'largest distance to the path for t >= settle_time', minimum=0.0)
    final_window: float = param(10.0, 's', 'length of the final window of the run',
                                minimum=0.0, exclusive_minimum=True)
    max_final_position_error: Optional[float] = param(
        None, 'm', 'largest distance to the reference point in the final window '
        '(stop-and-hold offset)', minimum=0.0)
    max_final_path_error: Optional[float] = param(
        None, 'm', 'largest distance to the path in the final window', minimum=0.0)
    max_final_oscillation: Optional[float] = param(
        None, 'm', 'peak-to-peak of the distance rolled x_v in the final window, its '
        'linear trend removed (a decaying oscillation is small there)',
        minimum=0.0)
    max_final_abs_theta: Optional[float] = param(
        None, 'rad', 'limit of |theta| in the final window', minimum=0.0)
    refusal_passes: bool = param(
        False, '1', 'a run refused before an obstacle passes without the path and end '
        'criteria if it holds near the back-off point to the end (for obstacles at or '
        'above the height the torque lifts)')
    refusal_hold_radius: float = param(
        0.2, 'm', 'refusal_passes: largest distance to the back-off point in the final window '
        '(the back-off distance: it holds behind where the axle stopped)',
        minimum=0.0, exclusive_minimum=True)


def criteria_from_mapping(mapping: Any, path: str = 'criteria') -> Criteria:
    """Build :class:`Criteria` from YAML data; errors name the key (``criteria.max_x``)."""
    return from_mapping(Criteria, mapping, path)


def criteria_to_mapping(criteria: Criteria) -> dict[str, Any]:
    return to_mapping(criteria)


def _zoh(t_to: np.ndarray, t_from: np.ndarray, values: np.ndarray) -> np.ndarray:
    index = np.searchsorted(t_from, t_to, side='right') - 1
    return values[np.clip(index, 0, len(values) - 1)]


def pulse_mask(t: np.ndarray, scenario, recovery: float) -> np.ndarray:
    """Return True where ``t`` is outside every [t0, t0 + width + recovery] of a pulse."""
    outside = np.ones_like(t, dtype=bool)
    for channel in scenario.disturbances.channels():
        for c in channel:
            if c.kind == 'pulse':
                outside &= ~((t >= c.start_time) & (t <= c.start_time + c.width + recovery))
    return outside


def path_errors(record: RunRecord) -> tuple[np.ndarray, np.ndarray]:
    """(t, distance of the true position to the reference path) at the truth samples."""
    truth, reference = record['truth'], record['reference']
    path = np.column_stack((reference['x'], reference['y']))
    points = np.column_stack((truth['x'], truth['y']))
    if len(path) == 0:
        return truth['t'], np.full(len(points), np.nan)
    distance, _ = cKDTree(path).query(points)
    return truth['t'], distance


def _max(values: np.ndarray) -> float | None:
    return float(np.max(values)) if len(values) else None


def measure(record: RunRecord, scenario, metrics: dict, criteria: Criteria,
            obstacle=None) -> dict[str, Any]:
    """Return the quantities the criteria compare, measured on the run (None if not defined).

    ``obstacle``: the run's first blocking by an obstacle (``RunResult.obstacle``), if any.
    """
    truth = record['truth']
    t = truth['t']
    end = float(t[-1]) if len(t) else 0.0
    outside = pulse_mask(t, scenario, criteria.pulse_recovery_time)
    t_path, path_error = path_errors(record)
    reference = record['reference']
    xr = _zoh(t, reference['t'], reference['x']) if len(reference['t']) else np.nan * t
    yr = _zoh(t, reference['t'], reference['y']) if len(reference['t']) else np.nan * t
    position_error = np.hypot(xr - truth['x'], yr - truth['y'])
    converged = np.nonzero(path_error <= criteria.convergence_radius)[0]
    late = t >= criteria.settle_time
    final = t >= end - criteria.final_window
    # x_v against the reference's distance travelled, detrended: the oscillation of the
    # longitudinal loop about its (possibly moving) set point.
    x_v = truth['x_v']
    oscillation = None
    if np.count_nonzero(final) > 2:
        tf, xf = t[final], x_v[final]
        trend = np.polyval(np.polyfit(tf - tf[0], xf, 1), tf - tf[0])
        oscillation = float(np.ptp(xf - trend))
    return {
        'fell': bool(metrics['fell']),
        'max_wheel_torque': metrics['max_abs_wheel_torque_nm'],
        'max_delta_tau_v': metrics['max_abs_delta_tau_v_nm'],
        'delta_tau_limit': scenario.mpc.largest_delta_torque(),
        'qp_failures': metrics['qp_failures'],
        'max_abs_theta': _max(np.abs(truth['theta'])),
        'max_abs_theta_outside_pulses': _max(np.abs(truth['theta'][outside])),
        'max_speed': _max(np.abs(truth['v'])),
        'max_speed_outside_pulses': _max(np.abs(truth['v'][outside])),
        'convergence_time': float(t_path[converged[0]]) if len(converged) else None,
        'rms_path_error_after_settle': (float(np.sqrt(np.mean(path_error[late] ** 2)))
                                        if np.any(late) else None),
        'max_path_error_after_settle': _max(path_error[late]),
        'final_position_error': _max(position_error[final]),
        'final_path_error': _max(path_error[final]),
        'final_oscillation': oscillation,
        'final_abs_theta': _max(np.abs(truth['theta'][final])),
        'end_time': end,
        **runaway_replay(record),
        **obstacle_outcome(record, scenario, bool(metrics['fell']), obstacle, final),
    }


def obstacle_outcome(record: RunRecord, scenario, fell: bool, obstacle,
                     final: np.ndarray) -> dict[str, Any]:
    """Return the run's outcome at the terrain's obstacle and, if refused, how it holds.

    Refused: named by the obstacle monitor, then the generator's reference stepped back
    by at least 0.9 ``obstacle_back_off`` in one tick, and not past the obstacle over the
    whole final window (else crossed) (x_e: the held point replaced a
    reference ahead of the axle). The point held is the estimated pose of that tick
    moved back along its heading (``obstacle_refusal.back_off_point``);
    ``refusal_hold_error`` [m] is the true position's largest distance to it in the final
    window, ``final_speed`` [m/s] |mean υ| there (the net motion).
    """
    truth, terrain = record['truth'], scenario.plant.terrain
    out: dict[str, Any] = {'outcome': '', 'refused_at': None, 'refusal_hold_error': None,
                           'final_speed': _abs_mean(truth['v'][final])}
    back_off = scenario.trajectory_generator.obstacle_back_off
    if obstacle is not None and obstacle.reason and back_off > 0.0:
        command, estimate = record['command'], record['estimate']
        step = np.diff(command['x_e'], prepend=command['x_e'][:1])
        k = np.nonzero((command['t'] >= obstacle.since) & (step <= -0.9 * back_off))[0]
        if len(k) and len(estimate['t']) == len(command['t']):
            i = int(k[0])
            hold = back_off_point(float(estimate['x'][i]), float(estimate['y'][i]),
                                  float(estimate['phi'][i]), back_off)
            out['refused_at'] = float(command['t'][i])
            out['refusal_hold_error'] = _max(np.hypot(truth['x'][final] - hold.x,
                                                      truth['y'][final] - hold.y))
    if terrain.bump_height > 0.0:
        beyond = terrain.bump_position + 0.5 * terrain.bump_length
    else:
        beyond = terrain.step_position if terrain.step_height > 0.0 else None
    # A refusal that the vehicle went on past (core/obstacle_refusal.py: it ended with the
    # axle over the edge) is a crossing when the whole final window is past the obstacle.
    past = (beyond is not None and len(truth['x'][final])
            and float(np.min(truth['x'][final])) > beyond)
    if fell:
        out['outcome'] = 'fell'
    elif out['refused_at'] is not None and not past:
        out['outcome'] = 'refused'
    elif beyond is not None:
        out['outcome'] = 'crossed' if np.max(truth['x'], initial=-np.inf) > beyond else 'stopped'
    return out


def _abs_mean(values: np.ndarray) -> float | None:
    return abs(float(np.mean(values))) if len(values) else None


def runaway_replay(record: RunRecord) -> dict[str, Any]:
    """Return what the real-time safety layer's runaway guard would say of the run.

    The guard (``core/runaway.py``, its defaults) fed each control tick's estimate and
    reference, from t = 0 (a real-time run feeds it from the engagement on):
    ``runaway_growth`` [m] its largest growth, ``runaway_alarm`` its first verdict ('' if
    none), with the time.
    """
    estimate, reference = record['estimate'], record['reference']
    guard = RunawayGuard()
    alarm = ''
    columns = (estimate['t'], estimate['x'], estimate['y'], estimate['phi'], estimate['v'],
               reference['x'], reference['y'])
    if len(reference['t']) == len(estimate['t']):
        for t, x, y, phi, v, xr, yr in zip(*(c.tolist() for c in columns)):
            verdict = guard.update(t, x, y, phi, v, xr, yr)
            if verdict:
                alarm = f't = {t:.2f} s: {verdict}'
                break
    return {'runaway_growth': guard.largest_growth, 'runaway_alarm': alarm}


#: criterion field -> (measured key, kind); kind 'max': measured <= threshold.
_CHECKS = {
    'max_wheel_torque': ('max_wheel_torque', 'hard'),
    'max_delta_tau_v': ('max_delta_tau_v', 'hard'),
    'max_qp_failures': ('qp_failures', 'max'),
    'max_abs_theta': ('max_abs_theta', 'max'),
    'max_abs_theta_outside_pulses': ('max_abs_theta_outside_pulses', 'max'),
    'max_speed_outside_pulses': ('max_speed_outside_pulses', 'max'),
    'max_speed': ('max_speed', 'max'),
    'max_convergence_time': ('convergence_time', 'max'),
    'max_rms_path_error_after_settle': ('rms_path_error_after_settle', 'max'),
    'max_path_error_after_settle': ('max_path_error_after_settle', 'max'),
    'max_final_position_error': ('final_position_error', 'max'),
    'max_final_path_error': ('final_path_error', 'max'),
    'max_final_oscillation': ('final_oscillation', 'max'),
    'max_final_abs_theta': ('final_abs_theta', 'max'),
}


#: Criteria a refused run cannot meet: the obstacle keeps the path and its end out of reach.
_OUT_OF_REACH = ('max_convergence_time', 'max_rms_path_error_after_settle',
                 'max_path_error_after_settle', 'max_final_position_error',
                 'max_final_path_error')


def _refusal_failures(measured: dict[str, Any], criteria: Criteria) -> dict[str, str]:
    """Failures of a refused run's own criterion: it holds near the point, to the end."""
    error = measured.get('refusal_hold_error')
    if error is None or error > criteria.refusal_hold_radius:
        return {'refusal_hold_radius': (f'refusal_hold_error = {error} > '
                                        f'{criteria.refusal_hold_radius:g}')}
    return {}


def evaluate(measured: dict[str, Any], criteria: Criteria,
             duration: float | None = None) -> dict[str, str]:
    """Failed criteria -> a one-line reason; empty if the run passes.

    A criterion on a window the run never reached (it fell before ``settle_time``)
    or a quantity never reached (no convergence) fails, with its reason.
    """
    failures: dict[str, str] = {}
    refused = criteria.refusal_passes and measured.get('outcome') == 'refused'
    if refused:
        failures.update(_refusal_failures(measured, criteria))
    if criteria.no_fall and measured['fell']:
        failures['no_fall'] = f'fell at t = {measured["end_time"]:.2f} s'
    if criteria.no_runaway_alarm and measured.get('runaway_alarm') and not measured['fell']:
        failures['no_runaway_alarm'] = f'runaway guard at {measured["runaway_alarm"]}'
    for name, (key, kind) in _CHECKS.items():
        threshold = getattr(criteria, name)
        if threshold is None and name == 'max_delta_tau_v':
            threshold = measured.get('delta_tau_limit')   # the controller's own (19)
        if threshold is None or (refused and name in _OUT_OF_REACH):
            continue
        value = measured.get(key)
        if value is None or (isinstance(value, float) and math.isnan(value)):
            failures[name] = f'{key} not reached (limit {threshold:g})'
            continue
        slack = HARD_LIMIT_TOLERANCE if kind == 'hard' else 0.0
        if value > threshold + slack:
            failures[name] = f'{key} = {value:.4g} > {threshold:g}'
    if duration is not None and measured['end_time'] < duration - 1e-9 and 'no_fall' not in \
            failures and criteria.no_fall:
        failures['no_fall'] = f'run ended at t = {measured["end_time"]:.2f} s of {duration:g} s'
    return failures
