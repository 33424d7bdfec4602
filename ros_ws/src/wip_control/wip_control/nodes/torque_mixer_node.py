"""Torque mixer node: wheel torques from (τυ, τω), eq. (24) in [1]_, behind the safety layer.

This node is the only one that commands the wheels, so it is the safety layer of the
drop-in controller (``core/safety.py``; why zero torque is the fail-safe of a balancing
robot: docs/decisions/safety-layer.md).

Topics
------
Subscribes
    ``/wip/yaw_torque`` (wip_msgs/YawTorque: τω), ``/wip/drive_torque`` (wip_msgs/DriveTorque:
    τυ and the MPC's status, held between MPC ticks), ``/wip/state_estimate``
    (wip_msgs/StateEstimate: θ̂ for the fall threshold, rates and disturbances for the ESO
    divergence check, ``settled`` for the start-up), ``/wip/estop`` (std_msgs/Bool: true
    engages the e-stop, latched; false releases the button, which allows a reset once no
    true came for ``safety.estop_hold_time``), ``/wip/heartbeat`` (std_msgs/Empty: the
    supervisor's arming heartbeat, ``safety.max_estop_age``; never a release),
    ``/wip/estop_reset`` (std_msgs/Empty: the reset, as the service below); in real
    time with ``runaway.enabled``, ``/wip/reference`` (wip_msgs/ReferenceState: the
    reference position, for the runaway guard of ``core/runaway.py``); in real
    time with ``wiring_check.enabled``, the base's ``/joint_states`` and ``/imu/data``
    (sensor-data QoS) for the wiring checks at engage (``core/wiring_check.py``: wheel
    signs, joint names and IMU mounting judged from the sensors against each other; a
    verdict is a latched fault naming the parameter).
Publishes
    ``/wip/wheel_torques`` (wip_msgs/WheelTorques: the torques of the tick, ``zeroed`` and
    the ``reason`` when the safety layer forced zero; in shadow mode the torques that would
    be sent), the command of the base on ``effort_topic`` (default
    ``/effort_controller/commands``, std_msgs/Float64MultiArray, one effort per joint in the
    order of ``joints``, for a ros2_control ``JointGroupEffortController``; each effort is
    the wheel torque times the joint's ``left_wheel_sign`` / ``right_wheel_sign`` (−1 for
    a joint whose positive direction rolls the robot backwards; the wheel torques are
    REP 103, positive driving forward); zero in shadow mode: the ESO, which reads
    /wip/wheel_torques as the applied torques, then assumes torques the base does not
    get, and its disturbance estimates absorb the difference),
    ``/diagnostics`` (safety state, every reason, input ages, counters; also at once
    on each change of the safety state).
Service
    ``~/reset_estop`` (std_srvs/Trigger): reset a latched e-stop (and latched faults);
    refused, with the reason, while ``/wip/estop`` still says true or said it within
    ``safety.estop_hold_time``.

Per tick: ``core.safety.SafetyMonitor.update`` — ``core.mixer.mix(τυ, τω, τmax)`` (the
runner's step 7: yaw first, each wheel within ±τmax) when every check passes, rate limited
by ``mixer.max_wheel_torque_rate``; zero torque at once, with the reason, otherwise.

Clock modes
-----------
realtime: a command as soon as a yaw torque arrives, with the latest drive torque and
estimate, and a watchdog timer of period 1/``rates.control_rate`` in between; lockstep:
one command per stamp t_k once that tick's inputs have arrived (docs/control-loop.md,
"The torque mixer's clock modes").

Parameters: section ``mixer`` (changeable at run time, validated), sections ``rates`` and
``safety`` (read-only: a safety setting does not change under a running robot),
``mpc.sampling_period``, ``mpc.fast_resolve_period`` [s], ``mpc.push_trigger``, ``joints``,
``left_joint``, ``right_joint``, ``left_wheel_sign``, ``right_wheel_sign`` (1 or −1),
``effort_topic``, ``clock_mode``, ``diagnostics_period``, section ``wiring_check``, ``model.*`` and
``imu_mounting_rpy`` (the wiring checks; all read-only).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from rclpy.duration import Duration
from std_msgs.msg import Bool, Empty, Float64MultiArray
from std_srvs.srv import Trigger
from wip_msgs.msg import (YawTorque, DriveTorque, ReferenceState as ReferenceStateMsg,
                          StateEstimate as StateEstimateMsg, WheelTorques)

from wip_runtime.config import ParamError
from ..core.arc import ArcOutput
from ..core.mixer import MixerParams
from ..core.mpc_config import drive_tick_decimation, resolves_faster
from ..core.safety import (ACTIVE, DEGRADED, ESTOP, FAULT, SafetyDecision, SafetyMonitor,
                           SHADOW, STARTING)
from ..core.safety_config import SafetyParams
from ..core.controller_settings import RatesParams
from ..core.reference_state import ReferenceState
from ..core.runaway import RunawayParams
from ..core.state_estimation import PoseEstimate
from .common import ControllerNode
from .mixer_wiring import WiringCheckInputs
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from wip_runtime.stamps import stamp_to_ns
from .conversions import (decision_to_msg, effort_command, EffortCommandCdr,
                          unchecked_estimate_from_msg)
from wip_runtime.diagnostics import ERROR, OK, WARN
from wip_runtime.executors import Watchdog
from .hardware_inputs import signed_efforts
from .effort_interface import declare_effort_interface
from wip_runtime.parameters import RosParams
from .settings import MixerNodeParams, MpcPeriod
from wip_runtime.sync import decimation, ExactTimeSync, is_decimated_tick

_INPUTS = ('yaw_torque', 'drive_torque')
_DIAGNOSED = (*_INPUTS, 'state_estimate', 'estop')
#: Estimates kept by stamp in lockstep (only the current tick's is needed).
_MAX_ESTIMATE_STAMPS = 64
#: Least wall time between two /diagnostics sent at once on a state change [s].
_DIAGNOSTICS_ON_CHANGE_PERIOD = 0.05
#: Commands over which the sensor -> command latency percentiles are reported (60 s).
LATENCY_WINDOW = 12000
#: Longest wait [s] for the base to acknowledge the zero command sent on stopping.
STOP_ACK_TIMEOUT = 1.0
_LEVEL = {ACTIVE: OK, DEGRADED: WARN, SHADOW: WARN, STARTING: WARN, FAULT: ERROR,
          ESTOP: ERROR}


class LatencyWindow:
    """The last ``size`` sensor -> command latencies [s], a ring of floats.

    A status takes their percentiles once a second, on the control thread, from the ring as
    it is: no copy of the window first.
    """

    __slots__ = ('values', 'count')

    def __init__(self, size: int) -> None:
        self.values = np.empty(size)
        self.count = 0      # latencies added so far

    def add(self, latency: float) -> None:
        """Take a command's latency [s], in place of the oldest once the window is full."""
        self.values[self.count % len(self.values)] = latency
        self.count += 1

    def __len__(self) -> int:
        """Return how many latencies the window holds (at most its size)."""
        return min(self.count, len(self.values))

    def percentiles(self, q) -> np.ndarray:
        """``np.percentile`` of the window's latencies (at least one added)."""
        return np.percentile(self.values[:len(self)], q)


class TorqueMixerNode(WiringCheckInputs, ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('torque_mixer', 'torque mixer (24) and safety', _DIAGNOSED, **kwargs)
        self.parameters = RosParams(self, 'mixer', MixerParams, self._on_config)
        self.mixer = self.parameters.config
        self.rates = RosParams(self, 'rates', RatesParams).config
        mpc_periods = RosParams(self, 'mpc', MpcPeriod).config
        self.safety = RosParams(self, 'safety', SafetyParams).config
        runaway = RosParams(self, 'runaway', RunawayParams).config
        settings = RosParams(self, '', MixerNodeParams).config
        wheels = declare_effort_interface(self)
        self.left_joint, self.right_joint = wheels.left_joint, wheels.right_joint
        self.joints = list(wheels.joints)
        self.left_sign, self.right_sign = wheels.left_sign, wheels.right_sign
        self.effort_command_cdr = EffortCommandCdr(self.joints, self.left_joint,
                                                   self.right_joint)
        effort_topic = settings.effort_topic
        if not effort_topic:
            raise ParamError(f'effort_topic: must be a topic name, got {effort_topic!r}')
        self.control_period = 1.0 / self.rates.control_rate
        # The drive stage's grid (core.control_step.DriveControllerStage.is_tick): its
        # re-solve period when set, every control tick with the push trigger (in lockstep
        # the MPC node answers each of its ticks, held or solved).
        fast = mpc_periods.fast_resolve_period
        self.every = drive_tick_decimation(
            decimation(mpc_periods.sampling_period, self.control_period),
            decimation(fast, self.control_period)
            if resolves_faster(mpc_periods.sampling_period, fast) else None,
            mpc_periods.push_trigger)
        self.monitor = SafetyMonitor(self.safety, self.mixer.max_wheel_torque,
                                     self.mixer.max_wheel_torque_rate, self.control_period,
                                     timing_checks=not self.lockstep, runaway=runaway)
        warning = self.monitor.use_compiled()
        if warning:
            self.get_logger().warning(f'safety tick interpreted: {warning}')
        self.last_decision: SafetyDecision | None = None
        self._decision_limits = self.mixer   # the limits the last decision was mixed with
        self.zeroed_ticks = 0
        self._diagnostics_sent_at = 0.0
        self.estimates: dict[int, tuple] = {}        # lockstep: stamp -> (estimate, settled)
        self.latest_estimate_stamp: int | None = None
        # The decision goes as it is to this process's ESO, MPC and reference.
        self.torques_publisher = self.create_publisher(WheelTorques, 'wip/wheel_torques',
                                                       RELIABLE_QOS, direct_type=SafetyDecision)
        self.effort_publisher = self.create_publisher(Float64MultiArray, effort_topic,
                                                      RELIABLE_QOS)
        if self.lockstep:
            self.sync = ExactTimeSync(_INPUTS, self._mix_set, required=self._required,
                                      gate=self._estimate_ready)
        else:
            # Watchdog: restarted by every command sent on a yaw torque's arrival; a
            # composed process keeps it in its spin loop (wip_runtime.executors.Watchdog).
            self.watchdog = Watchdog(self, self.control_period, self._tick)
            self.timer = self.watchdog.timer
        self.latencies = LatencyWindow(LATENCY_WINDOW)
        self._init_wiring_check()
        self._init_subscriptions(runaway.enabled)
        self.diagnostics.state(WARN, 'STARTING: waiting for the first inputs')
        # Ages and counters are filled in when a status is made, not at every tick.
        self._base_status = self.diagnostics.status
        self.diagnostics.status = self._status

    def _init_subscriptions(self, runaway_guard: bool) -> None:
        """Subscribe to the controllers' outputs, the e-stop, heartbeat and reset inputs."""
        self.subscribe(YawTorque, 'wip/yaw_torque', 'yaw_torque', self._on_yaw,
                       direct=self._on_yaw_value, value_type=ArcOutput)
        self.subscribe(DriveTorque, 'wip/drive_torque', 'drive_torque', self._on_drive)
        self.subscribe_value(StateEstimateMsg, 'wip/state_estimate', 'state_estimate',
                             self._on_estimate, PoseEstimate,
                             unchecked_estimate_from_msg)
        if not self.lockstep and runaway_guard:
            self.subscribe_value(ReferenceStateMsg, 'wip/reference', 'reference',
                                 self._on_reference, ReferenceState)
        self.subscribe(Bool, 'wip/estop', 'estop', self._on_estop)
        self.subscribe(Empty, 'wip/heartbeat', 'heartbeat',
                       lambda _msg: self.monitor.heartbeat(self.monitor_time()))
        self.subscribe(Empty, 'wip/estop_reset', 'estop_reset',
                       lambda _msg: self.reset_estop('/wip/estop_reset'))
        self.create_service(Trigger, '~/reset_estop', self._on_reset_service)

    # -- parameters and time -------------------------------------------------------------------
    def _on_config(self, config: MixerParams) -> None:
        self.mixer = config
        self.monitor.set_limits(config.max_wheel_torque, config.max_wheel_torque_rate)

    def monitor_time(self) -> float:
        """Time of the safety monitor [s]: steady clock in real time, node clock in lockstep."""
        if self.lockstep:
            return self.time_base.seconds(self.now_ns())
        return time.monotonic()

    def is_tick(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` is an MPC tick of the lockstep grid (from t = 0)."""
        return is_decimated_tick(stamp_ns, self.control_period, self.every)

    def _required(self, stamp_ns: int) -> tuple[str, ...]:
        return _INPUTS if self.is_tick(stamp_ns) else ('yaw_torque',)

    def _estimate_ready(self, stamp_ns: int) -> bool:
        # Lockstep: once estimates come, the set of t_k waits for estimate(t_k).
        return self.latest_estimate_stamp is None or self.latest_estimate_stamp >= stamp_ns

    # -- subscriptions -----------------------------------------------------------------------
    def _on_yaw(self, msg: YawTorque) -> None:
        self._on_yaw_value(stamp_to_ns(msg.header.stamp), msg)

    def _on_yaw_value(self, stamp: int, msg: YawTorque | ArcOutput) -> None:
        self.diagnostics.input('yaw_torque', stamp)
        if self.lockstep:
            self.feed('yaw_torque', stamp, msg.tau_omega)
        else:
            self.monitor.yaw_torque(self.monitor_time(), msg.tau_omega)
            self.watchdog.kick()
            self._tick(sensor_stamp=stamp)

    def _on_drive(self, msg: DriveTorque) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('drive_torque', stamp)
        value = (msg.tau_v, msg.status)
        if not self.lockstep:
            self.monitor.drive_torque(self.monitor_time(), *value, plan=msg.planned_tau_v,
                                      plan_period=msg.sampling_period)
        elif not self.is_tick(stamp):
            # Not awaited at this stamp: hold it from now on (the MPC's period differs
            # from mpc.sampling_period, which /diagnostics reports).
            self.diagnostics.drop('drive_torque', 'off the MPC ticks',
                                  f'stamp {stamp} ns; held without synchronisation')
            self.monitor.drive_torque(self.time_base.seconds(stamp), *value)
        else:
            self.feed('drive_torque', stamp, value)

    def _on_estimate(self, stamp: int, pose: PoseEstimate) -> None:
        self.diagnostics.input('state_estimate', stamp)
        value = (pose.estimate, bool(pose.settled), int(pose.position_status), pose.x, pose.y)
        if not self.lockstep:
            self.monitor.estimate(self.monitor_time(), *value)
            return
        last = self.sync.last_emitted
        if last is not None and stamp <= last:
            self.diagnostics.drop('state_estimate', 'stale',
                                  f'stamp {stamp} ns not after the last computed one')
            return
        if len(self.estimates) >= _MAX_ESTIMATE_STAMPS:
            del self.estimates[min(self.estimates)]
        self.estimates[stamp] = value
        if self.latest_estimate_stamp is None or stamp > self.latest_estimate_stamp:
            self.latest_estimate_stamp = stamp
        self.sync.drain()

    def _on_reference(self, _stamp: int, msg: ReferenceStateMsg | ReferenceState) -> None:
        self.monitor.reference(self.monitor_time(), msg.x, msg.y)

    def _on_estop(self, msg: Bool) -> None:
        engaged = bool(msg.data)
        self.diagnostics.input('estop', self.now_ns())
        was_latched = self.monitor.estop_latched
        self.monitor.estop(self.monitor_time(), engaged)
        if engaged and not was_latched:
            self.get_logger().error('e-stop engaged: zero torque until released and reset')

    def _on_reset_service(self, _request, response):
        response.success, response.message = self.reset_estop('~/reset_estop')
        return response

    def reset_estop(self, source: str) -> tuple[bool, str]:
        """Reset a latched e-stop (and latched faults); (success, message), logged."""
        ok, message = self.monitor.reset(self.monitor_time())
        if ok and self.wiring_check is not None:
            self.wiring_check.reset()
        if ok:
            self.get_logger().warning(f'reset via {source}: {message}')
        else:
            self.get_logger().error(f'reset refused via {source}: {message}')
        # On /diagnostics at once: a recorded run keeps every reset, also the service's.
        self.diagnostics.values['last e-stop reset'] = (
            f'{"done" if ok else "refused"} via {source} at {self.now_ns() * 1e-9:.3f} s: '
            f'{message}')
        self.diagnostics.publish()
        return ok, message

    # -- ticks ---------------------------------------------------------------------------------
    def _tick(self, sensor_stamp: int | None = None) -> None:
        """Realtime: one command with the latest inputs, on a yaw torque or from the watchdog.

        A yaw torque carries its sensor sample's stamp: the latency is recorded.
        """
        try:
            now = self.now_ns()
            decision = self.monitor.update(self.monitor_time())
            self._publish(now, decision)
            if sensor_stamp is not None and not decision.zeroed:
                self.latencies.add((self.now_ns() - sensor_stamp) * 1e-9)
        except Exception as err:  # noqa: BLE001 - a timer callback must not stop the node
            self.diagnostics.drop('tick', 'error', f'{type(err).__name__}: {err}')

    def _mix_set(self, stamp: int, values) -> None:
        """Lockstep: the command of stamp t_k from its complete input set."""
        t = self.time_base.seconds(stamp)
        self.monitor.yaw_torque(t, values['yaw_torque'])
        if 'drive_torque' in values:
            self.monitor.drive_torque(t, *values['drive_torque'])
        if self.estimates:
            usable = [s for s in self.estimates if s <= stamp]
            if usable:
                newest = max(usable)
                self.monitor.estimate(t, *self.estimates[newest])
                for s in usable:
                    del self.estimates[s]
        self._publish(stamp, self.monitor.update(t))

    def _publish(self, stamp: int, decision: SafetyDecision) -> None:
        start = time.perf_counter()
        self.torques_publisher.publish_value(stamp, decision, decision_to_msg)
        efforts = signed_efforts(*decision.command, self.left_sign, self.right_sign)
        # Serialized: no node of ours subscribes the effort topic, so the intra-process bus
        # never hands these bytes to a callback; DDS sends them as rclpy would the message.
        self.effort_publisher.publish(self.effort_command_cdr(*efforts))
        self.diagnostics.output(stamp, time.perf_counter() - start)
        self.zeroed_ticks += decision.zeroed
        if self.wiring_check is not None:
            tau_l, tau_r = decision.command
            self.wiring_check.torque(self.monitor_time(), tau_l + tau_r,
                                     decision.state in (ACTIVE, DEGRADED), tau_r - tau_l)
        previous = self.last_decision
        # The status text is made once per status (_status), with the limits of this tick.
        self.last_decision, self._decision_limits = decision, self.mixer
        changed = previous is None or previous.state != decision.state
        if changed:
            log = self.get_logger()
            text = f'safety state {decision.state}' + (f': {decision.reason}'
                                                       if decision.reason else '')
            # One call site per severity: rclpy refuses to change it between calls.
            if decision.state in (ACTIVE, SHADOW, STARTING):
                log.info(text)
            elif decision.state == DEGRADED:
                log.warning(text)
            else:
                log.error(text)
            wall = time.monotonic()
            if wall - self._diagnostics_sent_at >= _DIAGNOSTICS_ON_CHANGE_PERIOD:
                self._diagnostics_sent_at = wall
                self.diagnostics.publish()

    def _report(self, decision: SafetyDecision, limits: MixerParams) -> None:
        diag = self.diagnostics
        if decision.state == ACTIVE:
            limit = limits.max_wheel_torque
            clipped = max(abs(decision.tau_left), abs(decision.tau_right)) >= limit
            diag.state(OK, f'ACTIVE: wheel torque at the {limit:g} N m limit' if clipped
                       else 'ACTIVE: mixing within the limits')
        elif decision.state == DEGRADED:
            diag.state(WARN, f'DEGRADED: riding through: {decision.reason}')
        elif decision.state == SHADOW:
            diag.state(WARN, 'SHADOW: computing, commanding zero to the base (shadow_mode)')
        else:
            diag.state(_LEVEL[decision.state], f'{decision.state}: zero torque: '
                       f'{decision.reason}')

    def _status(self):
        """Return the node's DiagnosticStatus with the safety counters and input ages of now."""
        values = self.diagnostics.values
        if self.last_decision is not None:
            self._report(self.last_decision, self._decision_limits)
            values['safety state'] = self.last_decision.state
            values['safety reasons'] = self.last_decision.reason or 'none'
        for name, age in self.monitor.ages(self.monitor_time()).items():
            values[f'received {name} ago [s]'] = 'never' if age is None else f'{age:.4f}'
        values['ticks'] = str(self.monitor.ticks)
        if self.wiring_check is not None:
            values['wiring check'] = (self.monitor.wiring or
                                      'no contradiction: ' + self.wiring_check.summary())
        values['zeroed ticks'] = str(self.zeroed_ticks)
        if not self.lockstep and self.monitor.guard.config.enabled:
            guard = self.monitor.guard
            values['runaway guard'] = (
                self.monitor.runaway or f'wheel-propagated tracking error '
                f'{guard.wheel_error:.3f} m, largest growth {guard.largest_growth:.3f} m')
        if self.latencies:
            p50, p99, p100 = self.latencies.percentiles((50, 99, 100))
            values['sensor to command latency [ms] p50/p99/max'] = (
                f'{1e3 * p50:.3f}/{1e3 * p99:.3f}/{1e3 * p100:.3f} over '
                f'{len(self.latencies)} commands')
        return self._base_status()

    def send_stop_command(self) -> bool:
        """Real time: one zero effort command to the base, acknowledged; True if it was.

        A ros2_control JointGroupEffortController holds the last command forever, so a
        mixer that stops (Ctrl-C, ``ros2 run`` ended, SIGTERM from a supervisor) must not
        leave a torque behind. Lockstep drives a simulated plant on /wip/wheel_torques
        and has no base: nothing is sent (a run's command count stays one per tick).
        """
        if self.lockstep:
            return False
        self.effort_publisher.publish(effort_command(0.0, 0.0, self.joints, self.left_joint,
                                                     self.right_joint))
        acked = self.effort_publisher.wait_for_all_acked(Duration(seconds=STOP_ACK_TIMEOUT))
        self.get_logger().info('stopping: zero effort command sent' +
                               ('' if acked else ' (not acknowledged by every subscriber '
                                f'within {STOP_ACK_TIMEOUT} s)'))
        return acked


def main(args=None) -> int:
    """Entry point ``torque_mixer``: on SIGINT/SIGTERM a last zero command to the base."""
    return run_node(TorqueMixerNode, 'torque_mixer', args,
                    on_stop=TorqueMixerNode.send_stop_command)


if __name__ == '__main__':
    sys.exit(main())
