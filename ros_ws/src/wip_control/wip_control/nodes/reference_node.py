"""Reference node: the reference trajectory (x_r, y_r, ϕ_r, υ_r, ω_r, ω̇_r) of the generator.

Publishes ``/wip/reference`` (wip_msgs/ReferenceState) at ``rates.control_rate``, the
reference sampled at the stamp's time (``core.references``: trifolium, circle, line,
figure eight, waypoints), and ``/diagnostics``.

lockstep: one reference per ``/clock`` sample on the control grid (t = k / control_rate,
t = 0 included), stamped with that sample's time, so that the generator finds
reference(t_k) for every estimate(t_k). (A sim-time timer would first fire one period
after t = 0: see ``wip_runtime.clock``.)
realtime, ``realtime_trigger``:

- ``'state_estimate'`` (default): one reference per ``/wip/state_estimate``, stamped with
  the estimate's stamp (the sensor sample's time). The node then needs no wake-up of its
  own: a 200 Hz timer cost the composed controllers 2.6 points of a core
  (docs/realtime.md). An estimate not newer than the last one is dropped as stale.
- ``'timer'``: a timer of period 1/``rates.control_rate`` on the node clock, stamped with
  the node clock's now (the reference without an estimator, e.g. to view a path).

The reference time is, with ``realtime_start``:

- ``'first_tick'`` (default): the time since the node's first tick (the path starts when
  the node does);
- ``'engaged'`` (hardware mode): the time since the first /wip/wheel_torques message that
  is not ``zeroed``, i.e. since the safety layer first let torque through. Until then the
  node publishes the path's start, reference(0), so that a robot that is held, or waits
  for its sensors and the ESO to settle, does not fall behind a path that already runs.
  Later safety stops do not pause the path.

Commanded kinds (``reference.kind``, docs/driving.md):

- ``'cmd_vel'``: subscribes ``cmd_vel`` (geometry_msgs/TwistStamped, or Twist with
  ``reference.cmd_vel_stamped: false``; a relative name, so a namespace or a remap
  applies). A command stamped ahead of the node clock by more than ``max_stamp_lead``,
  older than ``reference.cmd_vel_timeout``, out of order or not finite is refused and
  counted on /diagnostics (input ``cmd_vel``).
- ``'path'``: subscribes ``plan`` (nav_msgs/Path, Nav2's planner output name), in
  ``frame_id`` (a path in another frame is refused, counted as ``plan`` 'frame'). A new
  path is taken up where the reference is (``PathReference.set_path``): the same path
  again changes nothing.

An obstacle the wheels cannot climb (``obstacle_blocked`` in a /wip/state_estimate, read
for the commanded kinds): when the trajectory generator refuses (blocked for
``trajectory_generator.obstacle_refuse_delay``), the commanded reference restarts at rest
``trajectory_generator.obstacle_back_off`` behind the blocked pose, where the generator
holds (core/obstacle_refusal.py); the next command or path resumes from there.

Both start at rest at ``line_start``, ``line_heading``; in real time with the
``state_estimate`` trigger at the estimated pose instead (the first estimate, or with
``realtime_start: 'engaged'`` the last one before the safety layer engaged), so that a
robot put down anywhere is not driven back to the map origin. Commands and paths before
the reference time starts (``'engaged'``) are refused as 'waiting'.

Parameters (read-only): sections ``reference`` and ``rates``;
``trajectory_generator.obstacle_back_off``, ``obstacle_refuse_delay``; ``frame_id``,
``realtime_start``, ``realtime_trigger``, ``clock_mode``, ``diagnostics_period``.
"""

from __future__ import annotations

import math
import sys
import time

from geometry_msgs.msg import Twist, TwistStamped
from nav_msgs.msg import Path
from wip_msgs.msg import (ReferenceState as ReferenceStateMsg, StateEstimate as StateEstimateMsg,
                          WheelTorques)

from ..core.obstacle_refusal import make_refusal
from ..core.reference_state import ReferenceState
from ..core.safety import SafetyDecision
from ..core.state_estimation import PoseEstimate
from ..core.references import COMMANDED_KINDS, make_loop_reference, ReferenceParams
from ..core.controller_settings import RatesParams
from .common import ControllerNode
from wip_runtime.clock import ClockTicker
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from wip_runtime.stamps import stamp_to_ns
from .conversions import reference_to_msg, unchecked_estimate_from_msg
from wip_runtime.diagnostics import OK, WARN
from wip_runtime.parameters import RosParams
from .settings import ObstacleRefusalParams, ReferenceNodeParams


class ReferenceNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        # 'tick': what makes the node publish (/clock, the state estimate or its timer).
        super().__init__('reference', 'reference trajectory', ('tick',), **kwargs)
        self.config = RosParams(self, 'reference', ReferenceParams).config
        self.rates = RosParams(self, 'rates', RatesParams).config
        settings = RosParams(self, '', ReferenceNodeParams).config
        refusal = RosParams(self, 'trajectory_generator', ObstacleRefusalParams).config
        self.frame_id = settings.frame_id
        self.realtime_start = settings.realtime_start
        self.waiting = not self.lockstep and self.realtime_start == 'engaged'
        self.reference = self._loop_reference()
        self.commanded = self.config.kind in COMMANDED_KINDS
        if self.config.kind == 'cmd_vel':
            # A teleop on another computer: its clock may lead ours a little (chrony).
            self.reference.max_lead = self.max_stamp_lead_ns / 1e9
        # Real time, estimate-triggered: the commanded reference starts at the estimate.
        self.start_at_estimate = (self.commanded and not self.lockstep
                                  and settings.realtime_trigger == 'state_estimate')
        self.started_at_estimate = False
        self.period = 1.0 / self.rates.control_rate
        self.publisher = self.create_publisher(ReferenceStateMsg, 'wip/reference',
                                               RELIABLE_QOS, direct_type=ReferenceState)
        self.last_stamp_ns: int | None = None
        if self.lockstep:
            self.ticker = ClockTicker(self, self.period, self._guarded)
        elif settings.realtime_trigger == 'state_estimate':
            self.subscribe_value(StateEstimateMsg, 'wip/state_estimate', 'tick',
                                 self._on_estimate, PoseEstimate,
                                 unchecked_estimate_from_msg)
        else:
            self.create_timer(self.period, lambda: self._guarded(self.now_ns()))
        if self.config.kind == 'cmd_vel':
            self._add_input('cmd_vel')
            if self.config.cmd_vel_stamped:
                self.subscribe(TwistStamped, 'cmd_vel', 'cmd_vel', self._on_twist_stamped)
            else:
                self.subscribe(Twist, 'cmd_vel', 'cmd_vel', self._on_twist)
        elif self.config.kind == 'path':
            self._add_input('plan')
            self.subscribe(Path, 'plan', 'plan', self._on_path)
        # A commanded reference restarts at rest where the generator holds after an
        # obstacle refused (core/obstacle_refusal.py): a new command or path resumes from there.
        self.refusal = make_refusal(refusal) if self.commanded else None
        triggered = not self.lockstep and settings.realtime_trigger == 'state_estimate'
        if self.refusal is not None and not triggered:
            self.subscribe_value(StateEstimateMsg, 'wip/state_estimate', 'state_estimate',
                                 self._on_state_estimate, PoseEstimate,
                                 unchecked_estimate_from_msg)
        if self.waiting:
            # The message as it is: _on_torques reads only `zeroed`, which the mixer's
            # SafetyDecision (handed in the same process) has under the same name.
            self.subscribe_value(WheelTorques, 'wip/wheel_torques', 'wheel_torques',
                                 self._on_torques, SafetyDecision)
            self.diagnostics.state(WARN, f'{self.config.kind} reference at '
                                   f'{self.rates.control_rate:g} Hz: holding its start '
                                   'until the safety layer engages')
        else:
            self.diagnostics.state(OK, f'{self.config.kind} reference at '
                                   f'{self.rates.control_rate:g} Hz')

    def _loop_reference(self):
        """Make the reference; a time-scaled curve sampled compiled (the same floats)."""
        reference, warning = make_loop_reference(self.config)
        if warning:
            self.get_logger().warning(f'time-scaled reference interpreted: {warning}')
        elif getattr(reference, 'compiled', False):
            self.get_logger().info('time-scaled reference: the compiled sample')
        return reference

    def _add_input(self, name: str) -> None:
        """Report the age of the command input on /diagnostics too."""
        self.diagnostics.inputs = (*self.diagnostics.inputs, name)
        self.diagnostics.last_stamp[name] = None

    def _on_estimate(self, stamp: int, pose: PoseEstimate) -> None:
        """realtime_trigger 'state_estimate': the reference at the estimate's time."""
        if self.last_stamp_ns is not None and stamp <= self.last_stamp_ns:
            self.diagnostics.input('tick', stamp)
            self.diagnostics.drop('tick', 'stale', f'stamp {stamp} ns not after the last '
                                  f'published {self.last_stamp_ns} ns')
            return
        if self.start_at_estimate and (self.waiting or not self.started_at_estimate):
            start = (pose.x, pose.y, pose.estimate.phi)
            if all(math.isfinite(value) for value in start):
                # Until the path's time starts, t stays 0 (see publish_at).
                self.reference.reset(0.0, *start)
                self.started_at_estimate = True
        if self.refusal is not None:
            self._on_obstacle(stamp, pose)
        self._guarded(stamp)

    def _on_state_estimate(self, stamp: int, pose: PoseEstimate) -> None:
        """Count an estimate that is not the node's trigger, then look at its obstacle."""
        self.diagnostics.input('state_estimate', stamp)
        self._on_obstacle(stamp, pose)

    def _on_obstacle(self, stamp: int, pose: PoseEstimate) -> None:
        """Restart a commanded reference at rest where a refusal holds (obstacle_blocked)."""
        times = self._command_times(stamp)
        if times is None:
            return
        t = times[0]
        refusal = self.refusal.blocking(t, pose.obstacle_blocked, pose.x, pose.y,
                                        pose.estimate.phi)
        if refusal is None:
            return
        hold, back_off = refusal.hold, self.refusal.back_off
        self.reference.reset(t, hold.x, hold.y, hold.phi)
        self.diagnostics.values['obstacle'] = (
            f'refused at {t:.2f} s: the {self.config.kind} reference restarted at rest at '
            f'({hold.x:.2f}, {hold.y:.2f}) m, {back_off:.2f} m back')
        self.get_logger().warning(
            f'wheels blocked by an obstacle: the {self.config.kind} reference restarts at rest '
            f'{back_off:.2f} m back; a new command or path resumes')

    def _command_times(self, stamp_ns: int) -> tuple[float, float] | None:
        """(stamp, now) [s] of the reference's time base; None before it starts."""
        if self.waiting or self.time_base.origin_ns is None:
            return None
        return self.time_base.seconds(stamp_ns), self.time_base.seconds(self.now_ns())

    def _on_twist_stamped(self, msg: TwistStamped) -> None:
        self._offer_twist(stamp_to_ns(msg.header.stamp), msg.twist)

    def _on_twist(self, msg: Twist) -> None:
        self._offer_twist(self.now_ns(), msg)  # no stamp: as of its arrival

    def _offer_twist(self, stamp_ns: int, twist: Twist) -> None:
        self.diagnostics.input('cmd_vel', stamp_ns)
        times = self._command_times(stamp_ns)
        if times is None:
            self.diagnostics.drop('cmd_vel', 'waiting', 'the reference has not started')
            return
        reason = self.reference.command(*times, twist.linear.x, twist.angular.z)
        if reason is not None:
            stamp, now = times
            self.diagnostics.drop('cmd_vel', reason, f'linear.x {twist.linear.x!r}, '
                                  f'angular.z {twist.angular.z!r}, stamp {stamp:.3f} s, '
                                  f'now {now:.3f} s')

    def _on_path(self, msg: Path) -> None:
        stamp_ns = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('plan', stamp_ns)
        if msg.header.frame_id != self.frame_id:
            self.diagnostics.drop('plan', 'frame', f'frame_id {msg.header.frame_id!r}, '
                                  f'expected {self.frame_id!r}')
            return
        if self._command_times(stamp_ns) is None:
            # A path before the start would be anchored at a pose that is still moving.
            self.diagnostics.drop('plan', 'waiting', 'the reference has not started')
            return
        points = [(pose.pose.position.x, pose.pose.position.y) for pose in msg.poses]
        reason = self.reference.set_path(points)
        if reason is not None:
            self.diagnostics.drop('plan', reason, f'{len(points)} poses')
            return
        if self.reference.joined == 'same':
            return   # a route published again: nothing changes, nothing to say
        how = {'continued': 'continues the current one', 'closest': 'from its closest point',
               'joined': 'joined by a straight leg to its closest point'}
        self.get_logger().info(f'new path: {len(points)} poses, '
                               f'{how.get(self.reference.joined, self.reference.joined)}, '
                               f'{self.reference.length:.2f} m to go')

    def _on_torques(self, stamp: int, torques: WheelTorques | SafetyDecision) -> None:
        """realtime_start 'engaged': the path's time starts at the first torque sent."""
        if self.waiting and not torques.zeroed:
            self.time_base.origin_ns = stamp
            self.waiting = False
            self.get_logger().info('the safety layer engaged: the path starts now')
            self.diagnostics.state(OK, f'{self.config.kind} reference at '
                                   f'{self.rates.control_rate:g} Hz, started when the '
                                   'safety layer engaged')

    def _guarded(self, stamp_ns: int) -> None:
        try:
            self.publish_at(stamp_ns)
        except Exception as err:  # noqa: BLE001 - a callback must not stop the node
            self.diagnostics.drop('tick', 'error', f'{type(err).__name__}: {err}')

    def publish_at(self, stamp_ns: int) -> None:
        """Publish the reference at the time of ``stamp_ns`` [ns]."""
        start = time.perf_counter()
        self.diagnostics.input('tick', stamp_ns)
        self.last_stamp_ns = stamp_ns
        # Before the start (realtime_start 'engaged'), and for a stamp older than it, the
        # path's start point.
        t = 0.0 if self.waiting else max(0.0, self.time_base.seconds(stamp_ns))
        ref = self.reference.update(t) if self.commanded else self.reference.sample(t)
        self.publisher.publish_value(stamp_ns, ref, self._reference_to_msg)
        if self.commanded:
            self._report_command(ref)
        self.diagnostics.output(stamp_ns, time.perf_counter() - start)

    def _reference_to_msg(self, ref: ReferenceState, stamp_ns: int) -> ReferenceStateMsg:
        return reference_to_msg(ref, stamp_ns, self.frame_id)

    def _report_command(self, ref) -> None:
        """Report what the commanded reference does, on /diagnostics (value 'command')."""
        moving = ref.v != 0.0 or ref.omega != 0.0
        if self.config.kind == 'cmd_vel':
            status = ('following the command' if not self.reference.timed_out
                      else 'no command in force: braking' if moving
                      else 'no command in force: at rest')
        else:
            status = ('no path: at rest' if not self.reference.points
                      else 'following the path' if not self.reference.done
                      else 'at the end of the path' if not moving
                      else 'end of the path reached: braking')
        if self.diagnostics.values.get('command') != status:
            self.diagnostics.values['command'] = status


def main(args=None) -> int:
    """Entry point ``reference``."""
    return run_node(ReferenceNode, 'reference', args)


if __name__ == '__main__':
    sys.exit(main())
