"""Metrics of one run, computed from a :class:`~wip_sim.core.record.RunRecord`.

The same function serves the in-process runner and ``scripts/report`` on a bag, so a
graph run and an in-process run are compared with identical arithmetic.

Definitions (all SI):

- position error: the true position against the reference, ‖(xr − x, yr − y)‖
  (equal to ‖(x_e, y_e)‖ of eq. (9), a rotation of it); heading error
  wrap(ϕr − ϕ). ``convergence_time_s`` is the first time the position error is
  ≤ 0.1 m (null if never); RMS and max are over t ≥ ``settle_time`` (10 s).
- ``max_abs_delta_tau_v_nm``: the largest change of the applied τυ between two MPC
  ticks (eq. (23)), whatever its origin (solution or fallback).
- ``eso_rms_error``: over t ≥ 1 s (after the observer's start-up, ε = 0.01 gives
  a bandwidth of 100 rad/s). The true lumped disturbance of a channel is what the
  ESO is meant to estimate: the true acceleration minus the nominal input term,
  f1 = ω̇ − g1 τω, f2 = υ̇ − g2 τυ, f3 = θ̈ − g3 τυ with the controllers' nominal
  g_i(θ) (eq. (1)); with the paper plant that is exactly fω1 + τd1 etc. The ESO's
  own 20 % error in ĝ1 therefore shows up as f1 error, as in the paper's Fig. 8.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from wip_control.core.angles import wrap_to_pi
from wip_control.core.model import input_gains
from wip_sim.core.plant import equation_model, Plant, plant_input_gains
from wip_sim.core.record import RunRecord

SETTLE_TIME_S = 10.0
CONVERGENCE_RADIUS_M = 0.1
ESO_START_S = 1.0
#: |θ| is allowed past the tilt limit for this long after a pulse disturbance [s].
PULSE_RECOVERY_S = 3.0


def _none_if_nan(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


def _rms(values: np.ndarray) -> float | None:
    return _none_if_nan(float(np.sqrt(np.mean(values ** 2)))) if len(values) else None


def _max_abs(values: np.ndarray) -> float | None:
    return _none_if_nan(float(np.max(np.abs(values)))) if len(values) else None


def _interp(t_to: np.ndarray, t_from: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Zero-order hold of (t_from, values) sampled at t_to (the signals are held)."""
    if len(values) == 0:  # A run that fell (or ended) before its first command.
        return np.full(len(t_to), np.nan)
    index = np.searchsorted(t_from, t_to, side='right') - 1
    return values[np.clip(index, 0, len(values) - 1)]


def true_lumped_disturbances(record: RunRecord, plant: Plant,
                             nominal_params) -> dict[str, np.ndarray]:
    """f1, f2, f3 as the ESO should see them, at the truth samples (see module doc)."""
    truth = record['truth']
    wheels = record['wheels']
    # Torques applied from t_k on: the command computed at t_k.
    tau_l = _interp(truth['t'], wheels['t'], wheels['tau_left'])
    tau_r = _interp(truth['t'], wheels['t'], wheels['tau_right'])
    # No command yet (a run shorter than one control period): tau is NaN, and so is f.
    theta = truth['theta']
    omd, vd, thdd = plant.accelerations_array(theta, truth['omega'], truth['v'],
                                              truth['theta_dot'], tau_l, tau_r)
    g1, g2, g3 = np.array([input_gains(nominal_params, th) for th in theta.tolist()]).T
    tau_v, tau_omega = tau_l + tau_r, tau_r - tau_l
    f = np.column_stack((omd + truth['d1'] - g1 * tau_omega,
                         vd + truth['d2'] - g2 * tau_v,
                         thdd + truth['d3'] - g3 * tau_v))
    return {'f1': f[:, 0], 'f2': f[:, 1], 'f3': f[:, 2]}


def pulse_windows(scenario) -> list[tuple[float, float]]:
    """[start, start + width + recovery] of every pulse disturbance in the scenario."""
    windows = []
    for channel in scenario.disturbances.channels():
        for component in channel:
            if component.kind == 'pulse':
                windows.append((component.start_time,
                                component.start_time + component.width + PULSE_RECOVERY_S))
    return windows


def compute_metrics(record: RunRecord, scenario, fell: bool | None = None,
                    duration_s: float | None = None) -> dict[str, Any]:
    """Return the metrics dictionary written to ``metrics.json`` (keys documented in README)."""
    metrics: dict[str, Any] = {'scenario': scenario.name}
    _tilt_metrics(metrics, record, scenario, fell, duration_s)
    _actuation_metrics(metrics, record)
    reference = record['reference']
    if 'truth' in record:
        _tracking_metrics(metrics, record, reference, scenario)
    else:
        for key in ('convergence_time_s', 'rms_position_error_m', 'max_position_error_m',
                    'rms_heading_error_rad', 'eso_rms_error', 'max_abs_v_mps'):
            metrics[key] = None
    return metrics


def _tilt_metrics(metrics: dict[str, Any], record: RunRecord, scenario, fell: bool | None,
                  duration_s: float | None) -> None:
    """Add whether it fell, the run's length and the tilt's extremes (truth, else estimate)."""
    has_truth = 'truth' in record
    tilt_source = record['truth'] if has_truth else record['estimate']
    theta = tilt_source['theta']
    t_tilt = tilt_source['t']
    if fell is None:
        fell = bool(len(theta) and np.max(np.abs(theta)) >= scenario.fall_threshold)
    metrics['fell'] = bool(fell)
    metrics['duration_s'] = float(duration_s if duration_s is not None else t_tilt[-1])
    metrics['tilt_source'] = 'truth' if has_truth else 'estimate'
    metrics['max_abs_theta_rad'] = _max_abs(theta)
    outside = np.ones_like(t_tilt, dtype=bool)
    for start, end in pulse_windows(scenario):
        outside &= ~((t_tilt >= start) & (t_tilt <= end))
    metrics['max_abs_theta_outside_pulse_windows_rad'] = _max_abs(theta[outside])
    metrics['theta_limit_exceeded_s'] = float(
        np.sum(np.abs(theta) > scenario.mpc.max_tilt) * (
            np.median(np.diff(t_tilt)) if len(t_tilt) > 1 else 0.0))


def _actuation_metrics(metrics: dict[str, Any], record: RunRecord) -> None:
    """Add the torques, the MPC's solves and the desired velocities' extremes."""
    wheels = record['wheels']
    metrics['max_abs_wheel_torque_nm'] = _max_abs(
        np.concatenate([wheels['tau_left'], wheels['tau_right']]))
    mpc = record['mpc']
    tau_v = mpc['tau_v']
    metrics['max_abs_delta_tau_v_nm'] = _max_abs(np.diff(np.concatenate([[0.0], tau_v])))
    metrics['max_abs_tau_v_nm'] = _max_abs(tau_v)
    metrics['qp_failures'] = int(np.sum(mpc['used_fallback'] > 0.5))
    metrics['mpc_ticks'] = int(len(tau_v))
    solve = mpc['solve_time']
    metrics['mpc_solve_time_s'] = {
        'p50': _none_if_nan(float(np.percentile(solve, 50))) if len(solve) else None,
        'p99': _none_if_nan(float(np.percentile(solve, 99))) if len(solve) else None,
        'max': _max_abs(solve)}
    metrics['max_slack'] = {'v': _max_abs(mpc['slack_v']), 'theta': _max_abs(mpc['slack_theta'])}

    command = record['command']
    metrics['max_abs_v_d_mps'] = _max_abs(command['v_d'])
    metrics['max_abs_omega_d_radps'] = _max_abs(command['omega_d'])
    metrics['max_abs_tau_omega_nm'] = _max_abs(record['arc']['tau_omega'])
    alpha = record['arc']['alpha_hat']
    metrics['alpha_hat_range'] = [_none_if_nan(float(np.min(alpha))),
                                  _none_if_nan(float(np.max(alpha)))] if len(alpha) else None


def _tracking_metrics(metrics: dict[str, Any], record: RunRecord, reference: dict,
                      scenario) -> None:
    """Add the tracking errors against the truth, the ESOs' errors and 1/g1's range."""
    truth = record['truth']
    metrics['max_abs_v_mps'] = _max_abs(truth['v'])
    t = truth['t']
    xr = _interp(t, reference['t'], reference['x'])
    yr = _interp(t, reference['t'], reference['y'])
    phir = _interp(t, reference['t'], reference['phi'])
    position_error = np.hypot(xr - truth['x'], yr - truth['y'])
    heading_error = np.array([wrap_to_pi(a) for a in phir - truth['phi']])
    converged = np.nonzero(position_error <= CONVERGENCE_RADIUS_M)[0]
    metrics['convergence_time_s'] = float(t[converged[0]]) if len(converged) else None
    late = t >= SETTLE_TIME_S
    metrics['rms_position_error_m'] = _rms(position_error[late])
    metrics['max_position_error_m'] = _max_abs(position_error[late])
    metrics['rms_heading_error_rad'] = _rms(heading_error[late])
    metrics['eso_rms_error'] = _eso_errors(record, scenario)
    # 1/g1 is monotonic in θ² for both models: its range is set by the extremes of |θ|.
    abs_theta = np.abs(truth['theta'])
    g1 = [plant_input_gains(scenario.plant.parameters, scenario.plant.model.model,
                            float(th))[0] for th in (np.min(abs_theta), np.max(abs_theta))]
    metrics['one_over_g1_range'] = [float(np.min(1 / np.array(g1))),
                                    float(np.max(1 / np.array(g1)))]


def _eso_errors(record: RunRecord, scenario) -> dict[str, float | None]:
    truth, estimate = record['truth'], record['estimate']
    plant = Plant(scenario.plant.parameters, equation_model(scenario.plant.model.model),
                  scenario.plant.model.wheel_friction)
    lumped = true_lumped_disturbances(record, plant, scenario.controller_model.parameters)
    t = estimate['t']
    errors = {}
    for name in ('omega', 'v', 'theta_dot'):
        true_values = _interp(t, truth['t'], truth[name])
        errors[name] = estimate[name] - true_values
    for name in ('f1', 'f2', 'f3'):
        errors[name] = estimate[name] - _interp(t, truth['t'], lumped[name])
    late = t >= ESO_START_S
    return {name: _rms(err[late]) for name, err in errors.items()}
