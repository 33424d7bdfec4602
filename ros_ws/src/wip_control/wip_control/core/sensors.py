"""Sensor models of the simulated WIP and their inverses for the estimators.

What a real base provides, and what the paper's ESOs (eq. (4) of [1]_) measure:

- **wheel encoders**: the two wheel joint angles φl, φr [rad]. The wheels roll without
  slip, so the rolling angles (wheel relative to the ground frame's vertical) satisfy
  x_v = r (φl + φr)/2 and ϕ − ϕ0 = r (φr − φl)/d (spec, section 1; d is the distance
  between the wheels). A real encoder measures the wheel **relative to the chassis**,
  which tilts with θ: joint angle = rolling angle − θ (both are rotations about the
  axle, positive forward). With ``encoders_relative_to_body`` (default) the model
  reports joint angles, and :func:`wheel_odometry` adds θ back:
  x_v = r ((φl + φr)/2 + θ). The yaw needs no correction: θ cancels in φr − φl.
  The angles are absolute: zero at x_v = 0, ϕ = ϕ0, θ = 0.
  Optional quantisation to ``encoder_counts_per_rev`` (rounded to the nearest count,
  so the error is at most half a count, 2π/(2N) rad).
- **IMU**: pitch θ and yaw ϕ [rad] (yaw wrapped to (−π, π]) and, for the ``Imu``
  message's angular velocity, the rates (θ̇, ω) [rad/s] of these two angles.
- **GPS**: the planar position (x, y) [m] in the map frame (REP 103/105: x east,
  y north), published by the nodes as NavSatFix around a datum with
  :func:`local_to_geodetic`, read back with :func:`geodetic_to_local`.

Noise (zero-mean Gaussian, independent per sample and per axis) is off by default, so
the paper scenario is clean; scenarios enable it. The random streams of encoders,
IMU and GPS are separate (a change in one sensor's noise does not change another's)
and seeded by the run seed.

Sampling rates are configuration only: the runner and the plant node schedule the
calls.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
.. [2] NIMA TR8350.2, "Department of Defense World Geodetic System 1984", 3rd ed.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from typing import Sequence

import numpy as np

from .config import ConfigError, param
from .model import OMEGA, PHI, THETA, THETA_DOT, V, X, XV, Y
from .params import WipParameters

#: WGS84 semi-major axis [m] and flattening [2]_.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)      # first eccentricity squared

_TWO_PI = 2.0 * math.pi
# Independent random streams, one per sensor (spawn keys of the run seed).
# (Spawn keys are sequential: adding a stream leaves the first three unchanged.)
_STREAM_ENCODERS, _STREAM_IMU, _STREAM_GPS, _STREAM_DROPOUT = 0, 1, 2, 3


@dataclasses.dataclass(frozen=True)
class SensorConfig:
    """Rates, resolution and noise of the simulated sensors; GPS datum of the fixes."""

    encoder_rate: float = param(200.0, 'Hz', 'wheel encoder sampling rate', minimum=0.0,
                                exclusive_minimum=True)
    imu_rate: float = param(200.0, 'Hz', 'IMU sampling rate', minimum=0.0,
                            exclusive_minimum=True)
    gps_rate: float = param(10.0, 'Hz', 'GPS fix rate', minimum=0.0, exclusive_minimum=True)
    encoder_counts_per_rev: int = param(
        0, 'counts/rev', 'encoder resolution; 0 = ideal (no quantisation). A typical '
        'motor encoder behind its gearbox gives a few thousand counts per wheel turn',
        minimum=0)
    encoders_relative_to_body: bool = param(
        True, '1', 'encoders measure the wheel relative to the tilting body (joint angle '
        '= rolling angle - pitch), as on a real base; false: rolling angles')
    imu_pitch_noise_std: float = param(0.0, 'rad', 'IMU pitch noise (std)', minimum=0.0)
    imu_yaw_noise_std: float = param(0.0, 'rad', 'IMU yaw noise (std)', minimum=0.0)
    gyro_noise_std: float = param(0.0, 'rad/s', 'IMU pitch and yaw rate noise (std)',
                                  minimum=0.0)
    gps_noise_std: float = param(0.0, 'm', 'GPS position noise (std, per axis)',
                                 minimum=0.0)
    gyro_pitch_bias: float = param(0.0, 'rad/s', 'constant bias of the pitch-rate gyro',
                                   minimum=-0.5, maximum=0.5)
    gyro_yaw_bias: float = param(0.0, 'rad/s', 'constant bias of the yaw-rate gyro',
                                 minimum=-0.5, maximum=0.5)
    gps_dropout_probability: float = param(
        0.0, '1', 'probability that a GPS fix is missing (independent per fix; the '
        'simulator then publishes a NavSatFix with status NO_FIX)', minimum=0.0,
        maximum=1.0)
    gps_latency: float = param(
        0.0, 's', 'age of the position a GPS fix reports (rounded to IMU periods); the '
        'fix is stamped when it arrives, as a receiver without time tagging',
        minimum=0.0, maximum=2.0)
    sensor_delay: float = param(
        0.0, 's', 'transport delay of the encoders and the IMU (rounded to IMU periods)',
        minimum=0.0, maximum=0.1)
    gps_datum_latitude: float = param(
        38.8816, 'deg', 'latitude of the map origin for NavSatFix messages (default: '
        "Dalian, the paper authors' university; any datum works)", minimum=-89.0,
        maximum=89.0)
    gps_datum_longitude: float = param(121.5290, 'deg', 'longitude of the map origin',
                                       minimum=-180.0, maximum=180.0)
    gps_datum_altitude: float = param(0.0, 'm', 'ellipsoidal height of the map origin',
                                      minimum=-1000.0, maximum=10000.0)

    def validate(self) -> None:
        if self.encoder_counts_per_rev < 0:
            raise ConfigError('encoder_counts_per_rev: must be >= 0')


class Sensors:
    """Samples the sensors from the true plant state (layout of :mod:`.model`).

    Parameters
    ----------
    params : true physical parameters (wheel radius r, track width d).
    config : rates, resolution and noise.
    initial_yaw : ϕ0 [rad], the yaw at which the encoders' difference is zero.
    seed : run seed of the noise (non-negative integer).
    """

    def __init__(self, params: WipParameters, config: SensorConfig | None = None,
                 initial_yaw: float = 0.0, seed: int = 0) -> None:
        if not math.isfinite(initial_yaw):
            raise ValueError(f'initial_yaw must be finite, got {initial_yaw!r}')
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
        self.params = params
        self.config = SensorConfig() if config is None else config
        self.config.validate()
        self.initial_yaw = float(initial_yaw)
        self.seed = int(seed)
        children = np.random.SeedSequence(self.seed).spawn(4)
        self._rng_encoders = np.random.default_rng(children[_STREAM_ENCODERS])
        self._rng_imu = np.random.default_rng(children[_STREAM_IMU])
        self._rng_gps = np.random.default_rng(children[_STREAM_GPS])
        self._rng_dropout = np.random.default_rng(children[_STREAM_DROPOUT])
        counts = self.config.encoder_counts_per_rev
        self.encoder_resolution = _TWO_PI / counts if counts > 0 else 0.0   # [rad]
        c = self.config
        self.sensor_delay_samples = int(round(c.sensor_delay * c.imu_rate))
        self.gps_latency_samples = int(round(c.gps_latency * c.imu_rate))
        depth = max(self.sensor_delay_samples, self.gps_latency_samples) + 1
        self._history: collections.deque = collections.deque(maxlen=depth)

    def delayed(self, state: Sequence[float]) -> tuple[Sequence[float], Sequence[float]]:
        """(state seen by the encoders and IMU, state seen by the GPS) for this sample.

        Call once per IMU sample with the true state, in order: with ``sensor_delay``
        and ``gps_latency`` zero both are ``state``; otherwise the states of
        round(delay · imu_rate) samples earlier (the first state until there is one).
        """
        if len(self._history) == 0 and self._history.maxlen == 1:
            return state, state
        self._history.append(state)
        newest = len(self._history) - 1
        return (self._history[max(0, newest - self.sensor_delay_samples)],
                self._history[max(0, newest - self.gps_latency_samples)])

    def gps_fix_available(self) -> bool:
        """Whether this GPS tick delivers a fix (``gps_dropout_probability``).

        Call once per GPS tick, before :meth:`gps` (its own random stream).
        """
        p = self.config.gps_dropout_probability
        if p <= 0.0:
            return True
        return bool(self._rng_dropout.random() >= p)

    def wheel_rates(self, state: Sequence[float]) -> tuple[float, float]:
        """(φ̇l, φ̇r) [rad/s]: joint rates of the true motion, noise-free.

        (φ̇l, φ̇r) [rad/s]: joint rates of the true motion, noise-free (the rate of
        :meth:`encoders`): rolling rate (υ ∓ (d/2) ω) / r, minus the tilt rate when the
        encoders measure against the body.
        """
        p = self.params
        v, omega, half_track = float(state[V]), float(state[OMEGA]), 0.5 * p.track_width
        body = float(state[THETA_DOT]) if self.config.encoders_relative_to_body else 0.0
        return ((v - half_track * omega) / p.wheel_radius - body,
                (v + half_track * omega) / p.wheel_radius - body)

    def encoders(self, state: Sequence[float]) -> tuple[float, float]:
        """(φl, φr) [rad]: wheel joint angles (or rolling angles, see the config)."""
        p = self.params
        half_turn = 0.5 * p.track_width * (float(state[PHI]) - self.initial_yaw)
        x_v = float(state[XV])
        left = (x_v - half_turn) / p.wheel_radius
        right = (x_v + half_turn) / p.wheel_radius
        if self.config.encoders_relative_to_body:
            theta = float(state[THETA])
            left -= theta
            right -= theta
        q = self.encoder_resolution
        if q > 0.0:
            left = q * round(left / q)
            right = q * round(right / q)
        if not math.isfinite(left + right):   # (a NaN or inf term propagates into the sum)
            _check_finite('encoder angles', left, right)
        return left, right

    def imu(self, state: Sequence[float]) -> tuple[float, float]:
        """(pitch θ, yaw ϕ wrapped to (−π, π]) [rad], with the configured noise."""
        pitch, yaw = float(state[THETA]), float(state[PHI])
        c = self.config
        if c.imu_pitch_noise_std > 0.0:
            pitch += c.imu_pitch_noise_std * self._rng_imu.standard_normal()
        if c.imu_yaw_noise_std > 0.0:
            yaw += c.imu_yaw_noise_std * self._rng_imu.standard_normal()
        if not math.isfinite(pitch + yaw):
            _check_finite('IMU angles', pitch, yaw)
        return pitch, _wrap_to_pi(yaw)

    def imu_rates(self, state: Sequence[float]) -> tuple[float, float]:
        """(θ̇, ω) [rad/s], the rates of pitch and yaw, with the gyro bias and noise.

        Drawn from the IMU's stream: the runner and the plant node call it right after
        :meth:`imu` at every sample, so the angle noise sequence is the same in both.
        """
        pitch_rate = float(state[THETA_DOT]) + self.config.gyro_pitch_bias
        yaw_rate = float(state[OMEGA]) + self.config.gyro_yaw_bias
        std = self.config.gyro_noise_std
        if std > 0.0:
            pitch_rate += std * self._rng_imu.standard_normal()
            yaw_rate += std * self._rng_imu.standard_normal()
        if not math.isfinite(pitch_rate + yaw_rate):
            _check_finite('IMU rates', pitch_rate, yaw_rate)
        return pitch_rate, yaw_rate

    def gps(self, state: Sequence[float]) -> tuple[float, float]:
        """(x, y) [m] in the map frame, with the configured noise per axis."""
        x, y = float(state[X]), float(state[Y])
        std = self.config.gps_noise_std
        if std > 0.0:
            x += std * self._rng_gps.standard_normal()
            y += std * self._rng_gps.standard_normal()
        if not math.isfinite(x + y):
            _check_finite('GPS position', x, y)
        return x, y

    def gps_fix(self, state: Sequence[float]) -> tuple[float, float, float]:
        """(latitude [deg], longitude [deg], altitude [m]) of :meth:`gps` about the datum."""
        x, y = self.gps(state)
        c = self.config
        return local_to_geodetic(x, y, c.gps_datum_latitude, c.gps_datum_longitude,
                                 c.gps_datum_altitude)


def wheel_odometry(phi_left: float, phi_right: float, pitch: float, params: WipParameters,
                   initial_yaw: float = 0.0,
                   relative_to_body: bool = True) -> tuple[float, float]:
    """(x_v [m], ϕ [rad]) from the wheel angles, the inverse of :meth:`Sensors.encoders`.

    x_v = r ((φl + φr)/2 + θ) if the encoders measure relative to the body (θ =
    ``pitch`` [rad]), else r (φl + φr)/2; ϕ = ϕ0 + r (φr − φl)/d, continuous (not
    wrapped), since the encoder angles are.
    """
    if not math.isfinite(phi_left + phi_right + pitch + initial_yaw):
        _check_finite('wheel_odometry inputs', phi_left, phi_right, pitch, initial_yaw)
    r = params.wheel_radius
    mean = 0.5 * (phi_left + phi_right)
    if relative_to_body:
        mean += pitch
    return r * mean, initial_yaw + r * (phi_right - phi_left) / params.track_width


# ----------------------------------------------------------------------------- geodesy

def local_to_geodetic(x: float, y: float, datum_latitude: float, datum_longitude: float,
                      datum_altitude: float, z: float = 0.0) -> tuple[float, float, float]:
    """Map-frame point (x east, y north, z up) [m] to (latitude, longitude [deg], altitude [m]).

    The map frame is the local tangent plane (ENU) of the WGS84 ellipsoid [2]_ at the
    datum, converted exactly through Earth-centred coordinates (the same convention as
    GeographicLib's LocalCartesian). Horizontal coordinates of ground points differ
    from distances along the ellipsoid by about D³/(6 R²) (0.1 mm at D = 3 km), and a
    point of the plane (z = 0) at distance D lies D²/(2 R) above the datum's height
    (0.8 mm at 100 m, 0.7 m at 3 km): the altitude of a fix reflects the curvature.
    :func:`geodetic_to_local` is the inverse to better than 1e-6 m.
    """
    _check_finite('local_to_geodetic inputs', x, y, z, datum_latitude, datum_longitude,
                  datum_altitude)
    _check_latitude(datum_latitude)
    x0, y0, z0 = _geodetic_to_ecef(datum_latitude, datum_longitude, datum_altitude)
    sl, cl, so, co = _datum_trig(datum_latitude, datum_longitude)
    dx = -so * x - sl * co * y + cl * co * z
    dy = co * x - sl * so * y + cl * so * z
    dz = cl * y + sl * z
    return _ecef_to_geodetic(x0 + dx, y0 + dy, z0 + dz)


def geodetic_to_local(latitude: float, longitude: float, altitude: float,
                      datum_latitude: float, datum_longitude: float,
                      datum_altitude: float) -> tuple[float, float, float]:
    """(latitude, longitude [deg], altitude [m]) to the map frame (x east, y north, z up) [m].

    Inverse of :func:`local_to_geodetic`; ignore z for a planar position.
    """
    _check_finite('geodetic_to_local inputs', latitude, longitude, altitude,
                  datum_latitude, datum_longitude, datum_altitude)
    _check_latitude(latitude)
    _check_latitude(datum_latitude)
    px, py, pz = _geodetic_to_ecef(latitude, longitude, altitude)
    x0, y0, z0 = _geodetic_to_ecef(datum_latitude, datum_longitude, datum_altitude)
    dx, dy, dz = px - x0, py - y0, pz - z0
    sl, cl, so, co = _datum_trig(datum_latitude, datum_longitude)
    east = -so * dx + co * dy
    north = -sl * co * dx - sl * so * dy + cl * dz
    up = cl * co * dx + cl * so * dy + sl * dz
    return east, north, up


def _datum_trig(latitude: float, longitude: float) -> tuple[float, float, float, float]:
    lat, lon = math.radians(latitude), math.radians(longitude)
    return math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)


def _geodetic_to_ecef(latitude: float, longitude: float,
                      altitude: float) -> tuple[float, float, float]:
    lat, lon = math.radians(latitude), math.radians(longitude)
    s = math.sin(lat)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)     # prime vertical radius
    r = (n + altitude) * math.cos(lat)
    return r * math.cos(lon), r * math.sin(lon), (n * (1.0 - WGS84_E2) + altitude) * s


def _ecef_to_geodetic(px: float, py: float, pz: float) -> tuple[float, float, float]:
    """Fixed-point iteration on the latitude; converges to 1e-15 rad in a few steps."""
    p = math.hypot(px, py)
    lon = math.atan2(py, px)
    lat = math.atan2(pz, p * (1.0 - WGS84_E2))
    for _ in range(10):
        s = math.sin(lat)
        n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * s * s)
        # Height formula valid at any latitude (no division by cos(lat)).
        h = p * math.cos(lat) + pz * s - WGS84_A * math.sqrt(1.0 - WGS84_E2 * s * s)
        new_lat = math.atan2(pz, p * (1.0 - WGS84_E2 * n / (n + h)))
        if abs(new_lat - lat) < 1e-15:
            lat = new_lat
            break
        lat = new_lat
    s = math.sin(lat)
    h = p * math.cos(lat) + pz * s - WGS84_A * math.sqrt(1.0 - WGS84_E2 * s * s)
    return math.degrees(lat), math.degrees(lon), h


def _wrap_to_pi(angle: float) -> float:
    """Angle [rad] in (−π, π]; ``math.remainder`` is exact, so |ϕ| < π is unchanged."""
    wrapped = math.remainder(angle, _TWO_PI)
    return wrapped + _TWO_PI if wrapped <= -math.pi else wrapped


def _check_latitude(latitude: float) -> None:
    if not -90.0 <= latitude <= 90.0:
        raise ValueError(f'latitude must be in [-90, 90] deg, got {latitude!r}')


def _check_finite(what: str, *values: float) -> None:
    """ValueError naming ``what`` if a value is NaN or infinite.

    The per-sample callers call it only when the values' sum is not finite: a NaN or inf among them
    makes the sum so, and a finite sum proves them all finite (a sum that overflows is checked
    here, value by value).
    """
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f'{what} must be finite, got {values!r}')
