"""Plant: eq. (1) of the paper, the full Lagrange–d'Alembert model, RK4, invariants."""

import math

import numpy as np
import pytest
from wip_control.core.integration import rk4_step
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import simpson

from wip_runtime.config import ParamError, from_mapping
from wip_control.core.model import OMEGA, PHI, THETA, THETA_DOT, V, XV, nominal_terms
from wip_description.params import ModelParams
from wip_sim.core.plant import (full_input_gains, Plant, PlantParams, simulate_hold,
                                tilt_pole)

PARAMS = ModelParams()
MODELS = ('paper', 'full')
finite = dict(allow_nan=False, allow_infinity=False)

states = st.tuples(
    st.floats(-50, 50, **finite), st.floats(-50, 50, **finite),      # x, y [m]
    st.floats(-20, 20, **finite), st.floats(-50, 50, **finite),      # ϕ [rad], x_v [m]
    st.floats(-3.0, 3.0, **finite), st.floats(-3, 3, **finite),      # θ [rad], ω [rad/s]
    st.floats(-3, 3, **finite), st.floats(-5, 5, **finite))          # υ [m/s], θ̇ [rad/s]
torques = st.floats(-30, 30, **finite)
disturbances = st.tuples(*[st.floats(-10, 10, **finite)] * 3)

# A state that swings around the hanging position (θ = π − 0.8 ± 0.9 rad), moving and
# turning: kinetic and potential energy are exchanged and J(θ) = J_ϕ + m_p l² sin²θ
# varies, so energy and yaw momentum are informative, and nothing escapes to infinity.
SWINGING = (0.0, 0.0, 0.0, 0.0, math.pi - 0.8, 0.5, 0.4, 1.0)
NO_DISTURBANCE = np.zeros((1, 3))


def step(plant, state, tau_left, tau_right, disturbance, dt):
    """One checked RK4 step of ``dt`` [s], torques and disturbance held."""
    return simulate_hold(plant, state, tau_left, tau_right, lambda _t: disturbance, 0.0, dt,
                         1)


def rk4_reference(f, x, h):
    """Step by the one RK4 (core.integration) on numpy arrays; the plant compiles it."""
    return rk4_step(lambda _, y: f(y), 0.0, x, h)


def full_model_reference(params, state, tau_left, tau_right, disturbance):
    """Return the full model's equations in mass-matrix form, M(θ) ν̇ = F, solved by numpy.

    Written from the module docstring independently of the plant's closed-form solve.
    """
    p = params
    _, _, phi, _, th, om, v, thd = state
    mp, l, r, g, d = p.body_mass, p.com_height, p.wheel_radius, p.gravity, p.track_width  # noqa: E741 - the paper's symbol
    s, c = math.sin(th), math.cos(th)
    tv, tw = tau_left + tau_right, tau_right - tau_left
    mass = np.array([[p.yaw_inertia_total + mp * l * l * s * s, 0.0, 0.0],
                     [0.0, p.effective_mass, mp * l * c],
                     [0.0, mp * l * c, p.pitch_inertia]])
    force = np.array([d * tw / (2 * r) - 2 * mp * l * l * s * c * om * thd - mp * l * s * v * om,
                      tv / r + mp * l * s * (thd ** 2 + om ** 2),
                      -tv + mp * g * l * s + mp * l * l * s * c * om ** 2])
    acc = np.linalg.solve(mass, force) + np.asarray(disturbance)
    return np.array([v * math.cos(phi), v * math.sin(phi), om, v, thd, *acc])


# ----------------------------------------------------------------------------- right-hand side

@settings(max_examples=200, deadline=None)
@given(state=states, tau_left=torques, tau_right=torques, dist=disturbances)
def test_paper_plant_is_eq1_with_rep103_torques(state, tau_left, tau_right, dist):
    plant = Plant(PARAMS, 'paper')
    xdot = plant.derivative(np.array(state), tau_left, tau_right, dist)
    _, _, phi, _, th, om, v, thd = state
    f1, f2, f3, g1, g2, g3 = nominal_terms(PARAMS, th, om, thd)
    tv, tw = tau_left + tau_right, tau_right - tau_left
    expected = [v * math.cos(phi), v * math.sin(phi), om, v, thd,
                f1 + g1 * tw + dist[0], f2 + g2 * tv + dist[1], f3 + g3 * tv + dist[2]]
    # Same formula rearranged: agreement to rounding (terms up to ~1e3, eps ~ 2e-16).
    np.testing.assert_allclose(xdot, expected, rtol=1e-11, atol=1e-11)


@settings(max_examples=200, deadline=None)
@given(state=states, tau_left=torques, tau_right=torques, dist=disturbances)
def test_full_plant_solves_the_lagrange_dalembert_mass_matrix_equations(
        state, tau_left, tau_right, dist):
    plant = Plant(PARAMS, 'full')
    xdot = plant.derivative(state, tau_left, tau_right, dist)
    expected = full_model_reference(PARAMS, state, tau_left, tau_right, dist)
    # Closed-form 2×2 solve vs LU: rounding only (condition number of M ~ 1e2).
    np.testing.assert_allclose(xdot, expected, rtol=1e-10, atol=1e-10)


@settings(max_examples=100, deadline=None)
@given(th=st.floats(-1.4, 1.4, **finite), v=st.floats(-3, 3, **finite),
       thd=st.floats(-5, 5, **finite), tau_v=torques)
def test_full_model_equals_paper_model_without_yaw_motion_or_input(th, v, thd, tau_v):
    # With ω = 0 and no torque, the centrifugal (ω²) and Coriolis (υω) terms vanish and
    # both models are the same Euler–Lagrange system of the same Lagrangian.
    state = (1.0, 2.0, 0.3, 0.5, th, 0.0, v, thd)
    paper = Plant(PARAMS, 'paper').derivative(state, 0.0, 0.0)
    full = Plant(PARAMS, 'full').derivative(state, 0.0, 0.0)
    np.testing.assert_allclose(full, paper, rtol=1e-12, atol=1e-12)
    # The input responses differ exactly by the motor reaction −τυ on the body pitch:
    # Δ(υ̇, θ̈) = M⁻¹ (0, −τυ) = (m_p l cosθ, −m_v) τυ / Ω.
    tau_l = tau_r = 0.5 * tau_v
    d_paper = Plant(PARAMS, 'paper').derivative(state, tau_l, tau_r) - paper
    d_full = Plant(PARAMS, 'full').derivative(state, tau_l, tau_r) - full
    big_omega = PARAMS.omega_denominator(th)
    mpl = PARAMS.body_mass * PARAMS.com_height
    expected = np.array([mpl * math.cos(th), -PARAMS.effective_mass]) * tau_v / big_omega
    # Differences of O(10) numbers: absolute rounding ~1e-13.
    np.testing.assert_allclose(d_full[[V, THETA_DOT]] - d_paper[[V, THETA_DOT]], expected,
                               atol=1e-11)


def test_full_model_yaw_gain_is_half_the_papers():
    # Wheel forces τ/r at ±d/2 give the yaw moment (τr − τl) d/(2r), with d the distance
    # between the wheels (the paper's g1 = d/(r J) counts it twice).
    state = (0.0, 0.0, 0.0, 0.0, 0.2, 0.0, 0.0, 0.0)
    for model, factor in (('paper', 1.0), ('full', 0.5)):
        plant = Plant(PARAMS, model)
        d_omega = (plant.derivative(state, -1.0, 1.0) - plant.derivative(state, 0.0, 0.0))[OMEGA]
        g1 = nominal_terms(PARAMS, 0.2, 0.0, 0.0).g1
        assert d_omega == pytest.approx(2.0 * factor * g1, rel=1e-12)   # τω = 2 N·m
    g1, g2, g3 = full_input_gains(PARAMS, 0.0)
    # Spec's default numbers at θ = 0: Ω0 = 262.5, paper g1 ≈ 2.58.
    assert g1 == pytest.approx(0.5 / (2 * 0.2 * PARAMS.yaw_inertia_total), rel=1e-12)
    assert g2 == pytest.approx((13.0 + 25 * 0.6 * 0.2) / (262.5 * 0.2), rel=1e-12)
    assert g3 == pytest.approx(-(37.5 * 0.2 + 25 * 0.6) / (262.5 * 0.2), rel=1e-12)


@pytest.mark.parametrize('model', MODELS)
def test_disturbances_add_to_the_three_accelerations(model):
    plant = Plant(PARAMS, model)
    state = np.array(SWINGING)
    delta = plant.derivative(state, 1.0, 2.0, (0.3, -0.7, 1.1)) - plant.derivative(state, 1.0, 2.0)
    np.testing.assert_allclose(delta, [0, 0, 0, 0, 0, 0.3, -0.7, 1.1], atol=1e-12)


# ----------------------------------------------------------------------------- integrator

@pytest.mark.parametrize('model', MODELS)
@settings(max_examples=50, deadline=None)
@given(state=states, tau_left=torques, tau_right=torques, dist=disturbances)
def test_step_is_classic_rk4_of_the_derivative(model, state, tau_left, tau_right, dist):
    plant = Plant(PARAMS, model)
    h = 1e-3
    expected = rk4_reference(lambda x: plant.derivative(x, tau_left, tau_right, dist),
                             np.array(state), h)
    # Same arithmetic in another order: rounding only, relative to |state| ≤ 50.
    np.testing.assert_allclose(step(plant, state, tau_left, tau_right, dist, h), expected,
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('model', MODELS)
def test_simulate_hold_samples_the_disturbance_at_each_step_start(model):
    plant = Plant(PARAMS, model)
    calls = []

    def disturbance(t):
        calls.append(t)
        return (math.sin(0.5 * t), 10.0 if 0.002 <= t < 0.004 else 0.0, 0.0)

    t0, dt = 0.5, 1e-3
    held = simulate_hold(plant, SWINGING, 1.5, -0.5, disturbance, t0, dt, 5)
    assert calls == pytest.approx([t0 + k * dt for k in range(5)], abs=1e-15)
    x = np.array(SWINGING)
    for t in list(calls):
        x = step(plant, x, 1.5, -0.5, disturbance(t), dt)
    np.testing.assert_array_equal(held, x)   # the same float operations: bit-identical
    no_disturbance = simulate_hold(plant, SWINGING, 0.0, 0.0, None, 0.0, dt, 3)
    expected = SWINGING
    for _ in range(3):
        expected = step(plant, expected, 0.0, 0.0, (0.0, 0.0, 0.0), dt)
    np.testing.assert_array_equal(no_disturbance, expected)


def _free_run(plant, state, dt, duration):
    """Zero input, zero disturbance; the trajectory sampled at every step."""
    n = int(round(duration / dt))
    out = np.empty((n + 1, 8))
    out[0] = state
    x = tuple(state)
    for k in range(n):
        x = plant.hold_floats(x, 0.0, 0.0, NO_DISTURBANCE, dt)
        out[k + 1] = x
    return out


def _max_energy_drift(plant, dt, duration=5.0):
    trajectory = _free_run(plant, SWINGING, dt, duration)
    energy = np.array([plant.energy(x) for x in trajectory])
    return np.max(np.abs(energy - energy[0])), trajectory


@pytest.mark.parametrize('model', MODELS)
def test_energy_is_conserved_to_fourth_order_in_dt(model):
    plant = Plant(PARAMS, model)
    drift_10ms, trajectory = _max_energy_drift(plant, 0.01)
    drift_5ms, _ = _max_energy_drift(plant, 0.005)
    drift_1ms, _ = _max_energy_drift(plant, 0.001)
    # The run is informative: θ swings over ~1.7 rad, kinetic energy up to ~10² J.
    assert np.ptp(trajectory[:, THETA]) > 1.5
    # RK4's global error is O(dt⁴): halving dt divides the drift by ~16 (measured 18.2
    # and 18.6 for the two models); [10, 32] tolerates the error constant's variation.
    assert 10.0 < drift_10ms / drift_5ms < 32.0
    # At the simulator's 1 ms step: drift(10 ms) ~ 1e-5 J scaled by (1/10)⁴ gives
    # ~1e-9 J (measured 6e-10 and 7e-10); 1e-7 J = 7e-10 of m_p g l leaves margin.
    assert drift_1ms < 1e-7


def test_paper_model_conserves_yaw_momentum():
    plant = Plant(PARAMS, 'paper')
    trajectory = _free_run(plant, SWINGING, 0.001, 5.0)
    momentum = np.array([plant.yaw_momentum(x) for x in trajectory])
    # J(θ) varies by m_p l² sin²θ ≈ 4.5 kg m² here, so ω changes while J ω must not.
    assert np.ptp(trajectory[:, OMEGA]) > 0.2
    # RK4 at 1 ms: same O(dt⁴) argument as the energy (measured 3e-10 kg m²/s).
    assert np.max(np.abs(momentum - momentum[0])) < 1e-7


def test_full_model_yaw_momentum_follows_its_balance_law():
    # d/dt (J(θ) ω) = −m_p l sinθ υ ω with zero input: the ground's wheel forces act on
    # the yaw momentum, so it is not conserved, but its change is this integral.
    plant = Plant(PARAMS, 'full')
    dt = 0.001
    trajectory = _free_run(plant, SWINGING, dt, 5.0)
    momentum = np.array([plant.yaw_momentum(x) for x in trajectory])
    th, om, v = trajectory[:, THETA], trajectory[:, OMEGA], trajectory[:, V]
    source = -PARAMS.body_mass * PARAMS.com_height * np.sin(th) * v * om
    integral = simpson(source, dx=dt)
    change = momentum[-1] - momentum[0]
    assert abs(change) > 0.5        # really not conserved (measured about −1.4)
    # Simpson's rule O(dt⁴) and RK4 O(dt⁴) errors are both ~1e-10 here; 1e-7 is margin.
    assert change == pytest.approx(integral, abs=1e-7)


@pytest.mark.parametrize('model', MODELS)
def test_rk4_converges_to_the_exact_solution_at_fourth_order(model):
    from scipy.integrate import solve_ivp
    plant = Plant(PARAMS, model)
    torque = (2.0, -1.0)
    state0 = np.array([0.0, 0.0, 0.2, 0.0, 0.1, 0.3, 0.5, -0.2])
    exact = solve_ivp(lambda t, x: plant.derivative(x, *torque), (0.0, 1.0), state0,
                      method='DOP853', rtol=1e-13, atol=1e-13).y[:, -1]
    errors = []
    for dt in (0.02, 0.01):
        x = state0
        for _ in range(int(round(1.0 / dt))):
            x = step(plant, x, *torque, (0.0, 0.0, 0.0), dt)
        errors.append(np.max(np.abs(x - exact)))
    # Global error ∝ dt⁴: ratio 16 in the asymptotic range (measured 15.5); DOP853's own error at
    # 1e-13 tolerance is far below either.
    assert 12.0 < errors[0] / errors[1] < 20.0


# ----------------------------------------------------------------------------- linearisation

def test_tilt_pole_closed_form_with_default_parameters():
    # sqrt(m_v m_p g l / Ω0) = sqrt(37.5·25·9.81·0.6 / 262.5) (spec: ≈ 4.6 rad/s).
    assert tilt_pole(PARAMS) == pytest.approx(math.sqrt(37.5 * 25 * 9.81 * 0.6 / 262.5),
                                              rel=1e-12)
    assert tilt_pole(PARAMS) == pytest.approx(4.585, abs=1e-3)
    assert tilt_pole(PARAMS, 'full') == tilt_pole(PARAMS, 'paper')


@pytest.mark.parametrize('model', MODELS)
@pytest.mark.parametrize('params', [PARAMS, PARAMS.replace(body_mass=60.0, com_height=0.9,
                                                           wheel_radius=0.1)])
def test_linearisation_at_rest_has_the_closed_form_tilt_pole(model, params):
    plant = Plant(params, model)
    rest = np.array([1.0, -2.0, 0.7, 0.3, 0.0, 0.0, 0.0, 0.0])
    a, b = plant.linearize(rest)
    # Longitudinal/tilt subsystem (υ, θ, θ̇): eigenvalues {0, ±λ}.
    idx = [V, THETA, THETA_DOT]
    eig = np.sort(np.linalg.eigvals(a[np.ix_(idx, idx)]).real)
    pole = tilt_pole(params, model)
    # Central differences with step 1e-6: O(1e-12) truncation, O(1e-10) rounding.
    np.testing.assert_allclose(eig, [-pole, 0.0, pole], atol=1e-6)
    # The yaw and tilt subsystems decouple at rest; ϕ, x_v, x, y are integrators.
    assert np.all(np.abs(a[OMEGA]) < 1e-8)
    assert a[PHI, OMEGA] == pytest.approx(1.0) and a[XV, V] == pytest.approx(1.0)
    g1, g2, g3 = (full_input_gains(params, 0.0) if model == 'full'
                  else nominal_terms(params, 0.0, 0.0, 0.0)[3:])
    np.testing.assert_allclose(b[[OMEGA, V, THETA_DOT]], [[-g1, g1], [g2, g2], [g3, g3]],
                               rtol=1e-7)


# ----------------------------------------------------------------------------- errors, config

@pytest.mark.parametrize('bad', [np.zeros(7), np.full(8, np.nan), [0.0] * 7 + [math.inf]])
def test_bad_state_raises_value_error(bad):
    plant = Plant(PARAMS)
    with pytest.raises(ValueError, match='plant state'):
        step(plant, bad, 0.0, 0.0, (0.0, 0.0, 0.0), 1e-3)
    with pytest.raises(ValueError, match='plant state'):
        plant.derivative(bad, 0.0, 0.0)


def test_bad_inputs_raise_value_error():
    plant = Plant(PARAMS)
    with pytest.raises(ValueError, match='finite'):
        step(plant, SWINGING, math.nan, 0.0, (0.0, 0.0, 0.0), 1e-3)
    with pytest.raises(ValueError, match='finite'):
        simulate_hold(plant, SWINGING, 0.0, math.inf, None, 0.0, 1e-3, 5)
    with pytest.raises(ValueError, match='dt'):
        step(plant, SWINGING, 0.0, 0.0, (0.0, 0.0, 0.0), 0.0)
    with pytest.raises(ValueError, match='n_steps'):
        simulate_hold(plant, SWINGING, 0.0, 0.0, None, 0.0, 1e-3, -1)
    with pytest.raises(ValueError, match="unknown plant model 'exact'"):
        Plant(PARAMS, 'exact')


def test_plant_config_accepts_only_the_two_models():
    assert from_mapping(PlantParams, {'model': 'full'}, 'plant').model == 'full'
    assert PlantParams().model == 'paper'
    with pytest.raises(ParamError, match=r'plant\.model'):
        from_mapping(PlantParams, {'model': 'exact'}, 'plant')


def test_has_fallen_uses_the_tilt_limit():
    assert not Plant.has_fallen((0, 0, 0, 0, 1.2, 0, 0, 0))
    assert Plant.has_fallen((0, 0, 0, 0, -1.5, 0, 0, 0))
    assert Plant.has_fallen((0, 0, 0, 0, 0.5, 0, 0, 0), limit=0.5)


@pytest.mark.parametrize('model', ['paper', 'full'])
def test_accelerations_on_arrays_equal_the_scalar_derivative(model):
    # The metrics evaluate the dynamics of a whole run at once; they must be the same
    # expressions as Plant.derivative (to rounding) at arbitrary states and torques.
    plant = Plant(ModelParams(), model)
    rng = np.random.default_rng(3)
    n = 50
    theta, omega = rng.uniform(-0.8, 0.8, n), rng.uniform(-2, 2, n)
    v, theta_dot = rng.uniform(-2, 2, n), rng.uniform(-3, 3, n)
    tau_l, tau_r = rng.uniform(-15, 15, n), rng.uniform(-15, 15, n)
    omd, vd, thdd = plant.accelerations_array(theta, omega, v, theta_dot, tau_l, tau_r)
    for i in range(n):
        state = (0.0, 0.0, 0.3, 0.0, theta[i], omega[i], v[i], theta_dot[i])
        expected = plant.derivative(state, tau_l[i], tau_r[i])[5:]
        assert (omd[i], vd[i], thdd[i]) == pytest.approx(tuple(expected), rel=1e-12, abs=1e-12)


def test_axle_friction_dissipates_what_its_power_balance_says():
    # Full model, no input: the friction torques -b·rel_i act between wheel and body, so
    # dE/dt = -b Σ rel_i², with rel = (υ ∓ (d/2) ω)/r − θ̇ the wheels' rates against the body.
    b = 0.05
    plant = Plant(PARAMS, 'full', wheel_friction=b)
    dt = 0.001
    trajectory = _free_run(plant, SWINGING, dt, 5.0)
    energy = np.array([plant.energy(x) for x in trajectory])
    p = PARAMS
    th_dot, om, v = trajectory[:, THETA_DOT], trajectory[:, OMEGA], trajectory[:, V]
    half = 0.5 * p.track_width * om
    rel_left = (v - half) / p.wheel_radius - th_dot
    rel_right = (v + half) / p.wheel_radius - th_dot
    dissipated = simpson(b * (rel_left ** 2 + rel_right ** 2), dx=dt)
    change = energy[-1] - energy[0]
    assert change < -0.1                       # really dissipative (measured -2.76 J)
    # RK4 and Simpson, both O(dt⁴) at 1 ms (the conservative runs drift 1e-9 J): 1e-6 J.
    assert change == pytest.approx(-dissipated, abs=1e-6)
    # Without friction the same run conserves energy (the test above): b = 0 changes nothing.
    assert step(Plant(PARAMS, 'full', wheel_friction=0.0), SWINGING, 1.0, -2.0, (0, 0, 0),
                0.01).tolist() == \
        step(Plant(PARAMS, 'full'), SWINGING, 1.0, -2.0, (0, 0, 0), 0.01).tolist()


@pytest.mark.parametrize('model', MODELS)
def test_axle_friction_matches_the_right_hand_side_it_extends(model):
    # The compiled step and the interpreted derivative agree with friction too: one RK4
    # step of the plant against the textbook RK4 on Plant.derivative.
    plant = Plant(PARAMS, model, wheel_friction=0.3)
    x = np.array(SWINGING)
    expected = rk4_reference(lambda y: plant.derivative(y, 2.0, -1.0), x, 0.002)
    assert step(plant, x, 2.0, -1.0, (0.0, 0.0, 0.0), 0.002) == pytest.approx(expected,
                                                                               rel=1e-12,
                                                                               abs=1e-12)


def test_axle_friction_is_refused_when_negative_or_not_finite():
    for bad in (-0.01, math.nan, math.inf):
        with pytest.raises(ValueError, match='wheel_friction'):
            Plant(PARAMS, 'paper', wheel_friction=bad)
    with pytest.raises(ParamError):
        from_mapping(PlantParams, {'wheel_friction': -1.0}, 'plant')
