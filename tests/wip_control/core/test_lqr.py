"""Tests of the discrete LQR baseline (core/lqr.py).

What is checked, and against what:
- ``dlqr`` against the closed-form scalar Riccati solution, and against the Riccati
  difference equation iterated to convergence here (independent of scipy);
- the baseline's gain stabilises the augmented model it was designed on, and its torque
  obeys the MPC's hard limits at random states (saturation), NaN input ramps τ to 0;
- the selection ``mpc.controller: lqr`` reaches the runner, which keeps a constant push
  at stop-and-hold without a position offset (the MPC's offset-free target).
"""

import dataclasses
import math

import numpy as np
import pytest

from wip_runtime.config import ParamError
from wip_control.core.lqr import LongitudinalLqr, dlqr, make_longitudinal_controller
from wip_control.core.model import nominal_terms
from wip_control.core.mpc import LongitudinalMpc, MpcStatus
from wip_control.core.mpc_config import MpcParams
from wip_control.core.mpc_prediction import gravity_aware_state_matrix
from wip_description.params import ModelParams
from wip_sim.core.runner import run_scenario
from wip_sim.core.scenario import scenario_from_mapping

PARAMS = ModelParams()
CONFIG = MpcParams(controller='lqr')


def scalar_riccati(a, b, q, r):
    """Scalar DARE: its positive root p and the gain k.

    Positive root of b²p² + (r − a²r − qb²) p − qr = 0, the scalar DARE
    p = a²p − a²b²p²/(r + b²p) + q, and k = abp/(r + b²p).
    """
    c1 = r - a * a * r - q * b * b
    p = (-c1 + math.sqrt(c1 * c1 + 4.0 * b * b * q * r)) / (2.0 * b * b)
    return a * b * p / (r + b * b * p), p


@pytest.mark.parametrize('a, b, q, r', [(1.2, 0.5, 2.0, 0.3), (0.9, 1.0, 1.0, 1.0),
                                        (1.458, -0.0286, 50.0, 0.5)])
def test_dlqr_matches_the_scalar_closed_form(a, b, q, r):
    k, p = dlqr(np.array([[a]]), np.array([[b]]), np.array([[q]]), np.array([[r]]))
    k_ref, p_ref = scalar_riccati(a, b, q, r)
    assert p[0, 0] == pytest.approx(p_ref, rel=1e-9)
    assert k[0, 0] == pytest.approx(k_ref, rel=1e-9)
    assert abs(a - b * k[0, 0]) < 1.0  # the closed loop is stable


def test_dlqr_matches_the_iterated_riccati_recursion():
    # Double integrator at 0.1 s: P_{i+1} = Q + AᵀP_iA − AᵀP_iB(R + BᵀP_iB)⁻¹BᵀP_iA.
    ts = 0.1
    a = np.array([[1.0, ts], [0.0, 1.0]])
    b = np.array([[0.5 * ts * ts], [ts]])
    q, r = np.diag([1.0, 0.5]), np.array([[0.2]])
    p = q.copy()
    for _ in range(5000):
        p = q + a.T @ p @ a - a.T @ p @ b @ np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    k, p_dare = dlqr(a, b, q, r)
    np.testing.assert_allclose(p_dare, p, rtol=1e-8)
    np.testing.assert_allclose(k, np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a), rtol=1e-8)


def test_the_gain_stabilises_the_model_it_was_designed_on():
    lqr = LongitudinalLqr(PARAMS, CONFIG)
    # The open loop has the pendulum's unstable Euler pole 1 + Ts·sqrt(a_θθ) ≈ 1.46.
    a = gravity_aware_state_matrix(PARAMS, CONFIG.sampling_period)
    assert np.abs(np.linalg.eigvals(a)).max() > 1.4
    assert np.abs(np.linalg.eigvals(lqr.closed_loop)).max() < 1.0
    # Same stage weights as the MPC: Q = diag(q, 0) on (υ, θ, θ̇, τ), R = r.
    assert lqr.riccati.shape == (4, 4)
    assert np.all(np.linalg.eigvalsh(0.5 * (lqr.riccati + lqr.riccati.T)) > 0.0)


def test_torque_obeys_the_hard_limits_at_random_states():
    rng = np.random.default_rng(7)
    lqr = LongitudinalLqr(PARAMS, CONFIG)
    dmax = CONFIG.max_delta_torque
    for _ in range(500):
        v, theta, theta_dot = rng.uniform([-2, -0.2, -2], [2, 0.2, 2])
        terms = nominal_terms(PARAMS, theta, 0.0, theta_dot)
        tau_prev, limit = rng.uniform(-30, 30), rng.uniform(0, 30)
        lqr.reset(tau_prev)
        result = lqr.step(v, theta, theta_dot, terms.f2 + rng.uniform(-5, 5),
                          terms.f3 + rng.uniform(-2, 2), rng.uniform(-1.5, 1.5), limit)
        assert result.status == MpcStatus.SOLVED and not result.used_fallback
        assert abs(result.delta_tau) <= dmax + 1e-12
        reachable = max(limit, abs(tau_prev) - dmax)
        assert abs(result.tau_v) <= reachable + 1e-12
        assert result.tau_v == pytest.approx(tau_prev + result.delta_tau, abs=1e-12)
        assert result.predicted.shape == (CONFIG.prediction_horizon, 3)
        assert lqr.tau_previous == result.tau_v


def test_unsaturated_increment_is_minus_k_times_the_deviation_from_the_target():
    lqr = LongitudinalLqr(PARAMS, dataclasses.replace(CONFIG, offset_free=False))
    lqr.reset(0.4)
    terms = nominal_terms(PARAMS, 0.01, 0.0, 0.02)
    result = lqr.step(0.2, 0.01, 0.02, terms.f2, terms.f3, 0.3, 30.0)
    expected = -lqr.gain @ np.array([0.2 - 0.3, 0.01, 0.02, 0.4])
    assert abs(expected) < CONFIG.max_delta_torque  # not saturated
    assert result.delta_tau == pytest.approx(expected, abs=1e-12)


def test_invalid_input_ramps_the_torque_toward_zero():
    lqr = LongitudinalLqr(PARAMS, CONFIG)
    lqr.reset(25.0)
    result = lqr.step(float('nan'), 0.0, 0.0, 0.0, 0.0, 0.0, 30.0)
    assert result.status == MpcStatus.INPUT_INVALID and result.used_fallback
    assert result.tau_v == pytest.approx(25.0 - CONFIG.max_delta_torque)


def test_controller_selection_builds_either_and_rejects_others():
    assert isinstance(make_longitudinal_controller(PARAMS, MpcParams()), LongitudinalMpc)
    assert isinstance(make_longitudinal_controller(PARAMS, CONFIG), LongitudinalLqr)
    with pytest.raises(ParamError, match=r"^mpc\.controller: 'pid' is not one of"):
        scenario_from_mapping({'mpc': {'controller': 'pid'}})


@pytest.mark.slow
def test_lqr_in_the_runner_holds_a_push_without_offset():
    # Stop-and-hold, paper plant, a 0.3 m/s² push from 2 s: the LQR tracks the same
    # offset-free target as the MPC (measured offset 3e-4 m after 20 s).
    mapping = {'duration': 30.0, 'mpc': {'controller': 'lqr'},
               'reference': {'kind': 'hold'},
               'initial_state': {'theta': 0.0, 'pose': [0.0, 0.0, 0.0]},
               'disturbances': {'yaw': [], 'longitudinal': [
                   {'kind': 'step', 'amplitude': 0.3, 'start_time': 2.0}]}}
    result = run_scenario(scenario_from_mapping(mapping))
    truth = result.record['truth']
    assert not result.fell
    assert np.abs(truth['x'][truth['t'] > 20.0]).max() <= 0.05
    wheels = result.record['wheels']
    assert np.abs(np.r_[wheels['tau_left'], wheels['tau_right']]).max() <= 15.0 + 1e-9
    assert np.abs(np.diff(np.r_[0.0, result.record['mpc']['tau_v']])).max() <= 10.0 + 1e-9
