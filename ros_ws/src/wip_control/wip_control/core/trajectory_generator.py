r"""Saturated trajectory generator, eq. (9) in [1]_, with body-frame errors.

.. math::

    x_e = \cos\phi (x_r - x) + \sin\phi (y_r - y), \quad
    y_e = -\sin\phi (x_r - x) + \cos\phi (y_r - y), \quad
    \phi_e = \mathrm{wrap}(\phi_r - \phi)

    \omega_d = \omega_r + \frac{\lambda_1 \upsilon_r y_e \,\mathrm{sinc}\,\phi_e}
        {1 + x_e^2 + y_e^2} + \lambda_2 \tanh \phi_e, \quad
    \upsilon_d = \upsilon_r \cos \phi_e + \lambda_3 \tanh x_e

then |ω_d| ≤ ω_max, |υ_d| ≤ υ_max by explicit saturation.

Deviations from the paper, as adopted in docs/paper.md §3:

- the errors are in the **body frame** (the paper's text says earth frame, but its
  Lyapunov function V2 = λ1 ln(1 + x_e² + y_e²)/2 + ϕ_e²/2 only decreases with
  body-frame errors: along ẋ = υ_d cos ϕ, ẏ = υ_d sin ϕ, ϕ̇ = ω_d,
  V̇2 = −λ1 λ3 x_e tanh x_e/(1 + x_e² + y_e²) − λ2 ϕ_e tanh ϕ_e ≤ 0);
- (9) bounds |ω_d| only by |ω_r| + λ1|υ_r|/2 + λ2, so the commands are saturated
  explicitly;
- ω̇_d, which the ARC (12) needs, is not given by the paper. It is the **filtered
  derivative of the saturated ω_d**, D(s) = s/(τ s + 1) discretised by backward Euler:
  ω̇_d,k = (τ ω̇_d,k−1 + ω_d,k − ω_d,k−1)/(τ + Δt), then clipped to
  ±``max_yaw_acceleration``; while ω_d stays saturated at the same limit (this sample
  and the previous one) ω̇_d is exactly 0 and the filter is reset, as
  d/dt sat(u) = 0 there. Why not analytic: the exact derivative of (9) needs the
  vehicle's actual (υ, ω), υ̇_r (not in the reference state) and the derivative of the
  saturation, and it would differentiate the position estimate, which jumps at each
  GPS fix. The filtered derivative is model-free, consistent with the saturation (zero
  when ω_d is held at ±ω_max), bounded by 2 ω_max/(τ + Δt) by construction (Abel
  summation of bounded increments), and lags by τ (default 0.05 s, against the 0.02 s time
  constant 1/(g1 kω) of the yaw loop, where it is only a feed-forward). The clip keeps a GPS
  jump from kicking the feed-forward harder than the ARC could follow anyway (0.8 N·m · g1 ≈
  2 rad/s²).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

from wip_runtime.config import param
from .reference_state import ReferenceState

_TWO_PI = 2.0 * math.pi
HEADING_DESIGNS = ('paper', 'poles')


@dataclasses.dataclass(frozen=True)
class TrajectoryGeneratorParams:
    """Gains and limits of the saturated trajectory generator, eq. (9) in [1]_."""

    lambda1: float = param(1.0, '1', 'lambda1 of eq. (9): weight of the lateral error y_e',
                           minimum=0.0, exclusive_minimum=True)
    lambda2: float = param(0.1, 'rad/s', 'lambda2 of eq. (9): weight of tanh(phi_e)',
                           minimum=0.0, exclusive_minimum=True)
    lambda3: float = param(0.85, 'm/s', 'lambda3 of eq. (9): weight of tanh(x_e); near the '
                           'path x_e decays at lambda3 [1/s per m] (Section V: 1; '
                           'docs/decisions/reference-parameters.md)',
                           minimum=0.0, exclusive_minimum=True)
    max_yaw_rate: float = param(0.3, 'rad/s', 'omega_max: |omega_d| saturation (Section V)',
                                minimum=0.0, exclusive_minimum=True)
    max_speed: float = param(1.5, 'm/s', 'upsilon_max: |upsilon_d| saturation (Section V)',
                             minimum=0.0, exclusive_minimum=True)
    yaw_rate_derivative_time_constant: float = param(
        0.05, 's', 'tau of the filtered derivative s/(tau s + 1) giving omega_d_dot',
        minimum=0.0, exclusive_minimum=True)
    max_yaw_acceleration: float = param(
        2.0, 'rad/s^2', '|omega_d_dot| clip (about the yaw authority tau_omega_max * g1)',
        minimum=0.0, exclusive_minimum=True)
    heading_design: str = param(
        'poles', '1', "gains of eq. (9): 'paper' lambda1, lambda2 as given; 'poles' "
        'lambda1 = w_n^2/v_r^2, lambda2 = 2 zeta w_n (docs/decisions/reference-parameters.md)',
        choices=HEADING_DESIGNS)
    heading_bandwidth: float = param(
        1.2, 'rad/s', "'poles': natural frequency w_n of the lateral/heading loop",
        minimum=0.01, maximum=10.0)
    heading_damping: float = param(
        1.0, '1', "'poles': damping ratio zeta of the lateral/heading loop", minimum=0.1,
        maximum=3.0)
    min_design_speed: float = param(
        0.1, 'm/s', "'poles': reference speed below which lambda1 stops growing (lambda1 "
        'v_r stays bounded when the reference stops)', minimum=0.01, maximum=10.0)
    obstacle_back_off: float = param(
        0.2, 'm', 'when an obstacle blocks the wheels, back off this far and hold there '
        'until the reference no longer leads past it or the vehicle goes on over it '
        '(core/obstacle_refusal.py); 0 = off',
        minimum=0.0, maximum=2.0)
    obstacle_refuse_delay: float = param(
        0.3, 's', 'obstacle_back_off: how long the wheels stay blocked (after the eso stall '
        'time) before the refusal; a stall that climbs sooner is a crossing', minimum=0.0,
        maximum=10.0)


class VelocityCommand(NamedTuple):
    """Output of the generator at one sample."""

    v_d: float          #: υ_d, desired speed, saturated [m/s]
    omega_d: float      #: ω_d, desired yaw rate, saturated [rad/s]
    omega_d_dot: float  #: ω̇_d, filtered derivative of ω_d [rad/s²]
    x_e: float          #: body-frame longitudinal error [m]
    y_e: float          #: body-frame lateral error [m]
    phi_e: float        #: heading error wrap(ϕ_r − ϕ) [rad]


def tracking_errors(ref: ReferenceState, x: float, y: float,
                    phi: float) -> tuple[float, float, float]:
    """Body-frame errors (x_e [m], y_e [m], ϕ_e [rad]) of eq. (9), ϕ_e in (−π, π]."""
    dx, dy = ref.x - x, ref.y - y
    c, s = math.cos(phi), math.sin(phi)
    phi_e = math.remainder(ref.phi - phi, _TWO_PI)
    return c * dx + s * dy, -s * dx + c * dy, phi_e


def heading_gains(config: TrajectoryGeneratorParams, v_r: float) -> tuple[float, float]:
    """(λ1 [1], λ2 [rad/s]) of eq. (9) at the reference speed ``v_r`` [m/s].

    'poles': near the path (x_e, y_e, ϕ_e small, υ ≈ υ_r) the body-frame errors obey
    ẏ_e ≈ υ_r ϕ_e and ϕ̇_e = ω_r − ω_d ≈ −λ1 υ_r y_e − λ2 ϕ_e, so
    ÿ_e + λ2 ẏ_e + λ1 υ_r² y_e = 0: λ1 = ω_n²/υ_r², λ2 = 2 ζ ω_n give the poles
    ω_n (−ζ ± j√(1 − ζ²)) at every speed. (The paper's λ1 = 1, λ2 = 0.1 give ζ ≈ 0.1 on
    the trifolium: ζ = λ2/(2 υ_r √λ1).) Both stay positive, so the Lyapunov argument of
    the module docstring holds at each instant.
    """
    if config.heading_design == 'paper':
        return config.lambda1, config.lambda2
    speed = max(abs(v_r), config.min_design_speed)
    w_n = config.heading_bandwidth
    return w_n * w_n / (speed * speed), 2.0 * config.heading_damping * w_n


def unsaturated_commands(config: TrajectoryGeneratorParams, ref: ReferenceState,
                         x_e: float, y_e: float, phi_e: float) -> tuple[float, float]:
    """(υ_d [m/s], ω_d [rad/s]) of eq. (9) before saturation."""
    sinc = math.sin(phi_e) / phi_e if abs(phi_e) > 1e-6 else 1.0 - phi_e * phi_e / 6.0
    lambda1, lambda2 = heading_gains(config, ref.v)
    omega_d = (ref.omega
               + lambda1 * ref.v * y_e * sinc / (1.0 + x_e * x_e + y_e * y_e)
               + lambda2 * math.tanh(phi_e))                             # Eq. (9) in [1]
    v_d = ref.v * math.cos(phi_e) + config.lambda3 * math.tanh(x_e)      # Eq. (9) in [1]
    return v_d, omega_d


class TrajectoryGenerator:
    """Desired velocities (υ_d, ω_d, ω̇_d) from the reference and the estimated pose.

    Parameters
    ----------
    config : gains λ1..λ3, limits ω_max, υ_max, derivative filter.
    """

    def __init__(self, config: TrajectoryGeneratorParams | None = None) -> None:
        self.config = config if config is not None else TrajectoryGeneratorParams()
        self.reset()

    def reset(self) -> None:
        """Forget the derivative filter's history (ω̇_d = 0 at the next step)."""
        self._t_prev: float | None = None
        self._omega_prev = 0.0
        self._omega_dot = 0.0
        self._sat_sign_prev = 0.0
        self.saturated_speed = False     #: whether |υ_d| was clipped at the last step
        self.saturated_yaw_rate = False  #: whether |ω_d| was clipped at the last step

    def state(self) -> tuple:
        """Everything :meth:`step` changes, for :meth:`restore`.

        That is the derivative filter and the saturation flags.
        """
        return (self._t_prev, self._omega_prev, self._omega_dot, self._sat_sign_prev,
                self.saturated_speed, self.saturated_yaw_rate)

    def restore(self, state: tuple) -> None:
        """Go back to a :meth:`state` (the guidance stage does after an overflow)."""
        (self._t_prev, self._omega_prev, self._omega_dot, self._sat_sign_prev,
         self.saturated_speed, self.saturated_yaw_rate) = state

    def step(self, t: float, ref: ReferenceState, x: float, y: float,
             phi: float) -> VelocityCommand:
        """Commands at time ``t`` [s] for the pose (x [m], y [m], ϕ [rad]) and ``ref``.

        Raises
        ------
        ValueError
            on non-finite inputs or time going backwards.
        """
        if not math.isfinite(t + x + y + phi + ref.x + ref.y + ref.phi + ref.v + ref.omega):
            raise ValueError(f'TrajectoryGenerator.step: non-finite input t={t!r}, '
                             f'pose=({x!r}, {y!r}, {phi!r}), ref={ref!r}')
        cfg = self.config
        x_e, y_e, phi_e = tracking_errors(ref, x, y, phi)
        v_d, omega_d = unsaturated_commands(cfg, ref, x_e, y_e, phi_e)
        # Explicit saturation (spec section 3): (9) alone exceeds omega_max.
        self.saturated_speed = abs(v_d) > cfg.max_speed
        if self.saturated_speed:
            v_d = math.copysign(cfg.max_speed, v_d)
        self.saturated_yaw_rate = abs(omega_d) > cfg.max_yaw_rate
        if self.saturated_yaw_rate:
            omega_d = math.copysign(cfg.max_yaw_rate, omega_d)
        # ω̇_d: backward-Euler filtered derivative of the saturated ω_d (module docstring).
        sat_sign = math.copysign(1.0, omega_d) if self.saturated_yaw_rate else 0.0
        if self._t_prev is None or (sat_sign != 0.0 and sat_sign == self._sat_sign_prev):
            # d/dt sat(u) = 0 while the saturation holds: exactly zero, filter reset.
            omega_dot = 0.0
        else:
            dt = t - self._t_prev
            if dt < 0.0:
                raise ValueError(f'TrajectoryGenerator.step: time went backwards from '
                                 f'{self._t_prev} to {t}')
            tau = cfg.yaw_rate_derivative_time_constant
            omega_dot = (tau * self._omega_dot + omega_d - self._omega_prev) / (tau + dt)
            limit = cfg.max_yaw_acceleration
            omega_dot = max(-limit, min(limit, omega_dot))
        self._t_prev, self._omega_prev, self._omega_dot = t, omega_d, omega_dot
        self._sat_sign_prev = sat_sign
        return VelocityCommand(v_d, omega_d, omega_dot, x_e, y_e, phi_e)
