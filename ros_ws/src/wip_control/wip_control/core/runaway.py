r"""Runaway guard: the vehicle's motion by its wheels and IMU against the reference's.

Not part of the paper [1]_. The trajectory generator (eq. (9)) drives the *estimated*
position onto the reference, so a wrong position (a datum copied from elsewhere, a jump
of the receiver that got through, an external odometry in another frame) makes the
controllers drive the real vehicle away, confidently, at the generator's speed limit. The
guard judges the motion without the position estimate:

- the **wheel-propagated tracking error** ε_w starts at the estimated tracking error
  e = p̂ − p_r when the safety layer engages, and then moves by what the wheels and the
  IMU say the vehicle did (υ̂ along ϕ̂, integrated) minus what the reference did:

  .. math:: ε_w(t_{k+1}) = ε_w(t_k) + \bar υ̂ \, Δt \, (\cos \bar ϕ̂, \sin \bar ϕ̂)
            − (p_r(t_{k+1}) − p_r(t_k)) + \frac{Δt}{T_a} (e − ε_w)

  The last term re-anchors ε_w to the estimate with the slow time constant T_a
  (``anchor_time``), so the odometry's drift over a long run does not accumulate, while a
  divergence faster than T_a shows in full. A vehicle that follows its reference keeps
  |ε_w| small or shrinking; one that is driven away grows it.
- **growth**: |ε_w| more than ``max_error_growth`` above its least value over the last
  ``growth_window`` seconds is a runaway if the vehicle's own motion (υ̂ along ϕ̂ since
  that least value, along ε_w) made at least ``min_own_share`` of the growth. A vehicle
  held still while its reference goes on (wheels stopped or spinning at an edge it cannot
  climb) falls behind, it does not run away: cutting its torque would tip it over;
- **absurd error**: |e| above ``max_tracking_error`` for ``tracking_error_time`` is one
  too (a datum off by hundreds of metres: the generator then "converges" on a reference
  that is somewhere else, and ε_w shrinks while the vehicle drives off).

The bounds and why no run of the robustness suite comes near them: docs/safety.md.

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import collections
import dataclasses
import math

from wip_runtime.config import param


@dataclasses.dataclass(frozen=True)
class RunawayParams:
    """Tunables of :class:`RunawayGuard` (ROS section ``runaway`` of the torque_mixer)."""

    enabled: bool = param(True, '1', 'judge the motion by the wheels and IMU against the '
                          "reference's while engaged (real time and hardware mode)")
    max_error_growth: float = param(
        2.0, 'm', 'runaway: the wheel-propagated tracking error grew by more than this '
        'within growth_window', minimum=0.0, exclusive_minimum=True)
    growth_window: float = param(
        4.0, 's', 'window over which the growth of the tracking error is measured',
        minimum=0.1, maximum=60.0)
    max_tracking_error: float = param(
        10.0, 'm', 'runaway: the estimated tracking error exceeded this for '
        'tracking_error_time', minimum=0.0, exclusive_minimum=True)
    tracking_error_time: float = param(
        1.0, 's', 'how long the tracking error may exceed max_tracking_error', minimum=0.0)
    anchor_time: float = param(
        30.0, 's', 'time constant with which the wheel-propagated error is pulled back to '
        'the estimated one (bounds the odometry drift)', minimum=0.1, maximum=1000.0)
    min_own_share: float = param(
        0.5, '1', "runaway: the least share of the growth that the vehicle's own motion "
        '(wheels, IMU) must make; a vehicle held at an obstacle while the reference goes on '
        'is not one', minimum=0.0, maximum=1.0)
    max_reference_step: float = param(
        0.5, 'm', 'a reference that moves farther than this in one step was replaced (a new '
        'path or a reset): the guard re-anchors instead of counting it', minimum=0.0,
        exclusive_minimum=True)


class RunawayGuard:
    """See the module docstring. Feed :meth:`update` at each estimate while engaged.

    :meth:`reset` when the safety layer stops sending torque; the next update anchors anew.
    """

    def __init__(self, config: RunawayParams | None = None) -> None:
        self.config = config if config is not None else RunawayParams()
        self.reset()

    def reset(self) -> None:
        self._last: tuple[float, float, float, float, float] | None = None  # t, xr, yr, ϕ, υ
        self.error_x = self.error_y = 0.0       # ε_w [m]
        # (t, |ε_w|, own_x, own_y): the sliding window's candidates for its least |ε_w|.
        self._history: collections.deque[tuple[float, float, float, float]] = (
            collections.deque())
        self.own_x = self.own_y = 0.0   # the vehicle's own path by wheels and IMU [m]
        self._absurd_since: float | None = None
        self.largest_growth = 0.0               # [m] since the last reset, for /diagnostics

    @property
    def wheel_error(self) -> float:
        """|ε_w| [m]."""
        return math.hypot(self.error_x, self.error_y)

    def update(self, t: float, x: float, y: float, phi: float, v: float, x_ref: float,
               y_ref: float) -> str:
        """Take the estimate (x̂, ŷ, ϕ̂, υ̂) and the reference (x_r, y_r) at ``t`` [s].

        Returns the verdict: '' or why the vehicle is running away.
        """
        cfg = self.config
        ex, ey = x - x_ref, y - y_ref
        values = (t, x, y, phi, v, x_ref, y_ref)
        if not all(map(math.isfinite, values)):
            return ''   # the safety layer's own checks refuse non-finite estimates
        last = self._last
        if last is not None and t <= last[0]:
            return ''   # not a new sample
        self._last = (t, x_ref, y_ref, phi, v)
        if last is None:
            self.error_x, self.error_y = ex, ey
            self._history.clear()
            self._history.append((t, math.hypot(ex, ey), self.own_x, self.own_y))
            return self._absurd(t, ex, ey)
        dt = t - last[0]
        dxr, dyr = x_ref - last[1], y_ref - last[2]
        if math.hypot(dxr, dyr) > cfg.max_reference_step:
            # The reference was replaced, not followed: start again from the estimate.
            self.error_x, self.error_y = ex, ey
            self._history.clear()
        else:
            heading = last[3] + 0.5 * math.remainder(phi - last[3], 2.0 * math.pi)
            rolled = 0.5 * (v + last[4]) * dt
            pull = min(1.0, dt / cfg.anchor_time)
            own_dx, own_dy = rolled * math.cos(heading), rolled * math.sin(heading)
            self.own_x += own_dx
            self.own_y += own_dy
            self.error_x += own_dx - dxr + pull * (ex - self.error_x)
            self.error_y += own_dy - dyr + pull * (ey - self.error_y)
        size = self.wheel_error
        # Sliding minimum over the window: a deque of increasing sizes (each sample is
        # pushed and popped once, so a tick costs O(1) whatever the window).
        history = self._history
        while history and history[-1][1] >= size:
            history.pop()
        history.append((t, size, self.own_x, self.own_y))
        while history[0][0] < t - cfg.growth_window:
            history.popleft()
        return self._growth(size, history[0], ex, ey) or self._absurd(t, ex, ey)

    def _growth(self, size: float, least: tuple, ex: float, ey: float) -> str:
        """Return the growth verdict, '' or why.

        ``least``: the window's sample of least |ε_w|, (t, |ε_w|, own_x, own_y).
        """
        cfg = self.config
        _, smallest, own_x0, own_y0 = least
        growth = size - smallest
        self.largest_growth = max(self.largest_growth, growth)
        if growth <= cfg.max_error_growth:
            return ''
        # The part of the growth the vehicle made itself: its own path since the window's
        # least error, along the error now (the rest is the reference leaving it behind).
        own = ((self.own_x - own_x0) * self.error_x
               + (self.own_y - own_y0) * self.error_y) / size
        if own < cfg.min_own_share * growth:
            return ''
        return (f'runaway: by its wheels and IMU the vehicle moved {growth:.2f} m farther '
                f'from the reference within {cfg.growth_window:g} s, {own:.2f} m of it by '
                f'its own motion (> max_error_growth {cfg.max_error_growth:g} m; the '
                f'position estimate says {math.hypot(ex, ey):.2f} m off): the position '
                'estimate is likely wrong (datum.*, position_source, a jump) or the wheels '
                'drive against the command (wheel signs)')

    def _absurd(self, t: float, ex: float, ey: float) -> str:
        cfg = self.config
        error = math.hypot(ex, ey)
        if error <= cfg.max_tracking_error:
            self._absurd_since = None
            return ''
        if self._absurd_since is None:
            self._absurd_since = t
        if t - self._absurd_since >= cfg.tracking_error_time:
            return (f'runaway: tracking error {error:.4g} m > max_tracking_error '
                    f'{cfg.max_tracking_error:g} m for {t - self._absurd_since:.2f} s: the '
                    "position and the reference disagree (datum.*, position_source, the "
                    "path's frame)")
        return ''
