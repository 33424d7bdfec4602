"""The robot's sensors as the controllers read them, and the inverse sensor maps.

:class:`SensorParams` describes the sensors (rates, resolution, noise, the GPS datum, whether
the encoders measure the wheel relative to the tilting body): the simulator samples them with
it (``wip_sim.core.sensor_models``) and the estimators read them back with the same figures.

- **wheel encoders**: the two wheel joint angles φl, φr [rad]. The wheels roll without
  slip, so the rolling angles satisfy x_v = r (φl + φr)/2 and ϕ − ϕ0 = r (φr − φl)/d
  (spec, section 1; d is the distance between the wheels). A real encoder measures the
  wheel **relative to the chassis**, which tilts with θ: joint angle = rolling angle − θ.
  :func:`wheel_odometry` adds θ back: x_v = r ((φl + φr)/2 + θ); θ cancels in φr − φl.
- **GPS**: the planar position (x, y) [m] in the map frame (REP 103/105: x east, y north),
  carried as NavSatFix around a datum: :func:`local_to_geodetic` and its inverse
  :func:`geodetic_to_local` (WGS84 [2]_).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
.. [2] NIMA TR8350.2, "Department of Defense World Geodetic System 1984", 3rd ed.
"""

from __future__ import annotations

import dataclasses
import math

from wip_runtime.config import ParamError, param
from .params import ModelParams

#: WGS84 semi-major axis [m] and flattening [2]_.
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)      # first eccentricity squared


@dataclasses.dataclass(frozen=True)
class SensorParams:
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
            raise ParamError('encoder_counts_per_rev: must be >= 0')


def wheel_odometry(phi_left: float, phi_right: float, pitch: float, params: ModelParams,
                   initial_yaw: float = 0.0,
                   relative_to_body: bool = True) -> tuple[float, float]:
    """(x_v [m], ϕ [rad]) from the wheel angles, the inverse of :meth:`Sensors.encoders`.

    x_v = r ((φl + φr)/2 + θ) if the encoders measure relative to the body (θ =
    ``pitch`` [rad]), else r (φl + φr)/2; ϕ = ϕ0 + r (φr − φl)/d, continuous (not
    wrapped), since the encoder angles are.
    """
    if not math.isfinite(phi_left + phi_right + pitch + initial_yaw):
        check_finite('wheel_odometry inputs', phi_left, phi_right, pitch, initial_yaw)
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
    check_finite('local_to_geodetic inputs', x, y, z, datum_latitude, datum_longitude,
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
    check_finite('geodetic_to_local inputs', latitude, longitude, altitude,
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


def _check_latitude(latitude: float) -> None:
    if not -90.0 <= latitude <= 90.0:
        raise ValueError(f'latitude must be in [-90, 90] deg, got {latitude!r}')


def check_finite(what: str, *values: float) -> None:
    """ValueError naming ``what`` if a value is NaN or infinite.

    The per-sample callers call it only when the values' sum is not finite: a NaN or inf among them
    makes the sum so, and a finite sum proves them all finite (a sum that overflows is checked
    here, value by value).
    """
    for v in values:
        if not math.isfinite(v):
            raise ValueError(f'{what} must be finite, got {values!r}')
