"""Forward sensor models of the simulated WIP: what the encoders, the IMU and the GPS report.

The quantities and their conventions are those of :mod:`wip_description.sensors`, whose
inverse maps the estimators use. Noise (zero-mean Gaussian, independent per sample and per
axis) is off by default, so the paper scenario is clean; scenarios enable it. The random
streams of encoders, IMU, GPS and GPS dropouts are separate (a change in one sensor's noise
does not change another's) and seeded by the run seed. The encoders can be quantised to
``encoder_counts_per_rev`` (rounded to the nearest count: at most half a count of error).
Sampling rates are configuration only: the simulation schedules the calls.
"""

from __future__ import annotations

import collections
import math
from typing import Sequence

import numpy as np

from wip_control.core.model import OMEGA, PHI, THETA, THETA_DOT, V, X, XV, Y
from wip_description.params import ModelParams
from wip_description.sensors import check_finite, local_to_geodetic, SensorParams

_TWO_PI = 2.0 * math.pi
# Independent random streams, one per sensor (spawn keys of the run seed).
# (Spawn keys are sequential: adding a stream leaves the first three unchanged.)
_STREAM_ENCODERS, _STREAM_IMU, _STREAM_GPS, _STREAM_DROPOUT = 0, 1, 2, 3


class Sensors:
    """Samples the sensors from the true plant state (layout of :mod:`.model`).

    Parameters
    ----------
    params : true physical parameters (wheel radius r, track width d).
    config : rates, resolution and noise.
    initial_yaw : ϕ0 [rad], the yaw at which the encoders' difference is zero.
    seed : run seed of the noise (non-negative integer).
    """

    def __init__(self, params: ModelParams, config: SensorParams | None = None,
                 initial_yaw: float = 0.0, seed: int = 0) -> None:
        if not math.isfinite(initial_yaw):
            raise ValueError(f'initial_yaw must be finite, got {initial_yaw!r}')
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
        self.params = params
        self.config = SensorParams() if config is None else config
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

    def wheel_rates(self, state: Sequence[float],
                    joint_rates: tuple[float, float] | None = None) -> tuple[float, float]:
        """(φ̇l, φ̇r) [rad/s]: joint rates of the true motion, noise-free.

        They are the rates of :meth:`encoders`: the rolling rate (υ ∓ (d/2) ω) / r, minus
        the tilt rate when the encoders measure against the body. ``joint_rates``: the
        joint rates against the body a plant with wheel contacts reports (slip included),
        used instead of the rolling rates.
        """
        p = self.params
        if joint_rates is not None:
            body = 0.0 if self.config.encoders_relative_to_body else float(state[THETA_DOT])
            return joint_rates[0] + body, joint_rates[1] + body
        v, omega, half_track = float(state[V]), float(state[OMEGA]), 0.5 * p.track_width
        body = float(state[THETA_DOT]) if self.config.encoders_relative_to_body else 0.0
        return ((v - half_track * omega) / p.wheel_radius - body,
                (v + half_track * omega) / p.wheel_radius - body)

    def encoders(self, state: Sequence[float],
                 wheel_yaw: float | None = None) -> tuple[float, float]:
        """(φl, φr) [rad]: wheel joint angles (or rolling angles, see the config).

        Their difference is d (ϕ − ϕ0) / r, rolling without slip; ``wheel_yaw``: the
        heading a plant with wheel contacts reads from its joints instead of ϕ (the
        two differ by the wheels' differential slip).
        """
        p = self.params
        yaw = float(state[PHI]) if wheel_yaw is None else wheel_yaw
        half_turn = 0.5 * p.track_width * (yaw - self.initial_yaw)
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
            check_finite('encoder angles', left, right)
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
            check_finite('IMU angles', pitch, yaw)
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
            check_finite('IMU rates', pitch_rate, yaw_rate)
        return pitch_rate, yaw_rate

    def gps(self, state: Sequence[float]) -> tuple[float, float]:
        """(x, y) [m] in the map frame, with the configured noise per axis."""
        x, y = float(state[X]), float(state[Y])
        std = self.config.gps_noise_std
        if std > 0.0:
            x += std * self._rng_gps.standard_normal()
            y += std * self._rng_gps.standard_normal()
        if not math.isfinite(x + y):
            check_finite('GPS position', x, y)
        return x, y

    def gps_fix(self, state: Sequence[float]) -> tuple[float, float, float]:
        """(latitude [deg], longitude [deg], altitude [m]) of :meth:`gps` about the datum."""
        x, y = self.gps(state)
        c = self.config
        return local_to_geodetic(x, y, c.gps_datum_latitude, c.gps_datum_longitude,
                                 c.gps_datum_altitude)


def _wrap_to_pi(angle: float) -> float:
    """Angle [rad] in (−π, π]; ``math.remainder`` is exact, so |ϕ| < π is unchanged."""
    wrapped = math.remainder(angle, _TWO_PI)
    return wrapped + _TWO_PI if wrapped <= -math.pi else wrapped
