r"""Reference trajectories (x_r, y_r, ϕ_r, υ_r, ω_r, ω̇_r) for the generator of eq. (9) in [1]_.

Every reference is a planar path with its speed along it, sampled as a pure function of
time. This module holds the configuration (:class:`ReferenceParams`) and builds the
reference a configuration selects (:func:`make_reference`).

Kinds
-----
``trifolium`` (Section V): x_r = κ cos(3Ω t) cos(Ω t), y_r = κ cos(3Ω t) sin(Ω t),
κ = 3 m, Ω = π/45 rad/s. Its speed is κΩ √(1 + 8 sin²(3Ω t)) ∈ [κΩ, 3κΩ] =
[0.21, 0.63] m/s, never zero, and |ω_r| peaks at 0.70 rad/s at the petal tips.
``circle``, ``line``, ``figure_eight`` (``reference_curves.py``), and ``waypoints``: a
polyline with circular fillets at the corners and a trapezoidal speed profile
(``reference_waypoints.py``). Any of them may be time-scaled (``time_scaling.py``).
``cmd_vel`` and ``path`` follow velocity commands and paths received at run time
(``commanded.py``).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Sequence

from .commanded import CmdVelReference, PathReference, UnicycleLimits
from wip_runtime.config import ParamError, param
from .reference_curves import Circle, FigureEight, StraightLine, Trifolium
from .reference_state import Reference
from .reference_waypoints import Waypoints
from .time_scaling import shared_tables, TimeScaled

KINDS = ('trifolium', 'circle', 'line', 'figure_eight', 'waypoints', 'hold', 'cmd_vel',
         'path')
#: Kinds commanded at run time (``core.commanded``): stateful, never time-scaled.
COMMANDED_KINDS = ('cmd_vel', 'path')


def distance_to_path(reference: Reference, x: Sequence[float], y: Sequence[float],
                     path_duration: float, resolution: float = 0.001):
    """Distance [m] of each point (x, y) to the path of ``reference``.

    The path is the one traced over [0, ``path_duration``] of the reference's own time (for
    a :class:`TimeScaled`, pass its base).

    The path is sampled every ``resolution`` [m] of arc length at most (nearest sample
    by a k-d tree), so the result exceeds the true distance by at most resolution/2.
    """
    import numpy as np
    import scipy.spatial
    v_peak = max(reference.sample(t).v for t in np.linspace(0.0, path_duration, 2001))
    n = max(2, int(math.ceil(path_duration * max(v_peak, 1e-9) / resolution)) + 1)
    times = np.linspace(0.0, path_duration, n)
    points = np.array([(r.x, r.y) for r in map(reference.sample, times)])
    tree = scipy.spatial.cKDTree(points)
    distance, _ = tree.query(np.column_stack([np.asarray(x, float), np.asarray(y, float)]))
    return distance


@dataclasses.dataclass(frozen=True)
class ReferenceParams:
    """Which reference to follow and its parameters (prefixed by the kind).

    Only the fields of the selected ``kind`` are used; all are validated.
    """

    kind: str = param('trifolium', '1', 'reference trajectory', choices=KINDS)
    trifolium_size: float = param(3.0, 'm', 'kappa of the trifolium (Section V: 3)',
                                  minimum=0.0, exclusive_minimum=True)
    trifolium_angular_frequency: float = param(
        math.pi / 45.0, 'rad/s', 'Omega_r of the trifolium (Section V: pi/45, one figure '
        'every 45 s)', minimum=0.0, exclusive_minimum=True)
    circle_center: tuple[float, float] = param((0.0, 0.0), 'm', 'centre of the circle')
    circle_radius: float = param(2.0, 'm', 'radius of the circle', minimum=0.0,
                                 exclusive_minimum=True)
    circle_speed: float = param(0.5, 'm/s', 'speed on the circle', minimum=0.0,
                                exclusive_minimum=True)
    circle_direction: str = param('ccw', '1', 'sense of travel on the circle',
                                  choices=('ccw', 'cw'))
    circle_start_angle: float = param(0.0, 'rad', 'polar angle of the start point about '
                                      'the centre')
    line_start: tuple[float, float] = param((0.0, 0.0), 'm', 'start point of the line '
                                            '(kinds hold, cmd_vel, path: the start pose)')
    line_heading: float = param(0.0, 'rad', 'direction of the line (REP 103: 0 = +x; kinds '
                                'hold, cmd_vel, path: the start heading)')
    line_speed: float = param(0.5, 'm/s', 'speed along the line', minimum=0.0,
                              exclusive_minimum=True)
    figure_eight_center: tuple[float, float] = param((0.0, 0.0), 'm',
                                                     'crossing point of the figure eight')
    figure_eight_size: float = param(3.0, 'm', 'half-width a of the lemniscate of Gerono',
                                     minimum=0.0, exclusive_minimum=True)
    figure_eight_period: float = param(60.0, 's', 'time to run the whole figure eight',
                                       minimum=0.0, exclusive_minimum=True)
    waypoints_x: tuple[float, ...] = param((0.0, 4.0, 4.0, 0.0), 'm',
                                           'x of the waypoints, in order')
    waypoints_y: tuple[float, ...] = param((0.0, 0.0, 4.0, 4.0), 'm',
                                           'y of the waypoints (same length as waypoints_x)')
    waypoints_speed: float = param(0.5, 'm/s', 'cruise speed between waypoints',
                                   minimum=0.0, exclusive_minimum=True)
    waypoints_acceleration: float = param(0.2, 'm/s^2', 'acceleration and braking limit '
                                          'of the speed profile', minimum=0.0,
                                          exclusive_minimum=True)
    waypoints_corner_radius: float = param(1.0, 'm', 'radius of the corner fillets '
                                           '(reduced where a leg is too short)',
                                           minimum=0.0, exclusive_minimum=True)
    waypoints_max_yaw_rate: float = param(0.25, 'rad/s', 'yaw-rate limit on the fillets '
                                          '(keep below the generator max_yaw_rate)',
                                          minimum=0.0, exclusive_minimum=True)
    cmd_vel_timeout: float = param(
        0.5, 's', 'cmd_vel: a command older than this (by its stamp) is refused; this long '
        'after the last accepted one the reference brakes to rest', minimum=0.05,
        maximum=10.0)
    cmd_vel_stamped: bool = param(
        True, '1', 'cmd_vel: true: geometry_msgs/TwistStamped (stamp checked); false: '
        'geometry_msgs/Twist (stamped on receipt)')
    commanded_max_speed: float = param(
        0.5, 'm/s', 'cmd_vel, path: |speed| limit of the reference (keep below the generator '
        'max_speed: the feedback of eq. (9) needs headroom)', minimum=0.0,
        exclusive_minimum=True, maximum=1.5)
    commanded_max_acceleration: float = param(
        0.3, 'm/s^2', 'cmd_vel, path: |acceleration| limit of the reference speed',
        minimum=0.0, exclusive_minimum=True, maximum=2.0)
    commanded_max_yaw_rate: float = param(
        0.25, 'rad/s', 'cmd_vel, path: |yaw rate| limit of the reference (keep below the '
        'generator max_yaw_rate)', minimum=0.0, exclusive_minimum=True, maximum=0.3)
    commanded_max_yaw_acceleration: float = param(
        0.5, 'rad/s^2', 'cmd_vel, path: |yaw acceleration| limit of the reference (keep '
        'below the generator max_yaw_acceleration)', minimum=0.0, exclusive_minimum=True,
        maximum=2.0)
    path_speed: float = param(
        0.3, 'm/s', 'path: cruise speed along the received path (at most '
        'commanded_max_speed)', minimum=0.0, exclusive_minimum=True, maximum=1.5)
    path_lookahead: float = param(
        0.5, 'm', 'path: the reference steers towards the point this far ahead on the path '
        '(pure pursuit; shorter: closer to the corners, sharper turns)', minimum=0.05,
        maximum=10.0)
    time_scaling: bool = param(
        True, '1', 'run the reference along its path with a progress that slows where '
        'its speed or yaw rate would exceed path_max_speed, path_max_yaw_rate (any kind; '
        'paper: false)')
    path_max_speed: float = param(
        1.2, 'm/s', 'time_scaling: speed limit of the reference (keep below the '
        'generator max_speed: the feedback of eq. (9) needs headroom)', minimum=0.0,
        exclusive_minimum=True)
    path_max_yaw_rate: float = param(
        0.2, 'rad/s', 'time_scaling: yaw-rate limit of the reference (keep below the '
        'generator max_yaw_rate)', minimum=0.0, exclusive_minimum=True)
    path_progress_rate_limit: float = param(
        0.5, '1/s', 'time_scaling: largest |d sigma/ds|, the change of the progress rate '
        'ds/dt per second of path (docs/decisions/reference-parameters.md)', minimum=0.01,
        maximum=100.0)
    path_speed_lead_time: float = param(
        0.75, 's', 'time_scaling: the speed feed-forward of eq. (9) is the re-timed speed '
        'this long ahead; 0: at t (docs/decisions/reference-parameters.md)', minimum=0.0,
        maximum=5.0)
    path_speed_lead_time_accelerating: float = param(
        0.6, 's', 'time_scaling: path_speed_lead_time used where the speed ahead of eq. (9) '
        'is larger (speeding up) (docs/decisions/reference-parameters.md)', minimum=0.0,
        maximum=5.0)

    def validate(self) -> None:
        if len(self.waypoints_x) != len(self.waypoints_y):
            raise ParamError(f'waypoints_y: has {len(self.waypoints_y)} values but '
                              f'waypoints_x has {len(self.waypoints_x)}')
        if len(self.waypoints_x) < 2:
            raise ParamError(f'waypoints_x: need at least 2 waypoints, got '
                              f'{len(self.waypoints_x)}')
        if self.kind == 'waypoints':
            try:
                _make_waypoints(self)
            except ValueError as err:
                raise ParamError(f'waypoints_x: {err}') from err


def _make_waypoints(config: ReferenceParams) -> Waypoints:
    return Waypoints(list(zip(config.waypoints_x, config.waypoints_y)),
                     speed=config.waypoints_speed,
                     acceleration=config.waypoints_acceleration,
                     corner_radius=config.waypoints_corner_radius,
                     max_yaw_rate=config.waypoints_max_yaw_rate)


def make_reference(config: ReferenceParams | None = None) -> Reference:
    """Build the reference selected by ``config.kind`` (default: the paper's trifolium).

    Time-scaled (:class:`TimeScaled`) if ``config.time_scaling``.
    """
    config = config if config is not None else ReferenceParams()
    config.validate()
    if config.kind in COMMANDED_KINDS:
        return make_commanded(config)
    base = _make_base_reference(config)
    if config.time_scaling:
        # The tables depend on neither lead time: one key for every lead.
        key = dataclasses.replace(config, path_speed_lead_time=0.0,
                                  path_speed_lead_time_accelerating=0.0)
        return TimeScaled(base, config.path_max_speed, config.path_max_yaw_rate,
                          config.path_progress_rate_limit,
                          speed_lead_time=config.path_speed_lead_time,
                          speed_lead_time_accelerating=config.path_speed_lead_time_accelerating,
                          tables=shared_tables(key))
    return base


def make_loop_reference(config: ReferenceParams | None = None) -> tuple[Reference, str]:
    """:func:`make_reference` for a control loop, and a warning ('' if none).

    A time-scaled closed-form curve is sampled compiled (``TimeScaled.use_compiled``: the
    same floats in one call); the warning says why a curve that has a compiled form is not.
    """
    reference = make_reference(config)
    if not isinstance(reference, TimeScaled) or reference.base_kernel_kind < 0:
        return reference, ''
    return reference, reference.use_compiled()


def _make_base_reference(config: ReferenceParams) -> Reference:
    if config.kind == 'trifolium':
        return Trifolium(config.trifolium_size, config.trifolium_angular_frequency)
    if config.kind == 'circle':
        return Circle(config.circle_center, config.circle_radius, config.circle_speed,
                      config.circle_direction, config.circle_start_angle)
    if config.kind == 'line':
        return StraightLine(config.line_start, config.line_heading, config.line_speed)
    if config.kind == 'hold':       # stand still: the line's start, at zero speed
        return StraightLine(config.line_start, config.line_heading, 0.0)
    if config.kind == 'figure_eight':
        return FigureEight(config.figure_eight_center, config.figure_eight_size,
                           config.figure_eight_period)
    if config.kind == 'waypoints':
        return _make_waypoints(config)
    raise ParamError(f'kind: {config.kind!r} is not one of {list(KINDS)}')


def make_commanded(config: ReferenceParams,
                   t0: float = 0.0) -> CmdVelReference | PathReference:
    """Return the reference of a commanded kind (``cmd_vel``, ``path``).

    It rests at the start pose (``line_start``, ``line_heading``) from time t0 [s] until
    commanded.
    """
    limits = UnicycleLimits(config.commanded_max_speed, config.commanded_max_acceleration,
                            config.commanded_max_yaw_rate,
                            config.commanded_max_yaw_acceleration)
    start = (*config.line_start, config.line_heading)
    if config.kind == 'cmd_vel':
        return CmdVelReference(limits, config.cmd_vel_timeout, start=start, t0=t0)
    if config.kind == 'path':
        return PathReference(limits, config.path_speed, config.path_lookahead, start=start,
                             t0=t0)
    raise ParamError(f'kind: {config.kind!r} is not one of {list(COMMANDED_KINDS)}')
