"""The gyro-aided estimator ('gyro', the default).

Closed forms of its two loops, noise gains against bandwidth, bias and disturbance convergence, the
WIP observer with it.

See core/rate_aided.py (RateAidedChannel) and docs/estimation.md.
"""

import math

import numpy as np
import pytest
from wip_control.core.integration import rk4_step

from wip_runtime.config import ParamError, from_mapping
from wip_control.core.eso import EsoParams
from wip_control.core.rate_aided import (complementary_bandwidth, discrete_pole_gains,
                                         rate_eso_noise_variance, RateAidedChannel)
from wip_control.core.state_observer import WipStateObserver
from wip_description.params import ModelParams

H = 0.005


@pytest.mark.parametrize('a, b', [(5.0, 0.2), (40.0, 40.0), (100.0, 3.0)])
def test_discrete_gains_place_the_error_poles(a, b):
    # Both loops share the error matrix [[1 − L1, −(1 − L1) h], [L2, 1 − L2 h]] (eso.py):
    # its eigenvalues must be e^{−a h}, e^{−b h}.
    l1, l2 = discrete_pole_gains(a, b, H)
    matrix = np.array([[1 - l1, -(1 - l1) * H], [l2, 1 - l2 * H]])
    # Characteristic polynomials (a double pole's eigenvalues are ill-conditioned).
    wanted = np.poly([math.exp(-a * H), math.exp(-b * H)])
    assert np.poly(matrix) == pytest.approx(wanted, abs=1e-12)


def test_rate_eso_noise_variance_closed_form_and_its_cubic_growth():
    # Discrete Lyapunov variance vs the continuous σ² h ω³/4 (H2 norm of ω² s/(s + ω)²):
    # within 20 % while ω h ≤ 0.2; and the cube law between two bandwidths.
    sigma = 0.01
    for w in (10.0, 20.0, 40.0):
        exact = rate_eso_noise_variance(sigma, w, H)
        approx = rate_eso_noise_variance(sigma, w, H, exact=False)
        assert exact == pytest.approx(approx, rel=0.2)
    ratio = rate_eso_noise_variance(sigma, 40.0, H) / rate_eso_noise_variance(sigma, 20.0, H)
    assert ratio == pytest.approx(8.0, rel=0.2)


def test_channel_noise_matches_the_closed_forms():
    # White rate noise σg and angle noise σa on a motionless channel: f̂ has the discrete
    # Lyapunov variance (sampling error of the estimate over 40 000 correlated samples
    # below 10 %), and the angle error the complementary filter's h σa σg at the optimal
    # crossover ω_c = σg/σa (continuous formula; 25 % margin for the bias loop and the
    # discretisation).
    rng = np.random.default_rng(3)
    sigma_a, sigma_g = 0.002, 0.01
    w_c = complementary_bandwidth(sigma_a, sigma_g)
    assert w_c == pytest.approx(5.0)
    channel = RateAidedChannel(w_c, 0.05, 40.0, H)
    n = 40000
    f_hat, angle = np.empty(n), np.empty(n)
    for k in range(n):
        out = channel.update((k + 1) * H, sigma_a * rng.standard_normal(),
                             sigma_g * rng.standard_normal(), 0.0)
        angle[k], f_hat[k] = out[0], out[2]
    skip = 4000  # the bias loop (0.05 rad/s) settles
    assert np.var(f_hat[skip:]) == pytest.approx(
        rate_eso_noise_variance(sigma_g, 40.0, H), rel=0.1)
    assert np.var(angle[skip:]) == pytest.approx(H * sigma_a * sigma_g, rel=0.25)
    # Against the raw angle the filter cuts the noise by sqrt(σa / (h σg)) = 6.3.
    assert np.std(angle[skip:]) < sigma_a / 5.0


def test_gyro_bias_and_a_constant_disturbance_are_estimated():
    # θ̈ = b u + f with f = 0.8 rad/s², the gyro reads θ̇ + 0.05 rad/s: after 10 bias time
    # constants (1/0.5 s each) the bias, the rate and f are exact to e^-10 of their
    # initial errors (the loops are linear and time invariant), the angle unbiased.
    channel = RateAidedChannel(5.0, 0.5, 40.0, H)
    theta, rate, f, b_u, bias = 0.0, 0.0, 0.8, -0.5, 0.05
    for k in range(1, int(20.0 / H) + 1):
        theta += H * rate + 0.5 * H * H * (f + b_u)
        rate += H * (f + b_u)
        channel.update(k * H, theta, rate + bias, b_u)
    assert channel.bias == pytest.approx(bias, abs=1e-5)
    assert channel.f == pytest.approx(f, abs=1e-4)
    assert channel.x2 == pytest.approx(rate, abs=1e-5)
    assert channel.x1 == pytest.approx(theta, abs=1e-5)


def test_channel_rejects_bad_input_with_one_line_errors():
    channel = RateAidedChannel(5.0, 0.2, 40.0, H)
    with pytest.raises(ValueError, match='non-finite'):
        channel.update(H, math.nan, 0.0, 0.0)
    with pytest.raises(ValueError, match='backwards'):
        channel.update(-1.0, 0.0, 0.0, 0.0)
    with pytest.raises(ParamError, match='rate_bandwidth'):
        RateAidedChannel(5.0, 0.2, 0.0, H)
    with pytest.raises(ValueError, match='noise levels'):
        complementary_bandwidth(0.0, 0.01)


def test_config_checks_bandwidths_against_the_sample_period_and_each_other():
    with pytest.raises(ParamError, match=r'^eso\.sample_period: the fastest'):
        from_mapping(EsoParams, {'longitudinal_bandwidth': 250.0}, 'eso')
    with pytest.raises(ParamError, match=r'^eso\.gyro_bias_bandwidth: must be below'):
        from_mapping(EsoParams, {'gyro_bias_bandwidth': 6.0}, 'eso')
    # The paper's estimator ignores the gyro bandwidths.
    from_mapping(EsoParams, {'estimator': 'paper', 'gyro_bias_bandwidth': 6.0}, 'eso')


def test_wip_observer_needs_the_rates_with_the_gyro_estimator():
    observer = WipStateObserver(ModelParams(), EsoParams(), (0.0, 0.0, 0.0))
    assert observer.needs_rates and not observer.in_ramp(0.0)
    with pytest.raises(ValueError, match="'gyro' estimator needs the IMU rates"):
        observer.update(H, 0.0, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match='non-finite rates'):
        observer.update(H, 0.0, 0.0, 0.0, 0.0, 0.0, (math.inf, 0.0))


def _simulate(config, duration, params=ModelParams(), pitch_noise=0.0, seed=0):
    """Paper plant (1), RK4 at 1 ms, torques held 5 ms; returns truth and estimates."""
    from wip_control.core.model import nominal_terms
    rng = np.random.default_rng(seed)
    state = np.array([0.2, 0.1, 0.05, 0.0, 0.0, 0.0])  # phi, x_v, theta, omega, v, theta_dot
    observer = WipStateObserver(params, config, initial_positions=state[:3],
                                encoders_relative_to_body=False)

    def derivative(s, tau_v, tau_w, t):
        terms = nominal_terms(params, s[2], s[3], s[5])
        return np.array([s[3], s[4], s[5],
                         terms.f1 + math.sin(0.5 * t) + terms.g1 * tau_w,
                         terms.f2 + 0.3 * math.cos(2.0 * t) + terms.g2 * tau_v,
                         terms.f3 + terms.g3 * tau_v])

    rows = []
    tau_v = tau_w = 0.0
    observer.update(0.0, state[0], state[1], state[2], 0.0, 0.0, (state[5], state[3]))
    for k in range(int(round(duration / H))):
        t = k * H
        for i in range(5):
            ti, dt = t + i * 1e-3, 1e-3
            state = rk4_step(lambda t_, x: derivative(x, tau_v, tau_w, t_), ti, state, dt)
        t1 = t + H
        theta_meas = state[2] + pitch_noise * rng.standard_normal()
        est = observer.update(t1, state[0], state[1], theta_meas, tau_v, tau_w,
                              (state[5], state[3]))
        terms = nominal_terms(params, state[2], state[3], state[5])
        truth = (state[3], state[4], state[5], terms.f1 + math.sin(0.5 * t1),
                 terms.f2 + 0.3 * math.cos(2.0 * t1), terms.f3, state[2])
        if t1 > 1.0:
            rows.append((truth, est))
        tau_v = float(np.clip(60.0 * est.theta + 15.0 * est.theta_dot, -30, 30))
        tau_w = 0.3 * math.sin(3.0 * t1)
    return rows


def test_wip_observer_with_gyro_tracks_states_and_disturbances_of_the_model():
    config = EsoParams(yaw_input_gain_scale=1.0)
    rows = _simulate(config, 3.0)
    truth = np.array([r[0] for r in rows])
    est = np.array([(r[1].omega, r[1].v, r[1].theta_dot, r[1].f1, r[1].f2, r[1].f3,
                     r[1].theta) for r in rows])
    err = np.abs(est - truth).max(axis=0)
    f_dot = np.abs(np.diff(truth[:, 3:6], axis=0)).max(axis=0) / H
    w = np.array([config.yaw_rate_bandwidth, config.longitudinal_bandwidth,
                  config.tilt_rate_bandwidth])
    # Quasi-static lags on a ramp of f: the rate ESO (double pole ω) has f error 2ḟ/ω
    # and rate error ḟ/ω²; the x_v ESO (triple pole, gains 3ω, 3ω², ω³) has f error
    # 3ḟ/ω and rate error 3ḟ/ω². 50 % margin for the curvature of f, plus the
    # interpolation bias of the x_v channel (as in test_eso).
    accel = np.abs(np.diff(truth[:, :3], axis=0)).max(axis=0) / H
    assert (err[3:6] <= 1.5 * np.array([2.0, 3.0, 2.0]) / w * f_dot
            + 0.005 * accel).all(), (err, f_dot)
    assert (err[:3] <= 1.5 * np.array([1.0, 3.0, 1.0]) / w ** 2 * f_dot
            + 1e-4 * accel).all(), (err, f_dot)
    assert err[6] < 1e-4   # θ̂: exact angle and rate, no noise


def test_pitch_noise_is_filtered_before_it_reaches_the_mpc():
    # 0.002 rad of IMU pitch noise: the paper's ESO (poles up to 300 rad/s) turns it into
    # θ̂̇ noise of order σ/ε; the gyro estimator reads θ̇ and passes θ̂ through the
    # complementary filter. Measured on the same seed: θ̂̇ error std 0.0006 rad/s (gyro,
    # the angle noise through the bias estimate) against 0.26 rad/s (paper); bounds 0.01 and
    # 0.2. θ̂ error 0.00027 against 0.0017 rad (paper); bound
    # σ/3.
    gyro = _simulate(EsoParams(), 3.0, pitch_noise=0.002, seed=1)
    paper = _simulate(EsoParams(estimator='paper'), 3.0, pitch_noise=0.002, seed=1)

    def errors(rows):
        truth = np.array([(r[0][2], r[0][6]) for r in rows])
        est = np.array([(r[1].theta_dot, r[1].theta) for r in rows])
        return np.std(est - truth, axis=0)

    (rate_gyro, angle_gyro), (rate_paper, _) = errors(gyro), errors(paper)
    assert rate_gyro < 0.01 < 0.2 < rate_paper
    assert angle_gyro < 0.002 / 3


@pytest.mark.parametrize('estimator', ['gyro', 'paper'])
def test_a_vehicle_engaged_at_speed_reads_its_speed_from_the_second_sample(estimator):
    """A vehicle engaged at speed reads its speed from the second sample.

    eso.speed_start 'first_difference': on a distance ramp at 1.5 m/s (no torque, no
    disturbance) the speed estimate is exactly the ramp's slope from the second sample on,
    and f2 stays 0; 'zero' (Section V) reads rest first and then a disturbance transient.
    """
    params = ModelParams()
    h, speed = 0.005, 1.5

    def run(speed_start):
        config = from_mapping(EsoParams, {'estimator': estimator, 'speed_start': speed_start,
                                          'epsilon_schedule': 'constant'}, 'eso')
        observer = WipStateObserver(params, config, initial_positions=(0.0, 0.0, 0.0))
        out = []
        for k in range(1, 41):
            out.append(observer.update(k * h, 0.0, speed * k * h, 0.0, 0.0, 0.0, (0.0, 0.0)))
        return out

    started = run('first_difference')
    # The constant-velocity ramp is a fixed point of the observer once (x, v, f) match it.
    for estimate in started:
        assert estimate.v == pytest.approx(speed, rel=1e-12)
        assert abs(estimate.f2) < 1e-9
    at_rest = run('zero')
    assert abs(at_rest[0].v - speed) > 0.3             # far from the truth at first
    assert max(abs(e.f2) for e in at_rest) > 1.0       # and a disturbance transient
