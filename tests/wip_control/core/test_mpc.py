"""Tests of the longitudinal/tilt MPC, eqs. (16)–(23) (core/mpc.py, mpc_prediction.py, qp.py).

What is checked, and against what:
- the condensed prediction against an explicit Euler simulation of x(k+1) = A x + B τ + c
  written out here from docs/paper.md §5's formulas (not from the code's matrices);
- the unconstrained solution against the closed form (G̃ᵀQG̃ + R)⁻¹ G̃ᵀQ(ȳr − ȳ_free);
- at random realistic states: every hard constraint, and the optimum against DAQP (an
  exact active-set solver) on the same QP, whose own KKT conditions are checked too;
- closed loops with perfect state knowledge on the paper plant (1): the paper's literal
  G̃ falls, the adopted gravity-aware prediction balances and tracks;
- the fallbacks: failed solve (injected and real), NaN input, unreachable torque limit.
"""

import dataclasses
import math
import warnings

import daqp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from longitudinal_mpc import simulate_longitudinal
from wip_tools.analysis.bench_mpc import STEP_KEYS, bench_mpc_against_daqp
from wip_runtime.config import ParamError, from_mapping
from wip_control.core.model import input_gains, nominal_terms
from wip_control.core.mpc import LongitudinalMpc, MpcInputError, MpcStatus
from wip_control.core.mpc_config import MpcParams, PAPER_MPC_SETTINGS
from wip_control.core.mpc_plan import MpcResult
from wip_control.core.mpc_prediction import CondensedPrediction
from wip_control.core.mpc_qp import TickData
from wip_control.core.mpc_reference import reference_qp
from wip_description.params import ModelParams
from wip_control.core.qp import QpSolution, make_solver

PARAMS = ModelParams()
# Single ticks of the formulation: without the start-up rule (disturbance_startup_time),
# which replaces the first ticks' estimates; it has tests of its own below.
CONFIG = MpcParams(disturbance_startup_time=0.0)
TS = CONFIG.sampling_period
NP, NC = CONFIG.prediction_horizon, CONFIG.control_horizon
DMAX = CONFIG.max_delta_torque

# ProxSuite stops when the primal and dual residuals are below eps_abs + eps_rel·(norms)
# and checks no complementarity, so there is no sharp a-priori bound on its distance to
# the optimum; the tolerances are measured ones with margin. The first increment (the
# torque applied) is the best determined: at most 2.1e-5 N m over 6000 random states.
# The tail of the plan is weighted less (cond(H) ≈ 4e4): at most 3.7e-4 N m over those
# 6000, and 1.34e-3 N m at a state hypothesis found (θ = θ̇ = f3 = 0, υd = 0, τ(k−1) 22 N m,
# limit 23 N m). 5e-3 N m is 2e-4 of the torque range, far below any motor's resolution.
FIRST_INCREMENT_TOL = 1e-4
SOLUTION_TOL = 5e-3
# Hard limits hold up to ProxSuite's primal residual (eps_abs = 1e-6 N m plus eps_rel
# times norms of ~1e2 N m); the applied torque is clipped exactly.
CONSTRAINT_TOL = 1e-5


def state_matrix_from_spec(prediction):
    """Return A of docs/paper.md §5, written out independently of mpc_prediction.py."""
    p = PARAMS
    a = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, TS], [0.0, 0.0, 1.0]])
    if prediction == 'gravity_aware':
        omega0 = p.effective_mass * p.pitch_inertia - (p.body_mass * p.com_height) ** 2
        a[0, 1] = -TS * p.body_mass ** 2 * p.com_height ** 2 * p.gravity / omega0
        a[2, 1] = TS * p.effective_mass * p.body_mass * p.gravity * p.com_height / omega0
    return a


def euler_rollout(x0, f2, f3, g2, g3, tau_previous, plan, prediction='gravity_aware'):
    """(Np, 3) states x(k+1..k+Np) of the Euler model with τ(k+i) = τ(k−1) + Σ_{j≤i} Δτ."""
    a = state_matrix_from_spec(prediction)
    a_paper = state_matrix_from_spec('paper')
    x0 = np.asarray(x0, dtype=float)
    c = TS * np.array([f2, 0.0, f3]) - (a - a_paper) @ x0
    b = TS * np.array([g2, 0.0, g3])
    x, tau, out = x0.copy(), tau_previous, []
    for i in range(NP):
        if i < len(plan):
            tau += plan[i]
        x = a @ x + b * tau + c
        out.append(x)
    return np.array(out)


def realistic_state(v, theta, theta_dot, d2, d3):
    """Estimates as an ideal ESO would give them: f̂ = f(x) of eq. (1) + disturbance."""
    terms = nominal_terms(PARAMS, theta, 0.0, theta_dot)
    return dict(v_hat=v, theta_hat=theta, theta_dot_hat=theta_dot, f2_hat=terms.f2 + d2,
                f3_hat=terms.f3 + d3)


# ---------------------------------------------------------------- prediction

@pytest.mark.parametrize('seed', range(5))
def test_condensed_prediction_equals_euler_simulation(seed):
    rng = np.random.default_rng(seed)
    pred = CondensedPrediction(PARAMS, TS, NP, NC, 'gravity_aware')
    x0 = rng.uniform([-1.5, -0.1, -1.0], [1.5, 0.1, 1.0])
    f2, f3, tau_prev = rng.uniform(-10, 10), rng.uniform(-3, 3), rng.uniform(-30, 30)
    _, g2, g3 = input_gains(PARAMS, x0[1])
    plan = rng.uniform(-DMAX, DMAX, NC)
    condensed = (pred.input_matrix(g2, g3) @ plan
                 + pred.free_response(x0, f2, f3, g2, g3, tau_prev)).reshape(NP, 3)
    expected = euler_rollout(x0, f2, f3, g2, g3, tau_prev, plan)
    # Both are sums of ≤ 20 products of O(1..100) numbers: round-off ~1e-13.
    np.testing.assert_allclose(condensed, expected, rtol=0, atol=1e-10)


def test_first_predicted_step_matches_the_paper_one_step_model():
    # The gravity terms are compensated in c: x(k+1) must be eq. (17) exactly.
    pred = CondensedPrediction(PARAMS, TS, NP, NC, 'gravity_aware')
    x0, f2, f3, tau = np.array([0.3, 0.07, -0.2]), 1.5, -2.0, 4.0
    _, g2, g3 = input_gains(PARAMS, x0[1])
    first = pred.free_response(x0, f2, f3, g2, g3, tau)[:3]
    paper = np.array([x0[0] + TS * (f2 + g2 * tau), x0[1] + TS * x0[2],
                      x0[2] + TS * (f3 + g3 * tau)])
    np.testing.assert_allclose(first, paper, rtol=0, atol=1e-14)


def test_paper_prediction_is_the_literal_one_step_gain_without_propagation():
    pred = CondensedPrediction(PARAMS, TS, NP, NC, 'paper')
    g2, g3 = 0.25, -0.29
    gt = pred.input_matrix(g2, g3).reshape(NP, 3, NC)
    for i in range(NP):
        for j in range(NC):
            expected = TS * np.array([g2, 0.0, g3]) if j <= i else np.zeros(3)
            np.testing.assert_array_equal(gt[i, :, j], expected)
    # Hence the θ rows do not depend on the decision variable at all (docs/paper.md §5).
    assert not np.any(gt[:, 1, :])
    # Its free response is the held-τ trajectory of the paper's A.
    x0, f2, f3, tau = np.array([0.2, 0.05, 0.1]), 0.5, 1.0, 3.0
    np.testing.assert_allclose(
        pred.free_response(x0, f2, f3, g2, g3, tau).reshape(NP, 3),
        euler_rollout(x0, f2, f3, g2, g3, tau, np.zeros(NC), 'paper'), rtol=0, atol=1e-10)


def test_mpc_reports_the_prediction_of_the_applied_plan():
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(2.0)
    state = realistic_state(0.4, 0.04, -0.1, 0.3, 0.0)
    result = mpc.step(**state, v_d=0.8, tau_limit=30.0)
    assert result.status == MpcStatus.SOLVED
    _, g2, g3 = input_gains(PARAMS, state['theta_hat'])
    expected = euler_rollout([state['v_hat'], state['theta_hat'], state['theta_dot_hat']],
                             state['f2_hat'], state['f3_hat'], g2, g3, 2.0, result.plan)
    assert result.predicted.shape == (NP, 3)
    np.testing.assert_allclose(result.predicted, expected, rtol=0, atol=1e-10)
    assert result.tau_v == pytest.approx(2.0 + result.plan[0], abs=1e-12)  # eq. (23)
    assert mpc.tau_previous == result.tau_v


# ---------------------------------------------------------------- closed form

def test_unconstrained_solution_equals_closed_form():
    far = dataclasses.replace(CONFIG, max_drive_torque=1e6, max_delta_torque=1e6,
                              max_speed=1e3, max_tilt=1e3)
    mpc = LongitudinalMpc(PARAMS, far)
    tau_prev = 1.0
    mpc.reset(tau_prev)
    state = realistic_state(0.2, 0.03, 0.05, 0.2, 0.1)
    result = mpc.step(**state, v_d=0.6, tau_limit=1e6)
    assert result.status == MpcStatus.SOLVED
    # Closed form from an explicit simulation (independent of the code's matrices).
    x0 = [state['v_hat'], state['theta_hat'], state['theta_dot_hat']]
    _, g2, g3 = input_gains(PARAMS, state['theta_hat'])
    free = euler_rollout(x0, state['f2_hat'], state['f3_hat'], g2, g3, tau_prev,
                         np.zeros(NC)).reshape(-1)
    gt = np.column_stack([
        euler_rollout(x0, state['f2_hat'], state['f3_hat'], g2, g3, tau_prev,
                      np.eye(NC)[j]).reshape(-1) - free for j in range(NC)])
    q = np.diag(np.tile(CONFIG.output_weights, NP))
    # Offset-free: the tilt reference is the steady-state target θs (checked on its own
    # in test_offset_free_target_balances_the_estimated_constant_disturbance).
    reference = np.tile([0.6, result.target_theta, 0.0], NP)
    expected = np.linalg.solve(gt.T @ q @ gt + CONFIG.input_weight * np.eye(NC),
                               gt.T @ q @ (reference - free))
    # Strongly convex (λmin(H) ≥ 2): a dual residual ≤ eps_abs = 1e-6 moves z by ≤ 5e-7.
    np.testing.assert_allclose(result.plan, expected, rtol=0, atol=1e-5)
    # The same from the QP the MPC built: −H⁻¹g on the Δτ block.
    qp = mpc.last_qp
    np.testing.assert_allclose(-np.linalg.solve(qp.H[:NC, :NC], qp.g[:NC]), expected,
                               rtol=1e-9, atol=1e-9)
    assert abs(result.slack_v) < CONSTRAINT_TOL and abs(result.slack_theta) < CONSTRAINT_TOL


# ---------------------------------------------------------------- random states

def daqp_reference(qp):
    """Exact optimum of the MPC's QP by DAQP, with its KKT conditions verified."""
    n = qp.H.shape[0]
    z, objective, flag, info = daqp.solve(qp.H, qp.g, qp.C, np.r_[qp.ub, qp.u],
                                          np.r_[qp.lb, qp.l])
    assert flag == 1
    lam = info['lam']
    lam_box, lam_rows = lam[:n], lam[n:]
    gradient = qp.H @ z + qp.g
    scale = max(1.0, np.abs(gradient).max(), np.abs(qp.g).max())
    # Stationarity Hz + g + λ_box + Cᵀλ = 0 (DAQP: λ > 0 at an upper, < 0 at a lower
    # bound), to round-off relative to the gradient's size.
    assert np.abs(gradient + lam_box + qp.C.T @ lam_rows).max() <= 1e-8 * scale
    # Feasibility and activity up to DAQP's primal tolerance (1e-6, absolute).
    primal_tol = daqp.Model().settings['primal_tol']
    rows, box = qp.C @ z, z
    for value, lower, upper, multiplier in ((rows, qp.l, qp.u, lam_rows),
                                            (box, qp.lb, qp.ub, lam_box)):
        assert np.all(value <= upper + primal_tol) and np.all(value >= lower - primal_tol)
        # Complementarity: a non-zero multiplier only on an active bound of its sign.
        active_upper = np.isclose(value, upper, rtol=0, atol=primal_tol)
        active_lower = np.isclose(value, lower, rtol=0, atol=primal_tol)
        assert np.all((multiplier <= 1e-9 * scale) | active_upper)
        assert np.all((multiplier >= -1e-9 * scale) | active_lower)
    return z, objective, gradient


# derandomize: the same 300 states on every run (a random run once found a first increment
# 1.4e-4 N m from DAQP's with the per-step-slack QP; 4000 uniform states: at most 2.2e-5).
@settings(max_examples=300, deadline=None, derandomize=True)
@given(v=st.floats(-1.8, 1.8), theta=st.floats(-0.15, 0.15), theta_dot=st.floats(-1.0, 1.0),
       d2=st.floats(-12.0, 12.0), d3=st.floats(-2.0, 2.0), v_d=st.floats(-1.5, 1.5),
       tau_previous=st.floats(-30.0, 30.0), tau_limit=st.floats(0.0, 30.0))
def test_random_states_respect_hard_limits_and_match_daqp(v, theta, theta_dot, d2, d3, v_d,
                                                          tau_previous, tau_limit):
    # Ranges: |υ| a little beyond its limit, |θ| up to 1.5 θmax, f̂ = f(x) of (1) plus a
    # disturbance up to the paper's 10 m/s² push; τ(k−1) anywhere in ±30 N m, also
    # beyond a shrunken limit.
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(tau_previous)
    result = mpc.step(**realistic_state(v, theta, theta_dot, d2, d3), v_d=v_d,
                      tau_limit=tau_limit)
    assert result.status == MpcStatus.SOLVED and not result.used_fallback
    plan = result.plan
    assert np.all(np.abs(plan) <= DMAX + CONSTRAINT_TOL)
    taus = tau_previous + np.cumsum(plan)
    # |τ(k+j)| ≤ τlim, relaxed to the reachable max(τlim, |τ(k−1)| − (j+1)Δτmax).
    reachable = np.maximum(tau_limit, abs(tau_previous) - DMAX * np.arange(1, NC + 1))
    assert np.all(np.abs(taus) <= reachable + CONSTRAINT_TOL)
    assert abs(result.tau_v) <= reachable[0] + 1e-12  # applied torque: clipped exactly
    assert abs(result.delta_tau) <= DMAX + 1e-12
    assert result.slack_v >= -CONSTRAINT_TOL and result.slack_theta >= -CONSTRAINT_TOL

    qp = mpc.last_qp
    z_ref, objective_ref, gradient_ref = daqp_reference(qp)
    z = np.r_[plan, mpc.last_solution.z[NC:]]  # every per-step slack
    assert result.slack_v == pytest.approx(z[NC:NC + NP].max())
    assert abs(z[0] - z_ref[0]) <= FIRST_INCREMENT_TOL
    assert np.abs(z[:NC] - z_ref[:NC]).max() <= SOLUTION_TOL
    # Objective: J(z) − J(z*) = ∇J(z*)ᵀΔz + ½ΔzᵀHΔz, so with ‖Δz‖∞ ≤ δ it is bounded by
    # ‖∇J(z*)‖₁ δ + ½ λmax(H) n δ² (δ from the solution difference actually found).
    delta = max(np.abs(z - z_ref).max(), 1e-12)
    bound = (np.abs(gradient_ref).sum() * delta
             + 0.5 * np.linalg.eigvalsh(qp.H)[-1] * len(z) * delta ** 2)
    objective = 0.5 * z @ qp.H @ z + qp.g @ z
    assert abs(objective - objective_ref) <= bound + 1e-9 * (1.0 + abs(objective_ref))


def test_daqp_backend_gives_the_same_plan_as_proxsuite():
    rng = np.random.default_rng(3)
    prox = LongitudinalMpc(PARAMS, CONFIG)
    exact = LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, backend='daqp'))
    for _ in range(20):
        tau_prev = rng.uniform(-20, 20)
        state = realistic_state(*rng.uniform([-1.5, -0.1, -0.5, -5, -1], [1.5, 0.1, 0.5, 5, 1]))
        v_d, limit = rng.uniform(-1, 1), rng.uniform(5, 30)
        prox.reset(tau_prev)
        exact.reset(tau_prev)
        a = prox.step(**state, v_d=v_d, tau_limit=limit)
        b = exact.step(**state, v_d=v_d, tau_limit=limit)
        assert a.status == b.status == MpcStatus.SOLVED
        np.testing.assert_allclose(a.plan, b.plan, rtol=0, atol=SOLUTION_TOL)


# ---------------------------------------------------------------- soft limits, pushes

def test_qp_stays_feasible_after_a_hard_push():
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(0.0)
    steady = realistic_state(0.5, 0.0, 0.0, 0.0, 0.0)
    for _ in range(5):
        mpc.step(**steady, v_d=0.5, tau_limit=30.0)
    # The collision: υ̂ jumps by +1 m/s beyond υmax and the ESO sees f̂2 = 10 m/s².
    pushed = realistic_state(1.5 + 0.5, 0.0, 0.0, 10.0, 0.0)
    result = mpc.step(**pushed, v_d=0.5, tau_limit=30.0)
    assert result.status == MpcStatus.SOLVED and not result.used_fallback
    assert result.slack_v > 0.1  # the soft speed limit absorbs what cannot be helped
    assert abs(result.delta_tau) <= DMAX + 1e-12 and abs(result.tau_v) <= 30.0


def test_torque_beyond_a_shrunken_limit_returns_at_the_increment_limit():
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(28.0)
    result = mpc.step(**realistic_state(0.0, 0.0, 0.0, 0.0, 0.0), v_d=0.0, tau_limit=5.0)
    assert result.status == MpcStatus.SOLVED
    # Unreachable in one step: the fastest way back, 28 − 10 = 18 N m, then 8, then ≤ 5.
    assert result.tau_v == pytest.approx(18.0, abs=CONSTRAINT_TOL)
    taus = 28.0 + np.cumsum(result.plan)
    assert taus[1] <= 8.0 + CONSTRAINT_TOL and np.all(np.abs(taus[2:]) <= 5.0 + CONSTRAINT_TOL)


# ---------------------------------------------------------------- closed loop

def test_paper_literal_prediction_falls_and_gravity_aware_balances():
    # Perfect state knowledge, f̂ = true f of (1), θ(0) = 0.05 rad, υd = 0.5 m/s, 10 s.
    literal = simulate_longitudinal(PARAMS, dataclasses.replace(CONFIG, prediction='paper'),
                                    duration=10.0, theta_initial=0.05, v_d=0.5)
    over = np.abs(literal.theta) > 0.5
    assert over.any(), 'the literal G̃ of (18) was expected to lose the pendulum'
    assert literal.t[np.argmax(over)] < 3.0  # docs/paper.md §5: falls within about 1.5 s

    adopted = simulate_longitudinal(PARAMS, CONFIG, duration=10.0, theta_initial=0.05,
                                    v_d=0.5)
    assert not adopted.fell
    assert np.abs(adopted.theta).max() <= CONFIG.max_tilt
    assert all(r.status == MpcStatus.SOLVED for r in adopted.results)
    # Tracks the constant υd: after 5 s within 1 cm/s (a type-1 loop through Δτ; the
    # measured error is ~1e-5 m/s at 10 s).
    settled = adopted.t >= 5.0
    assert np.abs(adopted.v[settled] - 0.5).max() < 0.01


# ---------------------------------------------------------------- fallbacks

class FailingSolver:
    """Stands in for ProxSuite, failing after ``successes`` real solves.

    Stands in for ProxSuite: after ``successes`` real solves, every solve reports
    MAX_ITER with a garbage iterate.
    """

    def __init__(self, successes=0):
        sizes = LongitudinalMpc(PARAMS, CONFIG)
        self.n = sizes.n_variables
        self.real = make_solver('proxsuite', sizes.n_variables, sizes.n_constraints,
                                CONFIG.qp_settings())
        self.successes = successes

    def solve(self, *qp):
        if self.successes > 0:
            self.successes -= 1
            return self.real.solve(*qp)
        return QpSolution(np.full(self.n, np.nan), MpcStatus.MAX_ITER_REACHED, 1000)

    def reset(self):
        self.real.reset()


def test_failed_solve_applies_the_shifted_previous_plan():
    mpc = LongitudinalMpc(PARAMS, CONFIG, solver=FailingSolver(successes=1))
    mpc.reset(0.0)
    state = realistic_state(0.0, 0.05, 0.0, 0.0, 0.0)
    first = mpc.step(**state, v_d=0.5, tau_limit=30.0)
    assert first.status == MpcStatus.SOLVED
    second = mpc.step(**state, v_d=0.5, tau_limit=30.0)
    assert second.used_fallback and second.status == MpcStatus.MAX_ITER_REACHED
    assert second.status_text == 'MAX_ITER_REACHED'
    assert second.delta_tau == pytest.approx(first.plan[1], abs=1e-12)
    np.testing.assert_allclose(second.plan, np.r_[first.plan[1:], 0.0], atol=1e-12)
    third = mpc.step(**state, v_d=0.5, tau_limit=30.0)
    assert third.delta_tau == pytest.approx(first.plan[2], abs=1e-12)
    assert math.isnan(third.slack_v)
    assert third.tau_v == pytest.approx(first.tau_v + first.plan[1] + first.plan[2])


def test_failed_solve_without_a_plan_holds_the_torque_within_the_limits():
    mpc = LongitudinalMpc(PARAMS, CONFIG, solver=FailingSolver())
    mpc.reset(25.0)
    state = realistic_state(0.0, 0.0, 0.0, 0.0, 0.0)
    held = mpc.step(**state, v_d=0.0, tau_limit=30.0)
    assert held.used_fallback and held.delta_tau == 0.0 and held.tau_v == 25.0
    clipped = mpc.step(**state, v_d=0.0, tau_limit=10.0)  # limit shrank below τ(k−1)
    assert clipped.tau_v == pytest.approx(15.0) and clipped.delta_tau == pytest.approx(-DMAX)


def test_real_solver_failure_is_reported_and_falls_back():
    # One outer iteration is not enough for this QP: ProxSuite returns MAX_ITER.
    mpc = LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, max_iter=1, max_inner_iter=1))
    mpc.reset(3.0)
    result = mpc.step(**realistic_state(1.0, 0.08, 0.3, 2.0, 0.5), v_d=-0.5, tau_limit=30.0)
    assert result.status == MpcStatus.MAX_ITER_REACHED and result.used_fallback
    assert result.tau_v == 3.0 and result.iterations >= 1


def test_invalid_input_ramps_the_torque_toward_zero_without_solving():
    mpc = LongitudinalMpc(PARAMS, CONFIG, solver=FailingSolver())
    mpc.reset(25.0)
    state = realistic_state(0.0, 0.0, 0.0, 0.0, 0.0)
    state['theta_hat'] = math.nan
    taus = [mpc.step(**state, v_d=0.0, tau_limit=30.0) for _ in range(4)]
    assert [r.tau_v for r in taus] == [15.0, 5.0, 0.0, 0.0]
    assert all(r.status == MpcStatus.INPUT_INVALID and r.used_fallback for r in taus)
    assert np.isnan(taus[0].predicted).all()
    bad_limit = realistic_state(0.0, 0.0, 0.0, 0.0, 0.0)
    assert mpc.step(**bad_limit, v_d=0.0, tau_limit=math.inf).status == MpcStatus.INPUT_INVALID
    with pytest.raises(MpcInputError, match='tau_limit'):
        mpc.step(**bad_limit, v_d=0.0, tau_limit=-1.0)
    with pytest.raises(MpcInputError, match='tau_previous'):
        mpc.reset(math.nan)


# ---------------------------------------------------------------- config, result, bench

def test_config_from_mapping_checks_keys_and_horizons():
    config = from_mapping(MpcParams, {'prediction_horizon': 30, 'output_weights': [1, 10, 1]},
                          'mpc')
    assert config.prediction_horizon == 30 and config.output_weights == (1.0, 10.0, 1.0)
    with pytest.raises(ParamError, match='mpc.control_horizon'):
        from_mapping(MpcParams, {'control_horizon': 25}, 'mpc')
    with pytest.raises(ParamError, match='mpc.prediction: '):
        from_mapping(MpcParams, {'prediction': 'linear'}, 'mpc')
    with pytest.raises(ParamError, match='mpc.epsilon: unknown key'):
        from_mapping(MpcParams, {'epsilon': 0.1}, 'mpc')
    with pytest.raises(ParamError, match=r'^mpc\.speed_limit_first_step: must be <= '):
        from_mapping(MpcParams, {'speed_limit_first_step': 21}, 'mpc')
    with pytest.raises(ParamError, match=r"^mpc\.soft_limits: 'max' is not one of"):
        from_mapping(MpcParams, {'soft_limits': 'max'}, 'mpc')
    # The paper's formulation is one mapping of ordinary keys.
    paper = from_mapping(MpcParams, dict(PAPER_MPC_SETTINGS), 'mpc')
    assert paper.soft_limits == 'worst_case' and not paper.offset_free


def test_result_fields_are_what_the_runner_records():
    assert MpcResult._fields[:10] == (
        'tau_v', 'delta_tau', 'status', 'iterations', 'solve_time_s', 'build_time_s',
        'slack_v', 'slack_theta', 'used_fallback', 'predicted')
    assert int(MpcStatus.SOLVED) == 0 and MpcStatus(8).name == 'INPUT_INVALID'


def test_bench_times_both_solvers_on_the_same_qps():
    run = simulate_longitudinal(PARAMS, CONFIG, duration=3.0, v_d=0.8)
    report = bench_mpc_against_daqp(run.inputs, PARAMS, CONFIG, repeats=1)
    assert report['ticks'] == len(run.inputs) == 30 and report['samples'] == 30
    assert report['proxsuite_failures'] == 0 and report['daqp_failures'] == 0
    assert report['max_plan_difference'] <= SOLUTION_TOL
    for key in ('tick', 'build', 'proxsuite_solve', 'daqp_solve'):
        stats = report[key]
        assert 0.0 < stats['median'] <= stats['p99'] <= stats['max']
    # The tick contains the build and the solve that are timed inside it.
    assert report['tick']['median'] >= report['proxsuite_solve']['median']
    with pytest.raises(ValueError, match='lacks'):
        bench_mpc_against_daqp([{k: 0.0 for k in STEP_KEYS}], PARAMS, CONFIG)


@pytest.mark.parametrize('field', ['v_hat', 'theta_hat', 'theta_dot_hat', 'f2_hat', 'f3_hat'])
def test_absurdly_large_finite_input_is_invalid_not_an_overflowing_qp(field):
    """An absurdly large finite input is invalid, not an overflowing QP.

    1e300 is finite but overflows the QP's gradient to inf (found by the node fuzzing);
    it must be refused like NaN, silently, not solved.
    """
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    state = realistic_state(0.5, 0.02, 0.0, 0.0, 0.0)
    assert mpc.step(**state, v_d=0.5, tau_limit=30.0).status == MpcStatus.SOLVED
    state[field] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter('error')          # no overflow on the way
        result = mpc.step(**state, v_d=0.5, tau_limit=30.0)
    assert result.status == MpcStatus.INPUT_INVALID and math.isfinite(result.tau_v)
    state[field] = 1e6                          # large, but taken as data
    assert mpc.step(**state, v_d=0.5, tau_limit=30.0).status != MpcStatus.INPUT_INVALID


def test_a_first_solve_that_runs_out_of_iterations_is_solved_by_the_retry(monkeypatch):
    """The retry from the equality-constrained initial guess (qp.ProxsuiteSolver.solve).

    Deterministic, whatever SIMD build ProxSuite picks at import (a QP found to stall the
    default start on one machine solved in 41 iterations on another): the first workspace
    is given an iteration limit of 1, so its solve must stop at MAX_ITER; the retry gets
    the configured settings. The MPC must then report SOLVED without a fallback, with the
    iterations of both attempts, at DAQP's optimum.
    """
    from wip_control.core import qp as qp_module
    original = qp_module.ProxsuiteSolver._new_workspace
    starts = []

    def first_attempt_starved(self, initial_guess=None):
        workspace = original(self, initial_guess)
        starts.append(initial_guess)
        if initial_guess is None:
            workspace.settings.max_iter = 1
        return workspace

    monkeypatch.setattr(qp_module.ProxsuiteSolver, '_new_workspace', first_attempt_starved)
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(2.0)
    result = mpc.step(**realistic_state(0.4, 0.03, -0.1, 0.5, 0.0), v_d=1.0,
                      tau_limit=CONFIG.max_drive_torque)
    assert starts == [None, qp_module._PROXQP.InitialGuess.EQUALITY_CONSTRAINED_INITIAL_GUESS]
    assert result.status == MpcStatus.SOLVED and not result.used_fallback
    assert result.iterations > 1                      # the starved attempt's 1, plus the retry's
    z_ref, _, _ = daqp_reference(mpc.last_qp)
    assert np.abs(result.plan - z_ref[:NC]).max() <= SOLUTION_TOL


def test_when_both_proxsuite_starts_run_out_daqp_solves_the_same_qp(monkeypatch):
    """When both ProxSuite starts run out, DAQP solves the same QP.

    The last resort of qp.ProxsuiteSolver.solve: every ProxSuite workspace is given an
    iteration limit of 1, so both starts stop at MAX_ITER (as a few badly scaled per-step
    slack QPs did from both starts, e.g. τ(k−1) = 26 N m above a 4 N m limit); DAQP then
    solves the same data: SOLVED, no fallback, DAQP's optimum.
    """
    from wip_control.core import qp as qp_module
    original = qp_module.ProxsuiteSolver._new_workspace

    def starved(self, initial_guess=None):
        workspace = original(self, initial_guess)
        workspace.settings.max_iter = 1
        return workspace

    monkeypatch.setattr(qp_module.ProxsuiteSolver, '_new_workspace', starved)
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(26.0)
    result = mpc.step(**realistic_state(0.0, 0.0, 0.0, 0.0, 0.0), v_d=0.0,
                      tau_limit=4.00006103515625)
    assert result.status == MpcStatus.SOLVED and not result.used_fallback
    z_ref, _, _ = daqp_reference(mpc.last_qp)
    np.testing.assert_allclose(mpc.last_solution.z, z_ref, rtol=0, atol=1e-9)


# ---------------------------------------------------------------- brake and hold (robust MPC)

PAPER_CONFIG = dataclasses.replace(CONFIG, **PAPER_MPC_SETTINGS)


def test_above_the_speed_limit_the_default_brakes_and_the_paper_formulation_coasts():
    # υ = 1.6 m/s > υmax = 1.5, υd = 0, upright and at rest otherwise. A WIP brakes by
    # first driving the wheels forward (τ > 0 tips the body back: g3 < 0).
    state = realistic_state(1.6, 0.0, 0.0, 0.0, 0.0)
    default = LongitudinalMpc(PARAMS, CONFIG)
    braking = default.step(**state, v_d=0.0, tau_limit=30.0)
    assert braking.status == MpcStatus.SOLVED
    assert braking.tau_v > 1.0                        # measured 6.4 N m
    # The plan is back under the limit within the horizon and stays there.
    speeds = braking.predicted[:, 0]
    assert speeds[-1] < CONFIG.max_speed
    # The paper's single worst-case slack: every braking plan raises the horizon's
    # maximum speed, so it coasts (measured −0.045 N m; the defect).
    paper = LongitudinalMpc(PARAMS, PAPER_CONFIG)
    coasting = paper.step(**state, v_d=0.0, tau_limit=30.0)
    assert abs(coasting.tau_v) < 0.2 * braking.tau_v


def test_per_step_slacks_bound_every_predicted_step():
    # Pushed far beyond both limits: the QP stays feasible and each step's violation is
    # carried by its own slack, |υ(k+i)| ≤ υmax (1 + sυ,i) from speed_limit_first_step on.
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    mpc.reset(0.0)
    result = mpc.step(**realistic_state(2.2, 0.12, 0.5, 10.0, 0.0), v_d=0.5, tau_limit=30.0)
    assert result.status == MpcStatus.SOLVED and not result.used_fallback
    z = mpc.last_solution.z
    s_v, s_theta, rise = z[NC:NC + NP], z[NC + NP:NC + 2 * NP], z[NC + 2 * NP:]
    assert np.all(s_v >= -CONSTRAINT_TOL) and np.all(s_theta >= -CONSTRAINT_TOL)
    # The rise slack (speed_rise_penalty) is a variable, but leaning forward (θ̂ = 0.12)
    # its rows are free: nothing to carry.
    assert rise.shape == (1,) and abs(rise[0]) <= 1e-6
    v, theta = result.predicted[:, 0], result.predicted[:, 1]
    first = CONFIG.speed_limit_first_step - 1
    assert np.all(np.abs(v[first:]) <= CONFIG.max_speed * (1 + s_v[first:]) + CONSTRAINT_TOL)
    assert np.all(np.abs(theta) <= CONFIG.max_tilt * (1 + s_theta) + CONSTRAINT_TOL)
    # Exact penalty: no slack is larger than its own step's violation needs.
    need_v = np.maximum(np.abs(v) / CONFIG.max_speed - 1.0, 0.0)
    assert np.all(s_v[first:] <= need_v[first:] + 1e-4)
    assert result.slack_v == pytest.approx(s_v.max())


def _rise(predicted_v, v_hat, steps):
    """Largest planned speed over the first ``steps`` above max(υmax, υ̂) [m/s]."""
    return max(0.0, float(np.max(predicted_v[:steps])) - max(CONFIG.max_speed, v_hat))


def _first_tick(state, v_d, **config):
    """Return (mpc, result) of the first tick of a fresh MPC.

    The MPC has CONFIG with ``config`` replaced; the tick starts from the ideal-ESO
    estimates ``state`` (:func:`realistic_state`'s arguments).
    """
    mpc = LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, **config))
    mpc.reset(0.0)
    return mpc, mpc.step(**realistic_state(*state), v_d=v_d, tau_limit=30.0)


def _without_and_with_rise_slack(state, v_d):
    """Return the first tick's results with speed_rise_penalty 0 and at its default."""
    return (_first_tick(state, v_d, speed_rise_penalty=0.0)[1],
            _first_tick(state, v_d)[1])


@pytest.mark.parametrize('v_hat, v_d', [(1.5, 1.0), (1.6, 1.0), (2.2, 0.5)])
def test_the_speed_rise_slack_makes_the_rise_before_braking_smaller_and_still_brakes(
        v_hat, v_d):
    """At or above the speed limit a WIP must speed up to brake.

    With the rise slack (speed_rise_penalty, default) the planned rise is smaller than without it,
    and the plan still brakes: its speed at the end of the 2 s horizon is below the start.
    """
    off, on = _without_and_with_rise_slack((v_hat, 0.0, 0.0, 0.0, 0.0), v_d)
    assert off.status == on.status == MpcStatus.SOLVED
    steps = CONFIG.speed_rise_steps
    assert _rise(on.predicted[:, 0], v_hat, steps) < _rise(off.predicted[:, 0], v_hat, steps)
    # Upright at θ = 0 with no disturbance, coasting holds υ̂: the plan brakes instead.
    assert on.predicted[-1, 0] < v_hat - 0.1


def test_the_speed_rise_slack_changes_nothing_below_the_speed_limit():
    # Accelerating from 1.0 toward 1.2 m/s (under the 1.5 limit): the rise rows are
    # inactive and the plan is the one without them (to the solver's tolerance).
    off, on = _without_and_with_rise_slack((1.0, 0.0, 0.0, 0.0, 0.0), 1.2)
    assert on.plan == pytest.approx(off.plan, abs=1e-5)


@pytest.mark.parametrize('theta, theta_dot', [(0.03, 0.0), (-0.005, 0.2)])
def test_the_speed_rise_slack_is_off_while_the_body_leans_the_way_it_travels(theta,
                                                                           theta_dot):
    # Above the limit and leaning forward now, or one MPC period ahead (θ̂ + Ts θ̂̇ > 0):
    # the wheels must speed up to catch the body. The plan is the one without the slack.
    off, on = _without_and_with_rise_slack((2.0, theta, theta_dot, 0.0, 0.0), 1.2)
    assert on.plan == pytest.approx(off.plan, abs=1e-5)
    # Leaning back at the same speed, the slack acts (the plans differ).
    ungated, gated = _without_and_with_rise_slack((2.0, -0.03, 0.0, 0.0, 0.0), 1.2)
    assert np.max(np.abs(gated.plan - ungated.plan)) > 1e-3


def test_the_speed_rise_slack_bounds_the_first_planned_speeds_above_the_current_one():
    # 2 m/s, upright: ±υ(k+i) ≤ υ̂ + υmax r over the first speed_rise_steps.
    mpc, result = _first_tick((2.0, 0.0, 0.0, 0.0, 0.0), 1.0)
    r = mpc.last_solution.z[NC + 2 * NP]
    assert r >= -CONSTRAINT_TOL
    v_first = result.predicted[:CONFIG.speed_rise_steps, 0]
    assert np.all(v_first <= 2.0 + CONFIG.max_speed * r + CONSTRAINT_TOL)
    assert np.max(v_first) > 2.0           # the rise before braking, weighed, not forbidden


def test_the_speed_rise_slack_is_off_below_the_speed_limit_even_when_the_plan_exceeds_it():
    # At 1.45 m/s (below the 1.5 limit), pushed forward (1 m/s²), the plan goes beyond the
    # limit within the first steps: the speed slacks' business alone, the same plan as
    # without the rise slack.
    off, on = _without_and_with_rise_slack((1.45, 0.0, 0.0, 1.0, 0.0), 1.5)
    assert np.max(off.predicted[:CONFIG.speed_rise_steps, 0]) > CONFIG.max_speed
    assert on.plan == pytest.approx(off.plan, abs=1e-5)


def test_speed_rise_steps_beyond_the_horizon_is_refused():
    with pytest.raises(ParamError, match='speed_rise_steps: must be <= prediction_horizon'):
        LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, speed_rise_steps=NP + 1))


@pytest.mark.parametrize('d2, d3', [(0.3, 0.0), (0.0, 0.5), (-0.4, 0.3)])
def test_offset_free_target_balances_the_estimated_constant_disturbance(d2, d3):
    # Closed form of the target at θ = 0 from the linearisation of (1):
    # [a_υθ g2; a_θθ g3](θs, τs) = −(d2, d3) with det = −mp g l / (Ω0 r) gives
    # θs = −d2/g − Jθ d3 / (mp g l).
    p = PARAMS
    expected = (-d2 / p.gravity
                - p.pitch_inertia * d3 / (p.body_mass * p.gravity * p.com_height))
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    result = mpc.step(**realistic_state(0.0, 0.0, 0.0, d2, d3), v_d=0.0, tau_limit=30.0)
    assert result.target_theta == pytest.approx(expected, rel=1e-9)
    # At the target tilt the same disturbance is balanced: the ideal ESO's drifts there,
    # plus g τs, give zero accelerations in the linear model.
    _, g2, g3 = input_gains(PARAMS, 0.0)
    omega0 = p.omega_denominator(0.0)
    a_vt = -(p.body_mass * p.com_height) ** 2 * p.gravity / omega0
    a_tt = p.effective_mass * p.body_mass * p.gravity * p.com_height / omega0
    tau_s = mpc._target.tau
    assert a_vt * expected + g2 * tau_s + d2 == pytest.approx(0.0, abs=1e-9)
    assert a_tt * expected + g3 * tau_s + d3 == pytest.approx(0.0, abs=1e-9)
    # The paper's reference (20) is θ = 0 whatever the disturbance.
    assert LongitudinalMpc(PARAMS, PAPER_CONFIG).step(
        **realistic_state(0.0, 0.0, 0.0, d2, d3), v_d=0.0, tau_limit=30.0).target_theta == 0


def test_offset_free_target_is_bounded_and_low_passed():
    mpc = LongitudinalMpc(PARAMS, CONFIG)
    big = mpc.step(**realistic_state(0.0, 0.0, 0.0, 5.0, 0.0), v_d=0.0, tau_limit=30.0)
    assert big.target_theta == pytest.approx(-CONFIG.max_target_tilt)  # −0.51 rad, bounded
    mpc.reset()
    mpc.step(**realistic_state(0.0, 0.0, 0.0, 0.0, 0.0), v_d=0.0, tau_limit=30.0)
    # A step of d2 = 0.3 m/s² enters through the first-order filter: after one tick
    # the target has moved by Ts/(T + Ts) of its way.
    step = mpc.step(**realistic_state(0.0, 0.0, 0.0, 0.3, 0.0), v_d=0.0, tau_limit=30.0)
    fraction = TS / (CONFIG.disturbance_filter_time_constant + TS)
    assert step.target_theta == pytest.approx(fraction * (-0.3 / PARAMS.gravity), rel=1e-9)


def test_offset_free_push_at_stop_and_hold_leaves_no_speed_offset():
    # Perfect knowledge, paper plant (1), υd = 0, a constant push d2 = 0.3 m/s². With the
    # paper's θ reference 0 a standing speed remains (the position loop (9) then turns
    # it into a position offset); the offset-free target removes it.
    push = lambda t: 0.3  # noqa: E731
    robust = simulate_longitudinal(PARAMS, CONFIG, duration=15.0, v_d=0.0,
                                   disturbance_v=push, theta_initial=0.0)
    paper = simulate_longitudinal(PARAMS, PAPER_CONFIG, duration=15.0, v_d=0.0,
                                  disturbance_v=push, theta_initial=0.0)
    late = robust.t >= 10.0
    assert np.abs(robust.v[late]).max() < 0.005
    assert np.abs(robust.theta[late] + 0.3 / PARAMS.gravity).max() < 0.002  # the lean
    assert abs(paper.v[-1]) > 0.05  # measured 0.18 m/s


# ---------------------------------------------------------------- closed loop, in-process runner
# Whole graph in one process (ESO, trajectory generator, ARC, mixer): the scenarios of the
# issue's findings, with the default (robust) MPC and, where the defect is the point, with
# PAPER_MPC_SETTINGS or the whole paper design (`design: paper`: its MPC, ESOs and
# generator), which must still show it.

def _run(mapping):
    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import scenario_from_mapping
    result = run_scenario(scenario_from_mapping(mapping))
    return result, result.record['truth']


def line_at_the_speed_limit(mpc, duration=20.0):
    """Return a line at υmax = 1.5 m/s entered at that speed, with the paper's pulse.

    A line at υmax = 1.5 m/s entered at that speed, the paper's yaw sine, and the
    paper's collision pulse (10 m/s² on υ̇ for 0.1 s) at 10 s.
    """
    return {'duration': duration, 'reference': {'kind': 'line', 'line_speed': 1.5},
            'initial_state': {'v': 1.5, 'theta': 0.0, 'pose': [0.0, 0.0, 0.0]},
            'mpc': mpc,
            'disturbances': {'longitudinal': [{'kind': 'pulse', 'amplitude': 10.0,
                                               'start_time': 10.0, 'width': 0.1}]}}


def stop_and_hold(mpc, d2, d3, plant='paper', duration=30.0):
    """Stand still on a line of speed 0 while a constant (d2, d3) acts from 2 s on."""
    return {'duration': duration, 'plant': {'model': plant},
            'reference': {'kind': 'hold'},
            'initial_state': {'theta': 0.0, 'pose': [0.0, 0.0, 0.0]}, 'mpc': mpc,
            'disturbances': {'yaw': [],
                             'longitudinal': [{'kind': 'step', 'amplitude': d2,
                                               'start_time': 2.0}],
                             'tilt': [{'kind': 'step', 'amplitude': d3, 'start_time': 2.0}]}}


def slope_disturbance(alpha):
    """(d2, d3) of a slope α [rad] (uphill = +x) in model (1), θ measured from vertical.

    The along-slope weight F = −(mp + mc + 2 mw) g sin α is a generalised force on the rolled
    distance, mapped through the inverse mass matrix at θ = 0, (d2, d3) = (Jθ, −mp l) F / Ω0 (the
    g2, g3 pattern of a wheel force τ/r).
    """
    p = PARAMS
    force = -(p.body_mass + p.chassis_mass + 2 * p.wheel_mass) * p.gravity * math.sin(alpha)
    omega0 = p.omega_denominator(0.0)
    return p.pitch_inertia * force / omega0, -p.body_mass * p.com_height * force / omega0


@pytest.mark.slow
def test_at_the_speed_limit_a_push_is_braked_back_under_the_limit_within_2_s():
    # Measured: the paper's formulation held 2.35-2.46 m/s for 30 s after the pulse.
    limit = CONFIG.max_speed
    result, truth = _run(line_at_the_speed_limit({}))
    t, v = truth['t'], truth['v']
    assert not result.fell
    assert v[t > 10.1].max() > limit + 0.5          # the push really threw it over
    # Back under the limit (0.2 % for the speed ripple of the tracking) within 2 s of
    # the end of the pulse (measured: 1.2 s), and never over it again (no run-away).
    over = np.abs(v) > limit * 1.002
    assert t[over].max() <= 10.1 + 2.0
    # The paper's design as a whole (its MPC, ESOs and generator: `design: paper`).
    paper, truth_paper = _run({**line_at_the_speed_limit({}), 'design': 'paper'})
    late = truth_paper['t'] > 15.0
    assert truth_paper['v'][late].min() > limit + 0.5   # the defect: it runs away


@pytest.mark.slow
@pytest.mark.parametrize('name, disturbance', [
    ('push 0.3 m/s²', (0.3, 0.0)),
    ('4° slope', slope_disturbance(math.radians(4.0)))])
def test_stop_and_hold_leaves_no_position_offset_under_a_constant_force(name, disturbance):
    # Paper plant; the ESO estimates the drifts, the MPC's target leans against them.
    # Measured: 0.002 m (push), 0.002 m (slope) after 20 s; the paper's formulation
    # leaves 0.21 m and 0.07 m.
    result, truth = _run(stop_and_hold({}, *disturbance))
    t = truth['t']
    assert not result.fell
    assert np.abs(truth['x'][t > 20.0]).max() <= 0.05
    assert np.abs(truth['y']).max() < 1e-6          # it really is a straight-line hold


@pytest.mark.slow
def test_paper_formulation_leaves_the_push_offset_that_the_target_removes():
    result, truth = _run(stop_and_hold(dict(PAPER_MPC_SETTINGS), 0.3, 0.0))
    assert not result.fell
    assert np.abs(truth['x'][truth['t'] > 20.0]).min() > 0.1   # measured 0.21 m


@pytest.mark.slow
def test_full_plant_standing_still_decays():
    # Full plant: its tilt input gain is 50 % above model (1)'s (motor reaction torque).
    # Measured: the paper's formulation turned a 0.01 rad tilt into a growing 9.4 s
    # oscillation. Default: the tilt envelope shrinks by ~3x every 20 s (measured
    # 0.0118, 0.0031, 0.0010 rad over 0-20, 20-40, 40-60 s).
    mapping = {'duration': 60.0, 'plant': {'model': 'full'},
               'reference': {'kind': 'hold'},
               'initial_state': {'theta': 0.01, 'pose': [0.0, 0.0, 0.0]},
               'disturbances': {'yaw': [], 'longitudinal': []}}
    result, truth = _run(mapping)
    assert not result.fell
    t, theta, x = truth['t'], np.abs(truth['theta']), truth['x']
    early, late = theta[t < 20.0].max(), theta[t >= 40.0].max()
    assert late < 0.3 * early
    assert np.ptp(x[t >= 40.0]) < 0.3 * np.ptp(x[t < 20.0])
    paper, truth_paper = _run({**mapping, 'design': 'paper'})  # its MPC and estimator
    t = truth_paper['t']
    theta_paper = np.abs(truth_paper['theta'])
    assert theta_paper[t >= 40.0].max() > theta_paper[t < 20.0].max()  # grows


def test_prediction_gain_scale_applies_to_the_increments_only():
    # f̂ + g τ(k−1) is the ESO's estimate of the present accelerations (model (1)'s g);
    # the scaled gains act on the increments. Rollout written out here, independently.
    scale = (1.2, 1.5)
    mpc = LongitudinalMpc(PARAMS, dataclasses.replace(CONFIG, prediction_gain_scale=scale))
    tau_prev = 3.0
    mpc.reset(tau_prev)
    state = realistic_state(0.3, 0.02, -0.05, 0.4, 0.1)
    result = mpc.step(**state, v_d=0.6, tau_limit=30.0)
    assert result.status == MpcStatus.SOLVED
    _, g2, g3 = input_gains(PARAMS, state['theta_hat'])
    a = state_matrix_from_spec('gravity_aware')
    x0 = np.array([state['v_hat'], state['theta_hat'], state['theta_dot_hat']])
    c = TS * np.array([state['f2_hat'] + g2 * tau_prev, 0.0, state['f3_hat'] + g3 * tau_prev])
    c -= (a - state_matrix_from_spec('paper')) @ x0
    b_scaled = TS * np.array([scale[0] * g2, 0.0, scale[1] * g3])
    x, increment, rows = x0.copy(), 0.0, []
    for i in range(NP):
        if i < NC:
            increment += result.plan[i]
        x = a @ x + c + b_scaled * increment
        rows.append(x)
    np.testing.assert_allclose(result.predicted, np.array(rows), rtol=0, atol=1e-10)


# ------------------------------------------------------------- transient disturbances

@pytest.mark.parametrize('ratio', [0.0, 0.37, 1.0])
def test_decaying_input_columns_are_the_euler_response_to_a_geometric_input(ratio):
    """The decaying-input columns are the Euler response to a geometric input.

    γρ of an input ρ^p at step p, against the explicit recursion x(k+1) = A x(k) + b ρ^k
    (ρ = 1: the constant-input columns of the free response; ρ = 0: an impulse).
    """
    prediction = CondensedPrediction(PARAMS, TS, NP, NC)
    decay_v, decay_theta_dot = prediction.decaying_input_columns(ratio)
    a = prediction.state_matrix
    for row, column in ((0, decay_v), (2, decay_theta_dot)):
        x, out = np.zeros(3), []
        for k in range(NP):
            b = np.zeros(3)
            b[row] = TS * ratio ** k
            x = a @ x + b
            out.append(x)
        np.testing.assert_allclose(column, np.ravel(out), rtol=1e-12, atol=1e-15)
    if ratio == 1.0:
        np.testing.assert_allclose(decay_v, prediction.free_v_column, rtol=1e-12)
        np.testing.assert_allclose(decay_theta_dot, prediction.free_theta_dot_column,
                                   rtol=1e-12)


def test_a_hard_push_predicted_to_pass_no_longer_drops_the_robot():
    """A hard push predicted to pass no longer drops the robot.

    A 0.1 s push of 8.8 m/s² on a 20 % heavier body (full plant, sensor noise), one of
    the campaign's falls: with the whole ESO disturbance held constant over the 2 s
    horizon (decay 0, the paper's prediction), the MPC plans against a push that lasts
    (it drove the wheels the wrong way for a step and could not return within the Δτ
    limit); with the transient part beyond the default dead zone decaying
    (disturbance_decay_time_constant 0.1 s, the default) the robot stays up.
    """
    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import scenario_from_mapping

    def run(decay):
        return run_scenario(scenario_from_mapping({
            'plant': {'model': 'full', 'parameters': {'body_mass': 29.7, 'com_height': 0.631}},
            'sensors': {'imu_pitch_noise_std': 0.002, 'gyro_noise_std': 0.01},
            'disturbances': {'longitudinal': [{'kind': 'pulse', 'amplitude': -8.77,
                                               'start_time': 20.68, 'width': 0.1}]},
            'duration': 24.0, 'mpc': {'disturbance_decay_time_constant': decay,
                                      'speed_slack_quadratic_penalty': 1e4,
                                      'fast_resolve_period': 0.0}}))
    # The speed slacks' penalty as when this draw was traced (1e4; docs/history/mpc.md §5): with
    # the default of §7 (100) the held prediction survives this draw too; and the torque
    # held for the MPC period, as then: re-solving after the push (§10) saves it too.
    held = run(0.0)
    assert held.fell and 20.68 < held.fall_time < 22.0
    decaying = run(0.1)
    assert not decaying.fell
    assert np.abs(decaying.record['truth']['theta']).max() < 0.35


def _transient_ticks(config, f2_values, f3_values):
    """τ and predicted outputs of an MPC fed a standing state whose f̂ jumps.

    From its first tick: without the start-up rule, which would replace f̂ there.
    """
    mpc = LongitudinalMpc(PARAMS, dataclasses.replace(config, disturbance_startup_time=0.0))
    out = []
    for f2, f3 in zip(f2_values, f3_values):
        result = mpc.step(0.0, 0.0, 0.0, f2, f3, 0.0)
        out.append((result.tau_v, result.predicted.copy()))
    return out


def test_a_transient_within_the_dead_zone_is_held_as_in_the_paper_prediction():
    """A transient within the dead zone is held, as in the paper's prediction.

    The dead zone of the transient decay: a transient disturbance estimate within
    ±(2 m/s², 2 rad/s²) (model error, noise) is held over the horizon exactly as with the
    decay off; beyond it (a push) the prediction and the torque change. Without the dead
    zone even the small transient decays (so the first assertion is not vacuous).
    """
    held = MpcParams(disturbance_decay_time_constant=0.0)
    default = MpcParams()
    assert default.disturbance_decay_time_constant > 0.0
    zone_v, zone_theta_dot = default.disturbance_decay_dead_zone
    no_zone = dataclasses.replace(default, disturbance_decay_dead_zone=(0.0, 0.0))
    # First tick initialises the slow estimate at 0; the second's transient is then
    # (1 − Ts/(T + Ts)) of the step: 5/6 of it for the default 0.5 s filter.
    small = ([0.0, 0.9 * zone_v], [0.0, 0.9 * zone_theta_dot])
    ref = _transient_ticks(held, *small)
    got = _transient_ticks(default, *small)
    for (tau_a, pred_a), (tau_b, pred_b) in zip(ref, got):
        assert tau_b == pytest.approx(tau_a, abs=1e-9)
        np.testing.assert_allclose(pred_b, pred_a, rtol=0, atol=1e-9)
    assert np.abs(_transient_ticks(no_zone, *small)[1][1] - ref[1][1]).max() > 1e-3
    # A push: 8 m/s² on υ̇ (the campaign's hard pushes are 7-10 m/s²).
    push = ([0.0, -8.0], [0.0, 0.0])
    ref, got = _transient_ticks(held, *push), _transient_ticks(default, *push)
    free = _transient_ticks(no_zone, *push)
    # Held, the push is extrapolated for 2 s: a predicted speed change of ~16 m/s.
    # Decaying beyond the zone, only the 2 m/s² within it is held (about 4 m/s).
    drift = [abs(p[1][1][-1, 0]) for p in (ref, got, free)]
    assert drift[0] > 1.5 * drift[1] and drift[1] > 1.5 * drift[2]


def _speed_ticks(config, v_d_values, v=1.0):
    """Results of an MPC at speed ``v``, upright, fed the commands ``v_d_values``."""
    mpc = LongitudinalMpc(PARAMS, config)
    return [mpc.step(v, 0.0, 0.0, 0.0, 0.0, v_d) for v_d in v_d_values]


def test_speed_preview_is_the_paper_reference_for_a_constant_command():
    """The speed preview is the paper's reference for a constant command.

    With υd constant the trend is 0 and the reference over the horizon is the held υd
    of (20): the same torques and plans as with the preview off.
    """
    off = MpcParams(speed_preview_time=0.0)
    on = MpcParams()
    assert on.speed_preview_time > 0.0
    for a, b in zip(_speed_ticks(off, [0.8] * 4), _speed_ticks(on, [0.8] * 4)):
        assert b.tau_v == pytest.approx(a.tau_v, abs=1e-9)
        np.testing.assert_allclose(b.predicted, a.predicted, rtol=0, atol=1e-9)


def test_speed_preview_brakes_earlier_for_a_falling_command_and_bounds_the_trend():
    """The speed preview brakes earlier for a falling command and bounds the trend.

    υd falling at 0.5 m/s² (a reference slowing for a corner): the previewed plan
    predicts a lower speed over the horizon than the held reference; a jump of υd (a
    push moves x_e) is extrapolated at most at ``max_speed_trend``.
    """
    falling = [1.0 - 0.05 * k for k in range(6)]
    off = _speed_ticks(MpcParams(speed_preview_time=0.0), falling)[-1]
    on = _speed_ticks(MpcParams(), falling)[-1]
    assert on.predicted[-1, 0] < off.predicted[-1, 0] - 0.05
    # The trend of a jump is clipped: a 1 m/s step of υd looks like max_speed_trend.
    config = MpcParams()
    mpc = LongitudinalMpc(PARAMS, config)
    mpc.step(1.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    mpc.step(1.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    gain = config.sampling_period / (config.speed_trend_filter_time_constant
                                     + config.sampling_period)
    assert mpc._preview.trend == pytest.approx(-gain * config.max_speed_trend, rel=1e-12)


def test_start_up_rule_ignores_the_estimators_zero_start_and_its_transient():
    """The start-up rule ignores the estimators' zero start and its transient.

    disturbance_startup_time: on the first tick the speed estimate is the estimator's
    zero start, so no speed error is acted on (as if υ̂ = υd); until the start-up time has
    passed, f̂2, f̂3 are replaced by model (1)'s own drift at the estimate (the ESO's
    start-up transient is not a disturbance). After it, the estimates count again.
    """
    config = MpcParams()
    ticks = math.ceil(config.disturbance_startup_time / config.sampling_period - 1e-9)
    assert ticks >= 2
    state = dict(theta_hat=0.01, theta_dot_hat=0.02)

    def run(v_first, f2_values):
        mpc = LongitudinalMpc(PARAMS, config)
        out = [mpc.step(v_hat=v_first, f2_hat=f2_values[0], f3_hat=0.0, v_d=1.2, **state)]
        for f2 in f2_values[1:]:
            out.append(mpc.step(v_hat=1.2, f2_hat=f2, f3_hat=0.0, v_d=1.2, **state))
        return [r.tau_v for r in out]

    quiet = [0.0] * (ticks + 1)
    transient = [0.0] + [4.0] * ticks
    # First tick: υ̂ = 0 (zero start) acts as υ̂ = υd.
    assert run(0.0, quiet)[0] == pytest.approx(run(1.2, quiet)[0], abs=1e-9)
    # Start-up ticks: f̂2 = 4 m/s² (the transient of a start at speed) changes nothing...
    a, b = run(1.2, quiet), run(1.2, transient)
    np.testing.assert_allclose(b[:ticks], a[:ticks], rtol=0, atol=1e-9)
    # ...and afterwards it does (the rule is not a blanket filter).
    assert abs(b[ticks] - a[ticks]) > 0.1
    # Off (the paper): the first tick acts on υ̂ = 0, i.e. it accelerates.
    off = LongitudinalMpc(PARAMS, CONFIG)
    first = off.step(v_hat=0.0, f2_hat=0.0, f3_hat=0.0, v_d=1.2, **state)
    assert abs(first.tau_v - run(1.2, quiet)[0]) > 0.5


def _min_peak_speed_after_push(v0, push=10.0, width=0.1, first_tick=0.1, back_by=2.1,
                               back_to=1.55, max_tilt=0.1, horizon=5.0, dt=0.005):
    """Return a lower bound on the peak speed of any causal controller after a forward push.

    See docs/history/mpc.md §7. An LP on the linearisation of the paper plant at rest
    (υ, θ, θ̇), exact zero-order-hold discretisation at ``dt``; the push d2 = ``push`` m/s²
    over [0, width); τυ held over 0.1 s ticks from ``first_tick`` (0 before: the controller
    has not seen the push), |τυ| ≤ 30 N·m, |Δτυ| ≤ 10 N·m per tick, |θ| ≤ max_tilt, υ ≤
    back_to from back_by on, θ = θ̇ = 0 at the end (caught). Minimises max υ.
    """
    import scipy.linalg
    import scipy.optimize

    from wip_control.core.model import THETA, THETA_DOT, V
    from wip_sim.core.plant import Plant

    x_eq = np.zeros(8)
    x_eq[V] = v0
    a_full, b_full = Plant(PARAMS, 'paper').linearize(x_eq)
    idx = [V, THETA, THETA_DOT]
    a, b = a_full[np.ix_(idx, idx)], b_full[idx, 0]   # τl = τr = τυ/2: B[:, l] per τυ
    big = np.zeros((5, 5))
    big[:3, :3], big[:3, 3], big[0, 4] = a, b, 1.0
    m = scipy.linalg.expm(big * dt)
    ad, bd, ed = m[:3, :3], m[:3, 3], m[:3, 4]
    n = int(round(horizon / dt))
    ticks = np.arange(first_tick, horizon - 1e-9, 0.1)
    k = len(ticks)
    owner = np.searchsorted(ticks, dt * np.arange(n) + 1e-9, side='right') - 1
    x_c, x_u = np.array([v0, 0.0, 0.0]), np.zeros((3, k))
    rows, rhs = [], []
    for j in range(n):
        x_c = ad @ x_c + ed * (push if j * dt < width - 1e-9 else 0.0)
        x_u = ad @ x_u
        if owner[j] >= 0:
            x_u[:, owner[j]] += bd
        rows.append(np.append(x_u[0], -1.0))      # υ ≤ peak
        rhs.append(-x_c[0])
        for sign in (1.0, -1.0):                  # |θ| ≤ max_tilt
            rows.append(np.append(sign * x_u[1], 0.0))
            rhs.append(max_tilt - sign * x_c[1])
        if (j + 1) * dt >= back_by:               # back under the limit
            rows.append(np.append(x_u[0], 0.0))
            rhs.append(back_to - x_c[0])
    for i in range(k):                            # |Δτ| ≤ 10 per tick, from τ = 0
        for sign in (1.0, -1.0):
            row = np.zeros(k + 1)
            row[i] = sign
            if i:
                row[i - 1] = -sign
            rows.append(row)
            rhs.append(10.0)
    equal = [np.append(x_u[i], 0.0) for i in (1, 2)]
    result = scipy.optimize.linprog(
        np.append(np.zeros(k), 1.0), A_ub=np.array(rows), b_ub=np.array(rhs),
        A_eq=np.array(equal), b_eq=[-x_c[1], -x_c[2]],
        bounds=[(-30.0, 30.0)] * k + [(None, None)], method='highs')
    assert result.status == 0, result.message
    return result.x[-1]


def test_the_speed_limit_push_needs_no_run_away_physically():
    """The speed_limit class: cruising at 1.21 m/s, a 10 m/s² push for 0.1 s adds 1.0 m/s.

    A WIP must speed up to brake (non-minimum phase), but gently enough it need not: the best
    causal plan within the torque, Δτ and tilt limits (first tick 0.1 s after the push starts)
    peaks at the push's own 2.21 m/s and is back under 1.55 m/s within 2 s. The criterion max_speed
    2.5 m/s is attainable (the MPC: 2.49 m/s).
    """
    v0 = 1.21
    peak = _min_peak_speed_after_push(v0)
    assert v0 + 0.99 <= peak < v0 + 1.0 + 0.05
    # Made to be back within 0.9 s instead (as the MPC is), a rise is forced (2.28 m/s):
    # the bound is not vacuous.
    assert _min_peak_speed_after_push(v0, back_by=1.0) > peak + 0.05


def test_a_process_that_exits_holding_an_mpc_prints_no_binding_leak_report():
    """A process that exits holding an MPC prints no binding leak report.

    A controller process holds its MPC until the interpreter exits, in a reference
    cycle (node <-> callbacks) that gc.freeze() (real-time hygiene) keeps from being
    collected; ProxSuite's binding layer (nanobind) reports every QP object still alive at
    its teardown as a 'leaked instance' (about 30 lines at the end of every controller
    log), which ``core.qp`` prevents by freeing the workspaces at exit.
    """
    import subprocess
    import sys
    program = ('from wip_control.core.mpc import LongitudinalMpc\n'
               'from wip_control.core.mpc_config import MpcParams\n'
               'from wip_description.params import ModelParams\n'
               'HELD = LongitudinalMpc(ModelParams(), MpcParams())\n'
               'result = HELD.step(v_hat=0.0, theta_hat=0.05, theta_dot_hat=0.0, f2_hat=0.0,'
               ' f3_hat=0.0, v_d=0.3, tau_limit=20.0)\n'
               'print(result.status.name)\n'
               'cycle = {"mpc": HELD}\n'
               'cycle["self"] = cycle\n'
               'del HELD, cycle\n'
               'import gc\n'
               'gc.freeze()\n')
    done = subprocess.run([sys.executable, '-c', program], capture_output=True, text=True,
                          timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == 'SOLVED'
    assert 'leaked' not in done.stderr, done.stderr


@pytest.mark.parametrize('seed', range(12))
def test_the_compiled_qp_is_the_numpy_formulation(seed):
    # Random states, half of them above the speed limit (the rise rows), with and without
    # the speed preview, a transient disturbance beyond its dead zone, a torque beyond
    # the limit: the kernel fills the same QP as the array expressions, to round-off.
    rng = np.random.default_rng(seed)
    config = dataclasses.replace(CONFIG, speed_preview_time=0.5 if seed % 2 else 0.0)
    mpc = LongitudinalMpc(PARAMS, config)
    v_hat = rng.choice([-1.0, 1.0]) * (config.max_speed + rng.uniform(-0.3, 0.3))
    theta_hat, theta_dot_hat = rng.uniform(-0.1, 0.1), rng.uniform(-0.5, 0.5)
    f2_hat, f3_hat = rng.uniform(-3, 3), rng.uniform(-20, 20)
    v_d, limit, tau_prev = rng.uniform(-1.5, 1.5), rng.uniform(5, 30), rng.uniform(-35, 35)
    _, g2, g3 = input_gains(PARAMS, theta_hat)
    g2p, g3p = g2 * rng.uniform(0.9, 1.1), g3 * rng.uniform(0.9, 1.1)
    transient = (rng.uniform(-2, 2), rng.uniform(-10, 10))
    mpc._target.transient = transient
    mpc._target.theta = rng.uniform(-0.05, 0.05)
    preview = mpc._preview
    preview.v_d_last, preview.trend = v_d - 0.01, rng.uniform(-1, 1)
    trend_before, last_before = preview.trend, preview.v_d_last
    # The trend filter's update of this tick, as SpeedPreview.update does it.
    trend = preview.update(v_d, config.sampling_period)
    if config.speed_preview_time > 0.0:
        ts = config.sampling_period
        rate = min(max((v_d - last_before) / ts, -config.max_speed_trend),
                   config.max_speed_trend)
        assert trend == trend_before + ts / (config.speed_trend_filter_time_constant + ts) * (
            rate - trend_before)
    zone = config.disturbance_decay_dead_zone
    excess = [max(abs(t) - b, 0.0) * math.copysign(1.0, t) for t, b in zip(transient, zone)]
    tick = TickData(v_hat, theta_hat, theta_dot_hat, f2_hat, f3_hat, g2, g3, g2p, g3p,
                    tau_prev, limit, *excess, v_d, trend, mpc.target_theta)
    free = mpc.qp.update(tick)
    expected = reference_qp(mpc.qp, tick)
    qp = mpc.last_qp
    for name, got, want in zip(('H', 'g', 'C', 'l', 'u', 'free'),
                               (qp.H, qp.g, qp.C, qp.l, qp.u, free), expected):
        finite = np.isfinite(want)
        assert np.array_equal(np.isfinite(got), finite), name
        assert np.array_equal(got[~finite], want[~finite]), name
        scale = 1.0 + np.abs(want[finite]).max()
        assert np.abs(got[finite] - want[finite]).max() <= 1e-12 * scale, name
