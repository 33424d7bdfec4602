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

import dataclasses
import math

import numpy as np

from wip_runtime.config import param

from .compiled import array_slot


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


#: The slots of the guard's state array (``RunawayGuard.state``); NaN: none yet.
(T_LAST, XR_LAST, YR_LAST, PHI_LAST, V_LAST, ERROR_X, ERROR_Y, OWN_X, OWN_Y, ABSURD_SINCE,
 LARGEST_GROWTH, HEAD, COUNT, VERDICT, GROWTH, OWN, TRACKING_ERROR, ABSURD_FOR) = range(18)
STATE_SIZE = 18
#: The slots of its constants (:func:`constants`).
(MAX_ERROR_GROWTH, GROWTH_WINDOW, MAX_TRACKING_ERROR, TRACKING_ERROR_TIME, ANCHOR_TIME,
 MIN_OWN_SHARE, MAX_REFERENCE_STEP) = range(7)
#: Verdicts of :func:`guard_step`.
NO_VERDICT, GROWTH_VERDICT, ABSURD_VERDICT = 0, 1, 2
#: Each sample of the sliding window's history: (t, |ε_w|, own_x, own_y).
HISTORY_FIELDS = 4


def constants(config: RunawayParams) -> np.ndarray:
    """Return the constants of :func:`guard_step` (the slots above)."""
    return np.array([config.max_error_growth, config.growth_window,
                     config.max_tracking_error, config.tracking_error_time,
                     config.anchor_time, config.min_own_share, config.max_reference_step])


class RunawayGuard:
    """See the module docstring. Feed :meth:`update` at each estimate while engaged.

    :meth:`reset` when the safety layer stops sending torque; the next update anchors anew.
    The state is kept in float64 arrays (``state``, ``history``) that :func:`guard_step`
    advances, interpreted or compiled (``safety_kernel``).
    """

    error_x = array_slot('state', ERROR_X, 'ε_w along x [m]')
    error_y = array_slot('state', ERROR_Y, 'ε_w along y [m]')
    own_x = array_slot('state', OWN_X, "the vehicle's own path by wheels and IMU, x [m]")
    own_y = array_slot('state', OWN_Y, "the vehicle's own path by wheels and IMU, y [m]")
    largest_growth = array_slot('state', LARGEST_GROWTH,
                                'the largest growth since the last reset [m] (/diagnostics)')

    def __init__(self, config: RunawayParams | None = None) -> None:
        self.config = config if config is not None else RunawayParams()
        self.constants = constants(self.config)
        self.constants_list = self.constants.tolist()   # for the interpreter: floats
        self.state = np.zeros(STATE_SIZE)
        # The sliding window's candidates for its least |ε_w|, a ring (HEAD, COUNT); grown
        # by make_room when full.
        self.history = np.zeros(64 * HISTORY_FIELDS)
        self.reset()

    def reset(self) -> None:
        """Forget everything: the next update anchors anew."""
        s = self.state
        s[:] = 0.0
        s[T_LAST] = s[ABSURD_SINCE] = math.nan

    @property
    def wheel_error(self) -> float:
        """|ε_w| [m]."""
        return _norm(self.error_x, self.error_y)

    def make_room(self) -> None:
        """Double the history's ring if it is full (before a step)."""
        s, h = self.state, self.history
        size = len(h) // HISTORY_FIELDS
        if s[COUNT] < size:
            return
        head = int(s[HEAD])
        ring = h.reshape(size, HISTORY_FIELDS)
        grown = np.zeros(2 * len(h))
        grown[:len(h)] = np.concatenate((ring[head:], ring[:head])).ravel()
        self.history = grown
        s[HEAD] = 0.0

    def update(self, t: float, x: float, y: float, phi: float, v: float, x_ref: float,
               y_ref: float) -> str:
        """Take the estimate (x̂, ŷ, ϕ̂, υ̂) and the reference (x_r, y_r) at ``t`` [s].

        Returns the verdict: '' or why the vehicle is running away.
        """
        self.make_room()
        guard_step(self.state, self.history, self.constants_list, t, x, y, phi, v, x_ref,
                   y_ref)
        return self.verdict()

    def verdict(self) -> str:
        """Return the last step's verdict: '' or why the vehicle is running away."""
        s, cfg = self.state, self.config
        kind = s[VERDICT]
        if kind == GROWTH_VERDICT:
            return (f'runaway: by its wheels and IMU the vehicle moved {s[GROWTH]:.2f} m '
                    f'farther from the reference within {cfg.growth_window:g} s, '
                    f'{s[OWN]:.2f} m of it by its own motion (> max_error_growth '
                    f'{cfg.max_error_growth:g} m; the position estimate says '
                    f'{s[TRACKING_ERROR]:.2f} m off): the position estimate is likely wrong '
                    '(datum.*, position_source, a jump) or the wheels drive against the '
                    'command (wheel signs)')
        if kind == ABSURD_VERDICT:
            return (f'runaway: tracking error {s[TRACKING_ERROR]:.4g} m > max_tracking_error '
                    f'{cfg.max_tracking_error:g} m for {s[ABSURD_FOR]:.2f} s: the position '
                    "and the reference disagree (datum.*, position_source, the path's frame)")
        return ''


def _norm(a: float, b: float) -> float:
    """sqrt(a² + b²): the same floats interpreted and compiled (math.hypot is not)."""
    largest = max(abs(a), abs(b))
    if largest > 1e150:     # the squares would overflow: scaled (absurd positions only)
        a, b = a / largest, b / largest
        return largest * math.sqrt(a * a + b * b)
    return math.sqrt(a * a + b * b)


def guard_step(s, h, c, t: float, x: float, y: float, phi: float, v: float, x_ref: float,
               y_ref: float) -> int:
    """Advance the guard's state ``s`` and history ``h`` by one sample; return the verdict.

    ``c``: :func:`constants`. The history must have room for one more sample
    (:meth:`RunawayGuard.make_room`). The verdict and its figures are kept in ``s``.
    """
    s[VERDICT] = NO_VERDICT
    if not (math.isfinite(t) and math.isfinite(x) and math.isfinite(y)
            and math.isfinite(phi) and math.isfinite(v) and math.isfinite(x_ref)
            and math.isfinite(y_ref)):
        return NO_VERDICT   # the safety layer's own checks refuse non-finite estimates
    t_last = float(s[T_LAST])
    if t <= t_last:
        return NO_VERDICT   # not a new sample
    ex, ey = x - x_ref, y - y_ref
    dt = t - t_last
    dxr, dyr = x_ref - float(s[XR_LAST]), y_ref - float(s[YR_LAST])
    phi_last, v_last = float(s[PHI_LAST]), float(s[V_LAST])
    s[T_LAST], s[XR_LAST], s[YR_LAST], s[PHI_LAST], s[V_LAST] = t, x_ref, y_ref, phi, v
    if math.isnan(t_last) or _norm(dxr, dyr) > c[MAX_REFERENCE_STEP]:
        # The first sample, or the reference was replaced, not followed: start again
        # from the estimate.
        s[ERROR_X], s[ERROR_Y] = ex, ey
        s[HEAD] = s[COUNT] = 0.0
        if math.isnan(t_last):
            _push(s, h, t, _norm(ex, ey), c[GROWTH_WINDOW])
            return _absurd(s, c, t, ex, ey)
    else:
        heading = phi_last + 0.5 * math.remainder(phi - phi_last, 2.0 * math.pi)
        rolled = 0.5 * (v + v_last) * dt
        pull = min(1.0, dt / c[ANCHOR_TIME])
        own_dx, own_dy = rolled * math.cos(heading), rolled * math.sin(heading)
        s[OWN_X] = float(s[OWN_X]) + own_dx
        s[OWN_Y] = float(s[OWN_Y]) + own_dy
        error_x, error_y = float(s[ERROR_X]), float(s[ERROR_Y])
        s[ERROR_X] = error_x + (own_dx - dxr + pull * (ex - error_x))
        s[ERROR_Y] = error_y + (own_dy - dyr + pull * (ey - error_y))
    size = _norm(float(s[ERROR_X]), float(s[ERROR_Y]))
    _push(s, h, t, size, c[GROWTH_WINDOW])
    verdict = _growth(s, h, c, size, ex, ey)
    return verdict if verdict != NO_VERDICT else _absurd(s, c, t, ex, ey)


def _push(s, h, t: float, size: float, window: float) -> None:
    """Add the sample to the window's candidates for its least |ε_w|; drop the old ones.

    A ring of increasing sizes: each sample is pushed and popped once, so a step costs
    O(1) whatever the window.
    """
    slots = len(h) // HISTORY_FIELDS
    head, count = int(s[HEAD]), int(s[COUNT])
    while count > 0 and h[((head + count - 1) % slots) * HISTORY_FIELDS + 1] >= size:
        count -= 1
    i = ((head + count) % slots) * HISTORY_FIELDS
    h[i], h[i + 1], h[i + 2], h[i + 3] = t, size, s[OWN_X], s[OWN_Y]
    count += 1
    while h[head * HISTORY_FIELDS] < t - window:
        head = (head + 1) % slots
        count -= 1
    s[HEAD], s[COUNT] = head, count


def _growth(s, h, c, size: float, ex: float, ey: float) -> int:
    """Return the growth verdict; its figures in ``s``.

    From the window's sample of least |ε_w| (the oldest of the ring).
    """
    i = int(s[HEAD]) * HISTORY_FIELDS
    smallest, own_x0, own_y0 = float(h[i + 1]), float(h[i + 2]), float(h[i + 3])
    growth = size - smallest
    s[LARGEST_GROWTH] = max(float(s[LARGEST_GROWTH]), growth)
    if growth <= c[MAX_ERROR_GROWTH]:
        return NO_VERDICT
    # The part of the growth the vehicle made itself: its own path since the window's
    # least error, along the error now (the rest is the reference leaving it behind).
    own = ((float(s[OWN_X]) - own_x0) * float(s[ERROR_X])
           + (float(s[OWN_Y]) - own_y0) * float(s[ERROR_Y])) / size
    if own < c[MIN_OWN_SHARE] * growth:
        return NO_VERDICT
    s[VERDICT], s[GROWTH], s[OWN], s[TRACKING_ERROR] = GROWTH_VERDICT, growth, own, _norm(ex, ey)
    return GROWTH_VERDICT


def _absurd(s, c, t: float, ex: float, ey: float) -> int:
    """Return the absurd-error verdict (|e| too large for too long); its figures in ``s``."""
    error = _norm(ex, ey)
    if error <= c[MAX_TRACKING_ERROR]:
        s[ABSURD_SINCE] = math.nan
        return NO_VERDICT
    if math.isnan(s[ABSURD_SINCE]):
        s[ABSURD_SINCE] = t
    since = t - float(s[ABSURD_SINCE])
    if since >= c[TRACKING_ERROR_TIME]:
        s[VERDICT], s[TRACKING_ERROR], s[ABSURD_FOR] = ABSURD_VERDICT, error, since
        return ABSURD_VERDICT
    return NO_VERDICT
