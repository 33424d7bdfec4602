"""Wheel-torque mixer, eq. (24) with REP 103 signs, limits and rate limiter."""

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wip_runtime.config import ParamError, from_mapping
from wip_control.core.mixer import MixerParams, WheelTorqueRateLimiter, drive_torque_limit, mix
from wip_control.core.model import input_gains, wheel_to_body_torques
from wip_description.params import ModelParams

finite = dict(allow_nan=False, allow_infinity=False)
MAX = 15.0


def test_mix_inverts_the_models_body_torques_inside_the_limits():
    tau_l, tau_r = mix(8.0, 0.6, MAX)
    assert (tau_l, tau_r) == (3.7, 4.3)
    # τl + τr = τυ and τr − τl = τω (model.wheel_to_body_torques), exact here.
    assert wheel_to_body_torques(tau_l, tau_r) == pytest.approx((8.0, 0.6), abs=1e-15)


def test_positive_yaw_torque_pushes_the_right_wheel_forward_and_turns_ccw():
    tau_l, tau_r = mix(0.0, 0.5, MAX)
    assert tau_r > 0.0 > tau_l
    # With g1 > 0 (eq. (1)), τω = τr − τl > 0 gives ω̇ > 0: counter-clockwise (REP 103).
    g1 = input_gains(ModelParams(), 0.0)[0]
    assert g1 * wheel_to_body_torques(tau_l, tau_r)[1] > 0.0


@settings(max_examples=500, deadline=None)
@given(tau_v=st.floats(-1e3, 1e3, **finite), tau_omega=st.floats(-1e3, 1e3, **finite),
       limit=st.floats(0.01, 100.0, **finite))
def test_wheel_limits_always_hold_and_yaw_is_kept_first(tau_v, tau_omega, limit):
    tau_l, tau_r = mix(tau_v, tau_omega, limit)
    assert abs(tau_l) <= limit and abs(tau_r) <= limit  # clipped: exact bound
    v, w = wheel_to_body_torques(tau_l, tau_r)
    # Rounding of (a ± b)/2 then a + b: a few ulps of the limit.
    tol = 1e-12 * max(1.0, limit)
    if abs(tau_omega) <= 2 * limit:
        assert w == pytest.approx(tau_omega, abs=tol)   # yaw preserved
        if abs(tau_v) <= drive_torque_limit(tau_omega, limit):
            assert v == pytest.approx(tau_v, abs=tol)   # inside: exact mix
        else:
            assert abs(v) == pytest.approx(drive_torque_limit(tau_omega, limit), abs=tol)
            # Drive clipped, never reversed (0 when the yaw torque takes the whole limit,
            # |τω| = 2 τmax: hypothesis found τυ = 1, τω = 0.02, τmax = 0.01).
            assert v * tau_v >= 0
    else:
        assert w == pytest.approx(math.copysign(2 * limit, tau_omega), abs=tol)
        assert v == pytest.approx(0.0, abs=tol)


def test_drive_torque_limit_is_twice_the_wheel_limit_minus_the_yaw_torque():
    assert drive_torque_limit(0.8, 15.0) == pytest.approx(29.2)
    assert drive_torque_limit(-0.8, 15.0) == pytest.approx(29.2)
    assert drive_torque_limit(40.0, 15.0) == 0.0


@pytest.mark.parametrize('args', [(math.nan, 0.0, MAX), (0.0, math.inf, MAX),
                                  (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), (0.0, 0.0, math.nan)])
def test_bad_inputs_raise(args):
    with pytest.raises(ValueError, match='mix:'):
        mix(*args)


@settings(max_examples=200, deadline=None)
@given(requests=st.lists(st.tuples(st.floats(-30, 30, **finite), st.floats(-30, 30, **finite)),
                         min_size=1, max_size=30),
       rate=st.floats(1.0, 1e4, **finite))
def test_rate_limiter_bounds_each_change_and_reaches_reachable_targets(requests, rate):
    dt = 0.005
    limiter = WheelTorqueRateLimiter(rate)
    prev = (0.0, 0.0)
    for tl, tr in requests:
        out = limiter.step(dt, tl, tr)
        for before, after, target in zip(prev, out, (tl, tr)):
            # |Δτ| ≤ rate·dt up to one rounding of the sum.
            assert abs(after - before) <= rate * dt * (1 + 1e-12) + 1e-12
            if abs(target - before) <= rate * dt:
                assert after == pytest.approx(target, abs=1e-12)
        prev = out


def test_default_rate_limit_does_not_bind_at_200_hz():
    # Default 1e4 N·m/s allows 50 N·m per 5 ms period, more than the 30 N·m full swing.
    limiter = WheelTorqueRateLimiter(MixerParams().max_wheel_torque_rate)
    assert limiter.step(0.005, 15.0, -15.0) == (15.0, -15.0)
    assert limiter.step(0.005, -15.0, 15.0) == (-15.0, 15.0)


def test_mixer_config_rejects_non_positive_limit():
    with pytest.raises(ParamError, match=r'^mixer\.max_wheel_torque: must be > 0'):
        from_mapping(MixerParams, {'max_wheel_torque': 0.0}, 'mixer')
    assert from_mapping(MixerParams, {}, 'mixer').max_wheel_torque == 15.0
