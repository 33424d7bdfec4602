"""Saturated trajectory generator, eq. (9): errors, limits, Lyapunov decrease, ω̇_d."""

import dataclasses
import math

import numpy as np
import pytest
from wip_control.core.integration import rk4_step
from hypothesis import given, settings
from hypothesis import strategies as st

from wip_control.core.reference_curves import Circle
from wip_control.core.reference_state import ReferenceState
from wip_control.core.trajectory_generator import (TrajectoryGenerator,
                                                   TrajectoryGeneratorParams,
                                                   tracking_errors, unsaturated_commands)

# Eq. (9) with the paper's lambda1, lambda2 (the pole-placed design: test_heading_design.py).
CONFIG = TrajectoryGeneratorParams(heading_design='paper', lambda3=1.0)
DT = 0.005

finite = dict(allow_nan=False, allow_infinity=False)
positions = st.floats(-100.0, 100.0, **finite)
angles = st.floats(-20.0, 20.0, **finite)
references = st.builds(ReferenceState, positions, positions, angles,
                       st.floats(0.0, 3.0, **finite), st.floats(-2.0, 2.0, **finite),
                       st.floats(-5.0, 5.0, **finite))


def v2(config, x_e, y_e, phi_e):
    """V2 = λ1 ln(1 + x_e² + y_e²)/2 + ϕ_e²/2 (Section IV-A)."""
    return config.lambda1 * math.log(1 + x_e ** 2 + y_e ** 2) / 2 + phi_e ** 2 / 2


def test_errors_are_in_the_body_frame():
    # Vehicle at the origin facing +y; reference 1 m to the east = to its right.
    ref = ReferenceState(1.0, 0.0, 0.3, 0.5, 0.0, 0.0)
    x_e, y_e, phi_e = tracking_errors(ref, 0.0, 0.0, math.pi / 2)
    assert (x_e, y_e) == pytest.approx((0.0, -1.0), abs=1e-15)
    assert phi_e == pytest.approx(0.3 - math.pi / 2)
    # ϕ_e wrapped to (−π, π]: 2π-equivalent headings give the same error.
    assert tracking_errors(ref, 0.0, 0.0, math.pi / 2 + 4 * math.pi)[2] == \
        pytest.approx(phi_e, abs=1e-12)


def test_commands_follow_eq_9_inside_the_limits():
    ref = ReferenceState(0.0, 0.0, 0.0, 0.4, 0.05, 0.0)
    gen = TrajectoryGenerator(CONFIG)
    cmd = gen.step(0.0, ref, -0.2, -0.1, -0.05)
    x_e, y_e, phi_e = tracking_errors(ref, -0.2, -0.1, -0.05)
    sinc = math.sin(phi_e) / phi_e
    expected_w = 0.05 + 1.0 * 0.4 * y_e * sinc / (1 + x_e ** 2 + y_e ** 2) \
        + 0.1 * math.tanh(phi_e)
    expected_v = 0.4 * math.cos(phi_e) + 1.0 * math.tanh(x_e)
    assert (cmd.v_d, cmd.omega_d) == pytest.approx((expected_v, expected_w), rel=1e-14)
    assert (cmd.x_e, cmd.y_e, cmd.phi_e) == (x_e, y_e, phi_e)
    assert not gen.saturated_speed and not gen.saturated_yaw_rate
    # sinc is finite at ϕ_e = 0
    assert math.isfinite(gen.step(DT, ref, 0.1, 0.1, ref.phi).omega_d)


@settings(max_examples=300, deadline=None)
@given(ref=references, poses=st.lists(st.tuples(positions, positions, angles),
                                      min_size=1, max_size=6))
def test_commands_stay_within_their_limits_for_arbitrary_errors(ref, poses):
    gen = TrajectoryGenerator(CONFIG)
    for k, (x, y, phi) in enumerate(poses):
        cmd = gen.step(k * DT, ref, x, y, phi)
        # Explicit saturation: exact bounds (copysign of the limit).
        assert abs(cmd.v_d) <= CONFIG.max_speed
        assert abs(cmd.omega_d) <= CONFIG.max_yaw_rate
        assert abs(cmd.omega_d_dot) <= CONFIG.max_yaw_acceleration
        assert all(math.isfinite(v) for v in cmd)


@settings(max_examples=200, deadline=None)
@given(omegas=st.lists(st.floats(-1.0, 1.0, **finite), min_size=2, max_size=40))
def test_filtered_derivative_is_bounded_by_twice_the_limit_over_tau_plus_dt(omegas):
    # Without the clip, |ω̇_d| ≤ 2 ω_max/(τ + Δt) for any sequence of saturated ω_d
    # (Abel summation, trajectory_generator.py): ω_d is driven here through ω_r.
    config = dataclasses.replace(CONFIG, max_yaw_acceleration=1e9)
    gen = TrajectoryGenerator(config)
    bound = 2 * config.max_yaw_rate / (config.yaw_rate_derivative_time_constant + DT)
    for k, w in enumerate(omegas):
        cmd = gen.step(k * DT, ReferenceState(0.0, 0.0, 0.0, 0.5, w, 0.0), 0.0, 0.0, 0.0)
        assert abs(cmd.omega_d_dot) <= bound * (1 + 1e-12)


@settings(max_examples=300, deadline=None)
@given(ref=references, x=st.floats(-5.0, 5.0, **finite), y=st.floats(-5.0, 5.0, **finite),
       phi=angles)
def test_lyapunov_function_decreases_along_the_unsaturated_kinematic_loop(ref, x, y, phi):
    # Unicycle with perfect velocity tracking (υ = υ_d, ω = ω_d), reference moving with
    # (υ_r, ω_r) along ϕ_r. Time derivatives of the body-frame errors by the chain rule
    # in the map frame (independent of the generator's formulas), then V̇2.
    x_e, y_e, phi_e = tracking_errors(ref, x, y, phi)
    v_d, w_d = unsaturated_commands(CONFIG, ref, x_e, y_e, phi_e)
    if abs(v_d) > CONFIG.max_speed or abs(w_d) > CONFIG.max_yaw_rate:
        return  # saturation active: (9)'s proof does not apply
    dx, dy = ref.x - x, ref.y - y
    ddx = ref.v * math.cos(ref.phi) - v_d * math.cos(phi)
    ddy = ref.v * math.sin(ref.phi) - v_d * math.sin(phi)
    c, s = math.cos(phi), math.sin(phi)
    x_e_dot = -s * w_d * dx + c * ddx + c * w_d * dy + s * ddy
    y_e_dot = -c * w_d * dx - s * ddx - s * w_d * dy + c * ddy
    phi_e_dot = ref.omega - w_d
    v2_dot = (CONFIG.lambda1 * (x_e * x_e_dot + y_e * y_e_dot) / (1 + x_e ** 2 + y_e ** 2)
              + phi_e * phi_e_dot)
    # Closed form: −λ1 λ3 x_e tanh x_e/(1 + x_e² + y_e²) − λ2 ϕ_e tanh ϕ_e ≤ 0.
    closed = (-CONFIG.lambda1 * CONFIG.lambda3 * x_e * math.tanh(x_e)
              / (1 + x_e ** 2 + y_e ** 2) - CONFIG.lambda2 * phi_e * math.tanh(phi_e))
    # Rounding: terms of size |ref.v|·|d| ≤ 3·150 cancel; 1e-12 relative to that scale.
    scale = 1.0 + ref.v * (abs(dx) + abs(dy)) + abs(w_d) * (abs(dx) + abs(dy))
    assert v2_dot == pytest.approx(closed, abs=1e-12 * scale)
    assert v2_dot <= 1e-12 * scale


def test_lyapunov_function_decreases_in_closed_loop_simulation_on_a_slow_circle():
    # Slow circle (υ_r = 0.2 m/s, ω_r = 0.05 rad/s) and the paper's initial errors: the
    # saturation never binds, so V2 must decrease monotonically. RK4 at 10 ms of
    # ẋ = υ_d cos ϕ, ẏ = υ_d sin ϕ, ϕ̇ = ω_d with the commands evaluated at each stage.
    ref = Circle(center=(0.0, 0.0), radius=4.0, speed=0.2)
    r0 = ref.sample(0.0)
    phi = r0.phi - 0.1
    pose = np.array([r0.x - (math.cos(phi) * 0.5 - math.sin(phi) * 0.5),
                     r0.y - (math.sin(phi) * 0.5 + math.cos(phi) * 0.5), phi])

    def rates(t, p):
        r = ref.sample(t)
        x_e, y_e, phi_e = tracking_errors(r, *p)
        v_d, w_d = unsaturated_commands(CONFIG, r, x_e, y_e, phi_e)
        assert abs(v_d) < CONFIG.max_speed and abs(w_d) < CONFIG.max_yaw_rate
        return np.array([v_d * math.cos(p[2]), v_d * math.sin(p[2]), w_d])

    h = 0.01
    values = []
    for k in range(6000):  # 60 s
        t = k * h
        values.append(v2(CONFIG, *tracking_errors(ref.sample(t), *pose)))
        pose = rk4_step(rates, t, pose, h)
    values = np.array(values)
    assert values[0] == pytest.approx(math.log(1.5) / 2 + 0.005)  # (0.5, 0.5, 0.1)
    # Monotone up to RK4's error (h⁵-order, ~1e-12 per step here).
    assert np.diff(values).max() <= 1e-10
    assert values[-1] < 0.01 * values[0]  # converging (slowly: λ2 = 0.1 on ϕ_e)


def test_omega_d_dot_is_zero_while_omega_d_is_saturated_and_constant():
    gen = TrajectoryGenerator(CONFIG)
    ref = ReferenceState(0.0, 0.0, 0.0, 0.6, 0.7, 0.0)  # ω_r = 0.7 > ω_max: petal tip
    cmds = [gen.step(k * DT, ref, 0.0, 0.0, 0.0) for k in range(5)]
    assert [c.omega_d for c in cmds] == [0.3] * 5
    assert [c.omega_d_dot for c in cmds] == [0.0] * 5


def test_omega_d_dot_tracks_a_ramp_of_omega_d_after_the_filter_lag():
    # Vehicle on the reference: ω_d = ω_r = a t. Backward-Euler filtered derivative of a
    # ramp: ω̇_k − a = (τ/(τ+Δt))(ω̇_{k−1} − a), so after 1 s (20 τ) it equals a to
    # (0.909)^200 ≈ 6e-9 relative.
    gen = TrajectoryGenerator(CONFIG)
    a = 0.1
    for k in range(201):
        t = k * DT
        cmd = gen.step(t, ReferenceState(0.0, 0.0, 0.0, 0.3, a * t, a), 0.0, 0.0, 0.0)
    assert cmd.omega_d == pytest.approx(a * 1.0)
    assert cmd.omega_d_dot == pytest.approx(a, rel=1e-7)
    gen.reset()
    assert gen.step(2.0, ReferenceState(0.0, 0.0, 0.0, 0.3, 0.2, a), 0.0, 0.0,
                    0.0).omega_d_dot == 0.0


def test_non_finite_inputs_and_time_reversal_raise():
    gen = TrajectoryGenerator(CONFIG)
    ref = ReferenceState(0.0, 0.0, 0.0, 0.3, 0.0, 0.0)
    with pytest.raises(ValueError, match='non-finite'):
        gen.step(0.0, ref, math.nan, 0.0, 0.0)
    with pytest.raises(ValueError, match='non-finite'):
        gen.step(0.0, ref._replace(phi=math.inf), 0.0, 0.0, 0.0)
    gen.step(1.0, ref, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match='backwards'):
        gen.step(0.5, ref, 0.0, 0.0, 0.0)
