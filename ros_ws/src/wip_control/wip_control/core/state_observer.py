"""The state observer of a WIP: three channel observers, yaw, distance and tilt.

The paper's three ESOs, eqs. (4) and (8) of [1]_ (``eso.py``), or, with the IMU's rates
measured, two rate-aided channels and the distance ESO (``rate_aided.py``).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import math
from typing import Sequence

from .eso import EsoParams, ExtendedStateObserver, StateEstimate
from .model import input_gains
from wip_description.params import ModelParams
from .rate_aided import RateAidedChannel

_TWO_PI = 2.0 * math.pi


class WipStateObserver:
    """The three ESOs of [1]_ for a WIP: yaw, eq. (4); distance and tilt, eq. (8).

    The input gains are those of eq. (1) at the current tilt estimate θ̂ (taken at the
    start of each period and held with the torques); the yaw channel uses
    ĝ1 = ``yaw_input_gain_scale`` · g1(θ̂), the paper's 20 % error.

    Parameters
    ----------
    params : nominal WIP parameters (the controllers' model).
    config : observer tunables.
    initial_positions : (ϕ [rad], x_v [m], θ [rad]) at ``initial_time``; the ESOs start
        there with zero rates and disturbances (Section V).
    initial_time : time [s] of the initial state, and origin of the ε ramp.
    """

    def __init__(self, params: ModelParams, config: EsoParams | None = None,
                 initial_positions: Sequence[float] = (0.0, 0.0, 0.0),
                 initial_time: float = 0.0, *,
                 encoders_relative_to_body: bool = False) -> None:
        self.params = params
        # 'gyro': x_v = r((φl + φr)/2 + θ) is recomputed with the filtered θ̂ instead of
        # the raw IMU pitch, whose noise r·σθ the x_v ESO would otherwise differentiate.
        self._xv_pitch_correction = (params.wheel_radius if encoders_relative_to_body
                                     else 0.0)
        self.config = config = config if config is not None else EsoParams()
        config.validate()
        common = dict(epsilon=config.epsilon, sample_period=config.sample_period,
                      schedule=config.epsilon_schedule, ramp_duration=config.ramp_duration,
                      measurement_hold=config.measurement_hold)
        self.gyro = config.estimator == 'gyro'
        if self.gyro:
            # The rates are measured: angle/rate channels, and a bandwidth-parameterised
            # x_v ESO (all three poles at −ω_l: gains (3, 3, 1), ε = 1/ω_l).
            h = config.sample_period
            self.yaw = RateAidedChannel(config.yaw_angle_bandwidth,
                                        config.gyro_bias_bandwidth,
                                        config.yaw_rate_bandwidth, h, name='yaw')
            self.tilt = RateAidedChannel(config.tilt_angle_bandwidth,
                                         config.gyro_bias_bandwidth,
                                         config.tilt_rate_bandwidth, h, name='tilt')
            self.longitudinal = ExtendedStateObserver(
                (3.0, 3.0, 1.0), 1.0 / config.longitudinal_bandwidth, h,
                measurement_hold=config.measurement_hold, name='longitudinal',
                rate_start=config.speed_start)
        else:
            self.yaw = ExtendedStateObserver(config.yaw_gains, name='yaw_gains', **common)
            self.longitudinal = ExtendedStateObserver(config.longitudinal_gains,
                                                      name='longitudinal_gains',
                                                      rate_start=config.speed_start, **common)
            self.tilt = ExtendedStateObserver(config.tilt_gains, name='tilt_gains',
                                              **common)
        self._yaw_scale = config.yaw_input_gain_scale
        self.reset(initial_positions, initial_time)

    def reset(self, initial_positions: Sequence[float], initial_time: float = 0.0) -> None:
        """Restart from positions (ϕ, x_v, θ) with zero rates and disturbances."""
        if len(initial_positions) != 3:
            raise ValueError('initial_positions: expected (phi, x_v, theta), got '
                             f'{initial_positions!r}')
        phi, x_v, theta = (float(v) for v in initial_positions)
        for label, value in (('phi', phi), ('x_v', x_v), ('theta', theta),
                             ('initial_time', initial_time)):
            if not math.isfinite(value):
                raise ValueError(f'initial {label} must be finite, got {value!r}')
        self.yaw.reset(phi, initial_time)
        self.longitudinal.reset(x_v, initial_time)
        self.tilt.reset(theta, initial_time)
        self._phi_meas = phi
        self._estimate = self._make_estimate(initial_time)

    @property
    def estimate(self) -> StateEstimate:
        """The latest estimate."""
        return self._estimate

    def _make_estimate(self, t: float) -> StateEstimate:
        y, lon, tilt = self.yaw, self.longitudinal, self.tilt
        return StateEstimate(y.x1, y.x2, y.f, lon.x1, lon.x2, lon.f, tilt.x1, tilt.x2,
                             tilt.f, self.epsilon_at(t))

    def epsilon_at(self, t: float) -> float:
        """ε [s] in use at ``t`` (gyro estimator: 1/ω_l of the x_v ESO, constant)."""
        return self.longitudinal.epsilon_at(t) if self.gyro else self.yaw.epsilon_at(t)

    def in_ramp(self, t: float) -> bool:
        """Return True while the paper's ε ramp runs (never with the gyro estimator)."""
        return False if self.gyro else self.yaw.in_ramp(t)

    @property
    def needs_rates(self) -> bool:
        """Whether :meth:`update` needs the IMU angular rates."""
        return self.gyro

    def update(self, t: float, phi_meas: float, xv_meas: float, theta_meas: float,
               tau_v_applied: float, tau_omega_applied: float,
               rates: Sequence[float] | None = None) -> StateEstimate:
        """Advance the three ESOs to time ``t`` [s].

        Parameters
        ----------
        t : sample time [s], ≥ the previous one (equal: estimate unchanged).
        phi_meas : measured yaw ϕ [rad]; moved to the 2π branch nearest the previous
            sample, so a wrapped (−π, π] yaw is accepted.
        xv_meas : measured distance rolled x_v [m] (wheel odometry; with
            ``encoders_relative_to_body`` the 'gyro' estimator replaces the raw pitch in
            it by θ̂).
        theta_meas : measured tilt θ [rad] (IMU).
        tau_v_applied, tau_omega_applied : τυ = τl + τr and τω = τr − τl [N·m] applied
            (held) since the previous update.
        rates : (θ̇, ϕ̇) [rad/s] measured by the IMU's gyro (sensor_msgs/Imu
            angular_velocity, as Euler rates); required by the 'gyro' estimator,
            ignored by the 'paper' one.

        Raises
        ------
        ValueError
            on a non-finite input or a time going backwards; the state is unchanged.
        """
        # One sum detects any NaN/inf among the inputs (inf − inf = NaN).
        if not math.isfinite(t + phi_meas + xv_meas + theta_meas + tau_v_applied
                             + tau_omega_applied):
            names = ('t', 'phi_meas', 'xv_meas', 'theta_meas', 'tau_v_applied',
                     'tau_omega_applied')
            values = (t, phi_meas, xv_meas, theta_meas, tau_v_applied, tau_omega_applied)
            bad = [f'{n}={v!r}' for n, v in zip(names, values) if not math.isfinite(v)]
            raise ValueError(f'WipStateObserver.update: non-finite input {", ".join(bad)}')
        if t < self.yaw.time:
            raise ValueError(f'WipStateObserver.update: time went backwards from '
                             f'{self.yaw.time} to {t}')
        d = phi_meas - self._phi_meas
        if d > math.pi or d < -math.pi:
            phi_meas -= _TWO_PI * round(d / _TWO_PI)
        self._phi_meas = phi_meas
        # Eq. (1) input gains at θ̂ of the start of the period, held like the torques.
        g1, g2, g3 = input_gains(self.params, self.tilt.x1)
        if self.gyro:
            if rates is None or len(rates) != 2:
                raise ValueError("WipStateObserver.update: the 'gyro' estimator needs the "
                                 f'IMU rates (pitch_rate, yaw_rate), got {rates!r}')
            pitch_rate, yaw_rate = float(rates[0]), float(rates[1])
            if not math.isfinite(pitch_rate + yaw_rate):
                raise ValueError(f'WipStateObserver.update: non-finite rates {rates!r}')
            self.yaw.update(t, phi_meas, yaw_rate, self._yaw_scale * g1 * tau_omega_applied)
            theta_hat = self.tilt.update(t, theta_meas, pitch_rate, g3 * tau_v_applied)[0]
            xv_meas += self._xv_pitch_correction * (theta_hat - theta_meas)
            self.longitudinal.update(t, xv_meas, g2 * tau_v_applied)
        else:
            self.yaw.update(t, phi_meas, self._yaw_scale * g1 * tau_omega_applied)
            self.longitudinal.update(t, xv_meas, g2 * tau_v_applied)
            self.tilt.update(t, theta_meas, g3 * tau_v_applied)
        self._estimate = estimate = self._make_estimate(t)
        return estimate
