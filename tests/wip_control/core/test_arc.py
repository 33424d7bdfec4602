"""Adaptive robust yaw control, eqs. (12)-(13): sign, decay rate, projection, saturation."""

import dataclasses
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wip_control.core.arc import AdaptiveRobustYawController, ArcParams
from wip_runtime.config import ParamError, from_mapping
from wip_control.core.model import input_gains
from wip_description.params import ModelParams
from wip_control.core.controller_settings import PAPER_DESIGN

G1 = input_gains(ModelParams(), 0.05)[0]  # ≈ 2.55 rad/s² per N·m
# The paper's law (13): the tests of this module check it; the robust modifications
# (the default) are tested in test_robust_adaptation.py.
CONFIG = from_mapping(ArcParams, PAPER_DESIGN['arc'], 'arc')
H = 0.005


def closed_loop(config, alpha0, f1, omega_d, e0, dt, duration):
    """ω̇ = f1 + g1 τω (eq. (10)) with τω held over dt; perfect estimates ω̂ = ω, f̂1 = f1.

    With τ held, ω̇ is constant over each period, so the plant step is exact.
    Returns the list of (e_ω, α̂, τω) before each step.
    """
    arc = AdaptiveRobustYawController(config, alpha0)
    omega = omega_d + e0
    out = []
    for _ in range(int(round(duration / dt))):
        res = arc.step(dt, omega, f1, omega_d, 0.0)
        out.append(res)
        omega += (f1 + G1 * res.tau_omega) * dt
    return out, arc


def test_error_decays_at_rate_g1_k_omega_with_exact_alpha():
    # ė_ω = −g1 kω e_ω when α̂ = 1/g1 and f̂1 = f1 (the sign check of arc.py). Adaptation
    # off (γ = 0) so that α̂ stays exact; e0 small enough that τω stays unsaturated.
    config = dataclasses.replace(CONFIG, adaptation_gain=0.0)
    rate = G1 * config.yaw_rate_gain  # ≈ 51 rad/s
    # Sampled at 5 ms: e_{k+1} = (1 − g1 kω h) e_k exactly (forward Euler of the loop).
    out, _ = closed_loop(config, 1 / G1, 0.5, 0.2, 0.01, H, 0.1)
    for a, b in zip(out[:-1], out[1:]):
        assert b.e_omega == pytest.approx((1 - rate * H) * a.e_omega, rel=1e-9, abs=1e-15)
    assert max(abs(o.tau_omega) for o in out) < config.max_yaw_torque
    # Fast sampling approaches the continuous exp(−g1 kω t): (1 − r dt)^(t/dt) differs by
    # t r² dt/2 ≈ 7e-4 relative at dt = 1e-5, t = 0.05 s.
    dt, t_end = 1e-5, 0.05
    out, _ = closed_loop(config, 1 / G1, 0.5, 0.2, 0.01, dt, t_end + dt)
    assert out[-1].e_omega == pytest.approx(0.01 * math.exp(-rate * t_end), rel=1e-3)


def test_torque_cancels_the_disturbance_with_exact_alpha():
    # e_ω = 0, ω̇_d = 0: τω = −α f̂1 so that ω̇ = f1 − g1 α f1 = 0.
    arc = AdaptiveRobustYawController(CONFIG, 1 / G1)
    out = arc.step(H, 0.1, 0.7, 0.1, 0.0)
    assert out.tau_omega == pytest.approx(-0.7 / G1)
    assert out.e_omega == 0.0


def test_adaptation_converges_to_one_over_g1_under_a_constant_disturbance():
    # α̂ < α leaves e_ω = f1(1 − g1 α̂)/(g1 kω) > 0 and (13) raises α̂ at rate γ e f1:
    # α̃ decays at about γ f1²/kω = 2.5 /s, so after 10 s by e^-25.
    out, arc = closed_loop(CONFIG, 0.5 / G1, 1.0, 0.0, 0.0, H, 10.0)
    assert arc.alpha_hat == pytest.approx(1 / G1, rel=1e-6)
    assert abs(out[-1].e_omega) < 1e-6
    # and monotonically from below (first-order slow dynamics)
    alphas = [o.alpha_hat for o in out]
    assert all(b >= a - 1e-15 for a, b in zip(alphas, alphas[1:]))


def test_one_step_follows_eqs_12_and_13():
    arc = AdaptiveRobustYawController(CONFIG, 0.4)
    out = arc.step(H, 0.21, 0.3, 0.2, 0.1)
    e = 0.01  # small enough that τω = −0.28 N·m is unsaturated
    assert out.e_omega == pytest.approx(e)
    assert out.tau_omega == pytest.approx(0.4 * 0.1 - 0.4 * 0.3 - 20 * e)  # Eq. (12)
    assert out.alpha_hat == 0.4  # the α̂ used for this τω
    assert arc.alpha_hat == pytest.approx(0.4 - 50 * e * (0.1 - 0.3) * H)  # Eq. (13)


def test_torque_is_saturated():
    arc = AdaptiveRobustYawController(CONFIG, 0.4)
    assert arc.step(H, 1.0, 0.0, 0.0, 0.0).tau_omega == -CONFIG.max_yaw_torque
    assert arc.step(H, -1.0, 0.0, 0.0, 0.0).tau_omega == CONFIG.max_yaw_torque


finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=200, deadline=None)
@given(steps=st.lists(st.tuples(st.floats(1e-4, 0.1, **finite), st.floats(-50, 50, **finite),
                                st.floats(-100, 100, **finite), st.floats(-5, 5, **finite),
                                st.floats(-100, 100, **finite)), min_size=1, max_size=30),
       alpha0=st.floats(-10.0, 10.0, **finite))
def test_alpha_hat_stays_in_the_projection_interval_and_torque_in_its_limit(steps, alpha0):
    arc = AdaptiveRobustYawController(CONFIG, alpha0)
    assert CONFIG.alpha_min <= arc.alpha_hat <= CONFIG.alpha_max
    for dt, omega_hat, f1_hat, omega_d, omega_d_dot in steps:
        out = arc.step(dt, omega_hat, f1_hat, omega_d, omega_d_dot)
        # Projection by clipping and saturation by clipping: exact bounds.
        assert CONFIG.alpha_min <= arc.alpha_hat <= CONFIG.alpha_max
        assert CONFIG.alpha_min <= out.alpha_hat <= CONFIG.alpha_max
        assert abs(out.tau_omega) <= CONFIG.max_yaw_torque


@pytest.mark.parametrize('args', [(0.0, 0.0, 0.0, 0.0, 0.0), (-H, 0.0, 0.0, 0.0, 0.0),
                                  (H, math.nan, 0.0, 0.0, 0.0), (H, 0.0, math.inf, 0.0, 0.0),
                                  (H, 0.0, 0.0, 0.0, -math.inf)])
def test_bad_inputs_raise_and_leave_alpha_unchanged(args):
    arc = AdaptiveRobustYawController(CONFIG, 0.4)
    with pytest.raises(ValueError, match='finite inputs and dt > 0'):
        arc.step(*args)
    assert arc.alpha_hat == 0.4


def test_projection_bounds_are_validated():
    with pytest.raises(ParamError, match=r'^arc\.alpha_max: must exceed alpha_min'):
        from_mapping(ArcParams, {'alpha_min': 2.0, 'alpha_max': 1.0}, 'arc')
    with pytest.raises(ParamError, match=r'^arc\.alpha_min: must be > 0'):
        from_mapping(ArcParams, {'alpha_min': 0.0}, 'arc')
    # The default interval contains α = 1/g1 for every tilt of the default robot.
    params = ModelParams()
    for theta in (0.0, 0.5, 1.0, math.pi / 2):
        assert CONFIG.alpha_min < 1 / input_gains(params, theta)[0] < CONFIG.alpha_max
