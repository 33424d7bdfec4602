"""Sensor models: encoder kinematics and their inverse, quantisation, IMU, GPS, geodesy."""

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wip_runtime.config import ParamError, from_mapping
from wip_description.params import ModelParams
from wip_description.sensors import (geodetic_to_local, local_to_geodetic, SensorParams, WGS84_A,
                                     WGS84_E2, wheel_odometry)
from wip_sim.core.sensor_models import Sensors

PARAMS = ModelParams()
finite = dict(allow_nan=False, allow_infinity=False)

states = st.tuples(
    st.floats(-100, 100, **finite), st.floats(-100, 100, **finite),   # x, y [m]
    st.floats(-50, 50, **finite), st.floats(-100, 100, **finite),     # ϕ [rad], x_v [m]
    st.floats(-1.5, 1.5, **finite), st.floats(-3, 3, **finite),       # θ [rad], ω [rad/s]
    st.floats(-3, 3, **finite), st.floats(-5, 5, **finite))           # υ [m/s], θ̇ [rad/s]


def state_of(x=0.0, y=0.0, phi=0.0, x_v=0.0, theta=0.0, omega=0.0, v=0.0, theta_dot=0.0):
    return np.array([x, y, phi, x_v, theta, omega, v, theta_dot])


def noisy(**overrides):
    return dataclasses.replace(SensorParams(), **overrides)


# ----------------------------------------------------------------------------- encoders

@settings(max_examples=300, deadline=None)
@given(state=states, initial_yaw=st.floats(-4, 4, **finite), relative=st.booleans())
def test_wheel_odometry_inverts_the_encoders_exactly_without_noise(state, initial_yaw,
                                                                    relative):
    config = noisy(encoders_relative_to_body=relative)
    sensors = Sensors(PARAMS, config, initial_yaw=initial_yaw)
    left, right = sensors.encoders(state)
    x_v, phi = wheel_odometry(left, right, state[4], PARAMS, initial_yaw, relative)
    # Exact up to rounding: angles up to ~600 rad, a few ulps each, scaled by r ≤ 1.
    assert x_v == pytest.approx(state[3], abs=1e-12 * (1 + abs(state[3]) + abs(state[2])))
    assert phi == pytest.approx(state[2], abs=1e-12 * (1 + abs(state[3]) + abs(state[2])))


def test_encoder_signs_follow_the_rolling_kinematics():
    r, d = PARAMS.wheel_radius, PARAMS.track_width
    ideal = Sensors(PARAMS, noisy(encoders_relative_to_body=False))
    # Rolling forward by 2πr turns both wheels one turn forward.
    assert ideal.encoders(state_of(x_v=2 * math.pi * r)) == pytest.approx((2 * math.pi,) * 2)
    # Turning counter-clockwise in place: right wheel forward, left backward, by d/(2r) ϕ.
    left, right = ideal.encoders(state_of(phi=0.4))
    assert (left, right) == pytest.approx((-0.4 * d / (2 * r), 0.4 * d / (2 * r)))
    # Joint encoders: leaning forward over a wheel that stays put turns the wheel
    # backward relative to the body by θ.
    joint = Sensors(PARAMS, SensorParams())
    assert joint.encoders(state_of(theta=0.1)) == pytest.approx((-0.1, -0.1))


@settings(max_examples=300, deadline=None)
@given(state=states, counts=st.integers(16, 100000))
def test_quantisation_error_is_at_most_half_a_count(state, counts):
    exact = Sensors(PARAMS, SensorParams()).encoders(state)
    quantised = Sensors(PARAMS, noisy(encoder_counts_per_rev=counts)).encoders(state)
    count = 2 * math.pi / counts
    for q, e in zip(quantised, exact):
        # Half a count plus the rounding of q·round(e/q) on angles up to ~600 rad.
        assert abs(q - e) <= 0.5 * count + 1e-12 * (1 + abs(e))
        assert abs(q / count - round(q / count)) < 1e-6      # a whole number of counts


# ----------------------------------------------------------------------------- IMU, GPS

def test_default_sensors_are_noise_free_and_unquantised():
    config = SensorParams()
    assert config.encoder_counts_per_rev == 0
    assert (config.imu_pitch_noise_std, config.imu_yaw_noise_std, config.gyro_noise_std,
            config.gps_noise_std) == (0.0, 0.0, 0.0, 0.0)
    state = state_of(x=1.5, y=-2.0, phi=0.3, theta=0.05, omega=0.2, theta_dot=-0.1)
    sensors = Sensors(PARAMS)
    assert sensors.imu(state) == (0.05, 0.3)
    assert sensors.imu_rates(state) == (-0.1, 0.2)
    assert sensors.gps(state) == (1.5, -2.0)
    assert (sensors.config.imu_rate, sensors.config.encoder_rate,
            sensors.config.gps_rate) == (200.0, 200.0, 10.0)


@settings(max_examples=300, deadline=None)
@given(phi=st.floats(-100, 100, **finite))
def test_imu_yaw_is_wrapped_to_minus_pi_pi(phi):
    _, yaw = Sensors(PARAMS).imu(state_of(phi=phi))
    assert -math.pi < yaw <= math.pi
    turns = (phi - yaw) / (2 * math.pi)
    assert turns == pytest.approx(round(turns), abs=1e-12)   # same angle mod 2π


def test_imu_yaw_wrap_edges():
    sensors = Sensors(PARAMS)
    assert sensors.imu(state_of(phi=math.pi))[1] == pytest.approx(math.pi)
    assert sensors.imu(state_of(phi=-math.pi))[1] == pytest.approx(math.pi)


def test_noise_has_the_configured_std_and_is_reproducible_from_the_seed():
    config = noisy(imu_pitch_noise_std=0.01, imu_yaw_noise_std=0.02, gps_noise_std=0.5)
    state = state_of(x=3.0, y=4.0, phi=0.5, theta=0.1)
    n = 4000
    sensors = Sensors(PARAMS, config, seed=11)
    imu = np.array([sensors.imu(state) for _ in range(n)])
    gps = np.array([sensors.gps(state) for _ in range(n)])
    errors = np.column_stack([imu - (0.1, 0.5), gps - (3.0, 4.0)])
    # Sample std within 4 standard errors σ/√(2n) (≈ 4.5 % for n = 4000).
    np.testing.assert_allclose(errors.std(axis=0), [0.01, 0.02, 0.5, 0.5],
                               rtol=4 / math.sqrt(2 * n))
    again = Sensors(PARAMS, config, seed=11)
    assert again.imu(state) == tuple(imu[0]) and again.gps(state) == tuple(gps[0])
    assert Sensors(PARAMS, config, seed=12).imu(state) != tuple(imu[0])


def test_sensor_noise_streams_are_independent_of_each_other():
    state = state_of(theta=0.1)
    imu_only = Sensors(PARAMS, noisy(imu_pitch_noise_std=0.01), seed=5)
    both = Sensors(PARAMS, noisy(imu_pitch_noise_std=0.01, gps_noise_std=1.0), seed=5)
    for _ in range(10):
        both.gps(state)          # draws from the GPS stream must not shift the IMU's
        assert imu_only.imu(state) == both.imu(state)


# ----------------------------------------------------------------------------- geodesy

datums = st.tuples(st.floats(-80, 80, **finite), st.floats(-180, 180, **finite),
                   st.floats(-100, 3000, **finite))


@settings(max_examples=300, deadline=None)
@given(x=st.floats(-5000, 5000, **finite), y=st.floats(-5000, 5000, **finite),
       z=st.floats(-50, 50, **finite), datum=datums)
def test_geodetic_round_trip_is_within_a_millimetre(x, y, z, datum):
    lat, lon, alt = local_to_geodetic(x, y, *datum, z=z)
    back = geodetic_to_local(lat, lon, alt, *datum)
    # 1 mm required; ECEF coordinates ~6.4e6 m carry ~1e-9 m of rounding.
    np.testing.assert_allclose(back, (x, y, z), atol=1e-3)


@pytest.mark.parametrize('datum_lat', [-60.0, 0.0, 38.8816, 75.0])
def test_small_displacements_follow_the_wgs84_radii_of_curvature(datum_lat):
    # Closed forms at height h: north = (M + h) Δφ, east = (N + h) cosφ Δλ, with the
    # meridian radius M = a(1−e²)/(1−e² sin²φ)^{3/2} and the prime-vertical radius
    # N = a/√(1−e² sin²φ).
    s = math.sin(math.radians(datum_lat))
    w = math.sqrt(1 - WGS84_E2 * s * s)
    m, n = WGS84_A * (1 - WGS84_E2) / w ** 3 + 50.0, WGS84_A / w + 50.0
    delta = 1e-5   # degrees, ~1 m: second-order terms ~ (1 m)²/R ~ 1e-7 m
    east, north, _ = geodetic_to_local(datum_lat + delta, 10.0, 50.0, datum_lat, 10.0, 50.0)
    assert east == pytest.approx(0.0, abs=1e-6)
    assert north == pytest.approx(m * math.radians(delta), abs=1e-6)
    east, north, _ = geodetic_to_local(datum_lat, 10.0 + delta, 50.0, datum_lat, 10.0, 50.0)
    assert east == pytest.approx(n * math.cos(math.radians(datum_lat)) * math.radians(delta),
                                 abs=1e-6)
    assert north == pytest.approx(0.0, abs=1e-6)


def test_points_of_the_tangent_plane_rise_above_the_ellipsoid_with_distance():
    # A plane point at distance D is D²/(2R) above the datum height (R between M and N).
    lat, lon, alt = local_to_geodetic(0.0, 1000.0, 45.0, 7.0, 100.0)
    assert alt - 100.0 == pytest.approx(1000.0 ** 2 / (2 * 6.37e6), rel=0.01)
    assert geodetic_to_local(45.0, 7.0, 100.0, 45.0, 7.0, 100.0) == pytest.approx((0, 0, 0),
                                                                                  abs=1e-9)


def test_gps_fix_is_the_gps_position_about_the_configured_datum():
    sensors = Sensors(PARAMS)
    c = sensors.config
    lat, lon, alt = sensors.gps_fix(state_of(x=12.0, y=-7.0))
    back = geodetic_to_local(lat, lon, alt, c.gps_datum_latitude, c.gps_datum_longitude,
                             c.gps_datum_altitude)
    np.testing.assert_allclose(back[:2], (12.0, -7.0), atol=1e-6)


# ----------------------------------------------------------------------------- errors, config

@pytest.mark.parametrize('mapping, key', [
    ({'gps_noise_std': -0.1}, 'sensors.gps_noise_std'),
    ({'imu_rate': 0.0}, 'sensors.imu_rate'),
    ({'encoder_counts_per_rev': 10.5}, 'sensors.encoder_counts_per_rev'),
    ({'gps_rate_hz': 10.0}, 'sensors.gps_rate_hz: unknown key'),
])
def test_bad_sensor_config_names_the_key(mapping, key):
    with pytest.raises(ParamError, match='^' + key.replace('.', r'\.')):
        from_mapping(SensorParams, mapping, 'sensors')


def test_bad_inputs_raise_value_error():
    with pytest.raises(ValueError, match='finite'):
        Sensors(PARAMS).encoders(state_of(x_v=math.nan))
    with pytest.raises(ValueError, match='finite'):
        wheel_odometry(0.0, math.inf, 0.0, PARAMS)
    with pytest.raises(ValueError, match='latitude'):
        geodetic_to_local(91.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match='seed'):
        Sensors(PARAMS, seed=-3)


# ---------------------------------------------------------------- real-sensor models

STATE = np.array([1.0, 2.0, 0.3, 4.0, 0.05, 0.2, 0.5, -0.1])


def test_gyro_bias_adds_to_the_rates():
    sensors = Sensors(ModelParams(), SensorParams(gyro_pitch_bias=0.02,
                                                    gyro_yaw_bias=-0.01))
    assert sensors.imu_rates(STATE) == pytest.approx((-0.1 + 0.02, 0.2 - 0.01), abs=1e-15)


def test_gps_dropouts_follow_the_configured_probability_on_their_own_stream():
    # 4000 fixes at p = 0.3: binomial std √(n p (1 − p)) = 29, bound 4 std. The dropout
    # draws do not shift the GPS noise sequence (separate stream).
    config = SensorParams(gps_dropout_probability=0.3, gps_noise_std=0.1)
    sensors = Sensors(ModelParams(), config, seed=5)
    reference = Sensors(ModelParams(), dataclasses.replace(
        config, gps_dropout_probability=0.0), seed=5)
    available = [sensors.gps_fix_available() for _ in range(4000)]
    assert abs(available.count(False) - 1200) < 4 * 29
    assert sensors.gps(STATE) == reference.gps(STATE)
    assert all(Sensors(ModelParams()).gps_fix_available() for _ in range(10))


def test_delays_return_the_states_of_earlier_samples():
    # 200 Hz IMU: sensor_delay 0.01 s = 2 samples, gps_latency 0.1 s = 20 samples; the
    # first state is repeated until the history is long enough.
    config = SensorParams(sensor_delay=0.01, gps_latency=0.1)
    sensors = Sensors(ModelParams(), config)
    assert (sensors.sensor_delay_samples, sensors.gps_latency_samples) == (2, 20)
    states = [np.full(8, float(k)) for k in range(30)]
    seen = [sensors.delayed(s) for s in states]
    for k, (sensed, gps) in enumerate(seen):
        assert sensed[0] == max(0, k - 2)
        assert gps[0] == max(0, k - 20)
    # No delay: the state itself, nothing stored.
    plain = Sensors(ModelParams())
    assert plain.delayed(STATE)[0] is STATE and plain.delayed(STATE)[1] is STATE
