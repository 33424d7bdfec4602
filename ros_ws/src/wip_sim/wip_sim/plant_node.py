"""Plant node: the simulated WIP as sensor topics, ground truth and (in lockstep) the clock.

The node runs the in-process runner's simulation (``core.simulation.Simulation``: the true
plant, the disturbances, the sensors and the initial state), built from one scenario file.

Clock modes (parameter ``clock_mode``)
--------------------------------------
``lockstep`` (default; every other node runs with ``use_sim_time``)
    Control tick k, t_k = k / rates.control_rate, exactly as ``wip_sim/core/runner.py``:

    1. publish ``/clock`` = t_k, then the sensors sampled at t_k: ``/joint_states``,
       ``/imu/data`` and, every control_rate / gps_rate ticks, ``/gps/fix``, then
       ``/wip/ground_truth`` (state at t_k, disturbances at t_k, wheel torques applied over
       [t_{k-1}, t_k)); all stamped t_k;
    2. wait for ``/wip/wheel_torques`` stamped t_k (older stamps are ignored);
    3. integrate to t_{k+1}: ``rates.substeps`` RK4 steps (``Simulation.step``) with
       the torques held and the disturbances sampled at each step.

    The run ends like the runner's loop: at t_N = duration, or at the first t_k with
    |θ| >= ``fall_threshold``, the last ground truth sample is published (stamped t_k)
    and the node exits, with code 0 at the end of the scenario and 3 after a fall. No
    ``/clock`` and no sensors are published for that last sample: no control step follows
    it, so the controllers compute for t_0 ... t_{N-1} only, as in the runner. Message
    counts of a full run: ``/wip/ground_truth`` N + 1; ``/clock``, ``/joint_states``,
    ``/imu/data`` N; ``/gps/fix`` ceil(N / gps_every).
``realtime``
    A wall-clock timer at the control rate. Each tick integrates one control period with
    the latest wheel torques (zero if none arrived, or if the newest is older than
    ``max_torque_age``), then publishes the ground truth and the sensors stamped with the
    wall-clock time. The simulated time advances one control period per tick. No
    ``/clock``. With ``hold_until_engaged`` (default) the vehicle is held at its initial
    state until the controllers engage (the first wheel torques with ``zeroed`` false):
    the sensors of that state are published each tick, the time stays at t = 0. Without
    it the vehicle falls freely while the safety layer settles (0.3-0.5 s measured: long
    enough to drop the paper's initial tilt of 0.05 rad). With ``hold_at_end`` (set by
    ``scripts/run_graph``) the end of the scenario does not end the process: the last
    state's sensors go on, frozen, until SIGINT/SIGTERM (exit 0), so that the launcher
    stops the controllers while their inputs still come; a fall still ends it at once.

Start handshake
---------------
The plant publishes nothing until it is started: by the service ``~/start``
(std_srvs/Trigger, used by ``scripts/run_graph`` after it has checked the whole graph), or
by itself when ``autostart`` is true. Either way it starts only when its own endpoints are
matched: ``/wip/wheel_torques`` has a publisher, and each sensor topic, ``/wip/ground_truth``
and ``/clock`` have at least ``start.expected_sensor_subscribers``,
``start.expected_ground_truth_subscribers`` and ``start.expected_clock_subscribers``
matched subscriptions (DDS matching seen by the publisher, which is stricter than the
graph view: a message published before the match would be lost). The service answers
``success: false`` with the unmatched topics until then; it can simply be retried.

Parameters
----------
:class:`wip_sim.settings.PlantNodeParams` (docs/parameters.md), all read-only: the scenario
file (default: the paper's Section V), the clock mode (default lockstep: the plant is a
simulator; the controller nodes default to realtime, for a real base), the joint and frame
names, autostart and the start handshake's ``start.*``, the realtime holds and
``max_torque_age``, and ``stats_file`` (per-tick timings and CPU time, written at exit).
The GPS datum is the scenario's ``sensors.gps_datum_*``.

The in-process runner's time t_k = k * dt is used for the dynamics, the disturbances and
the sensors; the stamps carry round(t_k * 1e9) ns.

Exit codes: 0 end of the scenario (or SIGINT), 1 runtime error, 2 invalid parameters or
scenario, 3 the vehicle fell.
"""

from __future__ import annotations

import json
import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray
from rclpy.clock import Clock, ClockType
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import Imu, JointState, NavSatFix
from std_srvs.srv import Trigger
from wip_msgs.msg import GroundTruth, WheelTorques

from wip_control.core.model import THETA
from wip_sim.core.scenario import load_scenario
from wip_sim.core.simulation import Simulation
from wip_runtime.composition import IntraProcessNode
from wip_runtime.qos import LOCKSTEP_WRITER_DEPTH
from wip_runtime.stamps import stamp_to_ns
from wip_sim.simulator_main import run_simulator_node
from wip_control.nodes.conversions import body_rates_from_euler, wheel_torques_from_msg
from wip_runtime.rotations import quaternion_from_euler
from wip_runtime.intra_process import local_match_count
from wip_runtime.diagnostics import create_diagnostics_timer
from wip_runtime.parameters import RosParams
from wip_description.wiring import WheelJoints
from wip_runtime.cli import EXIT_FAILED, EXIT_INTERNAL, EXIT_OK, EXIT_USAGE

from .plant_report import diagnostic_status, format_timing, run_stats, TickTimer
from .sensor_messages import gps_message, imu_message, set_stamp, write_fix
from .settings import ALREADY_STARTED, PlantNodeParams, StartHandshake

# The tools' table (wip_runtime.cli): a fall is 1, a bad parameter 2, a simulation
# that failed (non-finite state) an internal error, 3.
EXIT_FELL, EXIT_CONFIG, EXIT_ERROR = EXIT_FAILED, EXIT_USAGE, EXIT_INTERNAL

SENSOR_DEPTH = 10  # keep-last depth of every publisher/subscription [messages]
SPIN_TIMEOUT = 0.1  # [s] of one spin_once: bounds the reaction time to a shutdown
DIAGNOSTICS_PERIOD = 1.0  # [s], wall time
AUTOSTART_PERIOD = 0.05  # [s], wall time: how often autostart checks the matches


class PlantNode(IntraProcessNode):
    """The simulator; see the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('plant', **kwargs)
        # Composed with the controllers (ros2 run wip_sim simulation), the sensors and the
        # wheel torques skip DDS while no one outside subscribes; alone, plain rclpy.
        self.init_intra_process(True)
        self.exit_code: int | None = None  # set when the run is over
        settings = RosParams(self, '', PlantNodeParams).config
        self.clock_mode = settings.clock_mode
        self.scenario = scenario = load_scenario(settings.scenario_file or None)
        joints = RosParams(self, '', WheelJoints).config
        self.left_joint, self.right_joint = joints.left_joint, joints.right_joint
        sensors = scenario.sensors
        # The datum is the scenario's (sensors.gps_datum_*): one source, no datum.* here.
        self.datum = (sensors.gps_datum_latitude, sensors.gps_datum_longitude,
                      sensors.gps_datum_altitude)
        start = RosParams(self, 'start', StartHandshake).config
        self.expected = {'sensors': start.expected_sensor_subscribers,
                         'ground_truth': start.expected_ground_truth_subscribers,
                         'clock': start.expected_clock_subscribers}
        self.max_torque_age = settings.max_torque_age
        #: realtime: held at the initial state until the controllers engage
        self.held = self.clock_mode != 'lockstep' and settings.hold_until_engaged
        self.held_ticks = 0
        #: realtime: the scenario's end was reached and the last sensors are held until
        #: the stop (hold_at_end); the exit status it will be.
        self.hold_at_end = self.clock_mode != 'lockstep' and settings.hold_at_end
        self.ended = False
        self.final_exit_code: int | None = None
        self.stats_file = settings.stats_file
        self.sim = Simulation(scenario)
        self.dt_control, self.n_ticks = self.sim.dt_control, self.sim.n_ticks
        self.k = 0
        self.unacknowledged_topics: list[str] = []
        self.tau = (0.0, 0.0)  # applied over the previous control period [N m]
        self.started = False
        self._create_interfaces(settings)
        self._init_statistics()
        self.get_logger().info(
            f'scenario {scenario.name!r}: {scenario.duration:g} s, {self.n_ticks} ticks of '
            f'{self.dt_control * 1e3:g} ms, plant model {scenario.plant.model.model!r}, '
            f'clock {self.clock_mode}; waiting for '
            f'{"the start conditions" if settings.autostart else "~/start"}')

    @property
    def state(self) -> tuple:
        """The true state now (layout of ``core.model``)."""
        return self.sim.state

    def _create_interfaces(self, settings: PlantNodeParams) -> None:
        """Create the publishers, the torque subscription, the start service, timers."""
        # Reliable, keep last 10 (the graph design). Publishers offer transient-local
        # durability: compatible with volatile subscriptions, and a subscription that asks
        # for transient-local gets the samples published before it matched.
        # Lockstep: a deep writer history, so that a reader that lags loses nothing
        # (wip_runtime.qos.LOCKSTEP_WRITER_DEPTH).
        qos = QoSProfile(depth=(LOCKSTEP_WRITER_DEPTH if self.clock_mode == 'lockstep'
                                else SENSOR_DEPTH),
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        # Volatile: matches any publisher (a transient-local request would not match a
        # volatile publisher).
        torque_qos = QoSProfile(depth=SENSOR_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        # /clock: reliable publisher (compatible with rclpy's best-effort time source and
        # with a reliable recorder).
        self.clock_pub = (self.create_publisher(ClockMsg, '/clock', qos)
                          if self.clock_mode == 'lockstep' else None)
        self.joint_pub = self.create_publisher(JointState, 'joint_states', qos)
        self.imu_pub = self.create_publisher(Imu, 'imu/data', qos)
        self.gps_pub = self.create_publisher(NavSatFix, 'gps/fix', qos)
        self.truth_pub = self.create_publisher(GroundTruth, 'wip/ground_truth', qos)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        callback = (self._on_torques_lockstep if self.clock_mode == 'lockstep'
                    else self._on_torques_realtime)
        self.torque_sub = self.create_subscription(WheelTorques, 'wip/wheel_torques',
                                                   callback, torque_qos)
        self.add_intra_subscription(WheelTorques, self.torque_sub, callback)
        self.start_srv = self.create_service(Trigger, '~/start', self._on_start)
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        create_diagnostics_timer(self, self.publish_diagnostics, DIAGNOSTICS_PERIOD,
                                 starting=lambda: not self.started)
        self.autostart_timer = (self.create_timer(AUTOSTART_PERIOD, self._autostart,
                                                  clock=wall) if settings.autostart else None)
        self.realtime_timer = None
        self.latest_torques: tuple[float, float, int] | None = None  # left, right, stamp
        # Preallocated messages (fields are overwritten each tick). Also safe when
        # composed, where the controllers receive these very objects: the eso converts
        # each at once, and the next tick's overwrite comes only after the torques of this
        # one, which the intra-process queue (FIFO) delivers after them.
        self._clock_msg = ClockMsg()
        self._truth_msg = GroundTruth()
        self._truth_msg.header.frame_id = settings.map_frame
        self._joint_msg = JointState()
        self._joint_msg.name = [self.left_joint, self.right_joint]
        self._imu_msg = imu_message(self.scenario.sensors, settings.imu_frame,
                                    acceleration=False)
        self._gps_msg = gps_message(self.scenario.sensors, settings.gps_frame)

    def _init_statistics(self) -> None:
        """Per-tick timings and counters (``stats``)."""
        self.wall_start: float | None = None  # perf_counter at the start [s]
        self.wall_end: float | None = None  # perf_counter at the end [s]
        self.cpu_start: float | None = None  # process_time at the start [s]
        self.cpu_end: float | None = None  # process_time at the end [s]
        self.publish_time = TickTimer()  # publishing one sample [s]
        self.wait_time = TickTimer()  # sample published -> torques of that tick received
        self.step_time = TickTimer()  # the plant's step [s]
        self.loop_time = TickTimer()  # /clock published -> torques of that tick received
        self.published_at = 0.0
        self._tick_started_at = 0.0
        self.stale_torques = 0  # lockstep: torque messages with an unexpected stamp
        self.zeroed_torques = 0  # realtime: ticks run with zero torques (none or stale)
        self.zeroed_torques_before_first = 0  # ... of them before the first torques arrived
        self.end_reason = ''

    # -- start --------------------------------------------------------------------------------
    def unmatched(self) -> list[str]:
        """Return what the start still waits for (empty when every endpoint is matched)."""
        missing = []
        if (self.torque_sub.get_publisher_count()
                + local_match_count(self, 'publishers', self.torque_sub.topic_name)) < 1:
            missing.append(f'{self.torque_sub.topic_name} has no publisher')
        checks = [(self.joint_pub, self.expected['sensors']),
                  (self.imu_pub, self.expected['sensors']),
                  (self.gps_pub, self.expected['sensors']),
                  (self.truth_pub, self.expected['ground_truth'])]
        if self.clock_pub is not None:
            checks.append((self.clock_pub, self.expected['clock']))
        for publisher, wanted in checks:
            have = publisher.get_subscription_count()
            if have < wanted:
                missing.append(f'{publisher.topic_name}: {have}/{wanted} subscriptions')
        return missing

    def _on_start(self, request, response):
        if self.started:
            response.success = False
            response.message = ALREADY_STARTED
            return response
        missing = self.unmatched()
        if missing:
            response.success = False
            response.message = 'not connected: ' + '; '.join(missing)
            return response
        self.start()
        response.success = True
        response.message = f'started at t = {self.k * self.dt_control:g} s'
        return response

    def _autostart(self) -> None:
        if not self.started and not self.unmatched():
            self.start()

    def start(self) -> None:
        """Publish the sample of t_0 and begin stepping."""
        if self.started:
            return
        self.started = True
        if self.autostart_timer is not None:
            self.autostart_timer.cancel()
        self.wall_start = time.perf_counter()
        self.cpu_start = time.process_time()
        self.get_logger().info('started')
        if self.clock_mode == 'lockstep':
            self._publish_tick()
        else:
            self._publish_tick()
            self.realtime_timer = self.create_timer(self.dt_control, self._realtime_tick)

    # -- one tick -------------------------------------------------------------------------
    def _publish_tick(self) -> None:
        """Publish the sample of tick self.k; finish the run at its end or after a fall."""
        started_at = time.perf_counter()
        k = self.k
        t = k * self.dt_control  # exactly the runner's time
        if self.clock_mode == 'lockstep':
            stamp_ns = int(round(t * 1e9))
        else:
            stamp_ns = self.get_clock().now().nanoseconds
        state = self.state
        d1, d2, d3 = self.sim.disturbance(k)
        fell = self.sim.fallen()
        last = fell or k >= self.n_ticks
        if last:
            # No control step follows the last sample: no /clock, no sensors.
            self._publish_truth(stamp_ns, state, d1, d2, d3)
            self._finish(fell, t)
            return
        set_stamp(self._clock_msg.clock, stamp_ns)
        if self.clock_pub is not None:
            self.clock_pub.publish(self._clock_msg)
        self._publish_sensors(stamp_ns, k, state)
        # The controllers are at work now: the ground truth (for recorders only) last.
        self._publish_truth(stamp_ns, state, d1, d2, d3)
        self.published_at = now = time.perf_counter()
        self._tick_started_at = started_at
        self.publish_time.add(now - started_at)

    def _publish_truth(self, stamp_ns, state, d1, d2, d3) -> None:
        msg = self._truth_msg
        set_stamp(msg.header.stamp, stamp_ns)
        (msg.x, msg.y, msg.phi, msg.x_v, msg.theta, msg.omega, msg.v,
         msg.theta_dot) = state
        msg.tau_d1, msg.tau_d2, msg.tau_d3 = d1, d2, d3
        msg.tau_left, msg.tau_right = self.tau
        self.truth_pub.publish(msg)

    def _publish_sensors(self, stamp_ns, k, state) -> None:
        # Delays (sensors.sensor_delay, gps_latency), noise: the runner's readings.
        reading = self.sim.read_sensors(k, state)
        joint = self._joint_msg
        set_stamp(joint.header.stamp, stamp_ns)
        joint.position = list(reading.encoders)
        joint.velocity = list(reading.wheel_rates)
        joint.effort = list(self.tau)
        self.joint_pub.publish(joint)

        imu = self._imu_msg
        set_stamp(imu.header.stamp, stamp_ns)
        pitch, yaw = reading.imu
        q = imu.orientation
        q.x, q.y, q.z, q.w = quaternion_from_euler(0.0, pitch, yaw)
        # A gyro measures the body's angular velocity, (−ϕ̇ sin θ, θ̇, ϕ̇ cos θ) in
        # base_link; it is written at the published pitch so that the eso node's inverse
        # (conversions.euler_rates_from_body) returns the runner's (θ̇, ϕ̇) to rounding.
        (imu.angular_velocity.x, imu.angular_velocity.y,
         imu.angular_velocity.z) = body_rates_from_euler(pitch, *reading.imu_rates)
        self.imu_pub.publish(imu)

        if reading.gps_due:
            fix = self._gps_msg
            set_stamp(fix.header.stamp, stamp_ns)
            write_fix(fix, reading.gps, self.datum)
            self.gps_pub.publish(fix)

    def _step(self, tau_left: float, tau_right: float) -> None:
        """Integrate [t_k, t_{k+1}] with the torques held (the runner's step 8)."""
        started_at = time.perf_counter()
        self.tau = (tau_left, tau_right)
        self.sim.step(self.k, tau_left, tau_right)
        self.k += 1
        self.step_time.add(time.perf_counter() - started_at)

    def _on_torques_lockstep(self, msg: WheelTorques) -> None:
        if not self.started or self.exit_code is not None:
            return
        received_at = time.perf_counter()
        expected_ns = int(round(self.k * self.dt_control * 1e9))
        stamp_ns = stamp_to_ns(msg.header.stamp)
        if stamp_ns != expected_ns:
            # An older command (e.g. a repeated one); the plant waits for t_k's.
            self.stale_torques += 1
            if stamp_ns > expected_ns:
                self.get_logger().error(
                    f'wheel torques stamped {stamp_ns * 1e-9:.9f} s, ahead of the plant '
                    f'at {expected_ns * 1e-9:.9f} s: is another plant running?')
            return
        self.wait_time.add(received_at - self.published_at)
        self.loop_time.add(received_at - self._tick_started_at)
        try:
            left, right = wheel_torques_from_msg(msg)  # ValueError if not finite
            self._step(left, right)
            self._publish_tick()
        except ValueError as err:
            self.get_logger().error(f'simulation failed at t = '
                                    f'{self.k * self.dt_control:.3f} s: {err}')
            self.end_reason = str(err)
            self.exit_code = EXIT_ERROR

    @property
    def held_s(self) -> float:
        """Wall time [s] the vehicle was held at its initial state (hold_until_engaged)."""
        return self.held_ticks * self.dt_control

    def _on_torques_realtime(self, msg: WheelTorques) -> None:
        self.latest_torques = (float(msg.left), float(msg.right),
                               stamp_to_ns(msg.header.stamp))
        if self.held and self.started and not msg.zeroed:
            self.held = False
            self.wall_start = time.perf_counter()  # the real-time factor counts from here
            self.get_logger().info(f'the controllers engaged: released after '
                                   f'{self.held_s:.2f} s held')

    def _realtime_tick(self) -> None:
        if self.exit_code is not None:
            return
        if self.ended:
            # hold_at_end: the last state's sensors, frozen, until the stop (no truth: the
            # run ended at its last sample).
            self._publish_sensors(self.get_clock().now().nanoseconds, self.k, self.state)
            return
        if self.held:
            # The initial state, measured each tick; no step, the time stays at t = 0.
            self.held_ticks += 1
            stamp_ns = self.get_clock().now().nanoseconds
            self._publish_sensors(stamp_ns, self.held_ticks, self.state)
            self._publish_truth(stamp_ns, self.state, *self.sim.disturbance(0))
            return
        left = right = 0.0
        latest = self.latest_torques
        now_ns = self.get_clock().now().nanoseconds
        if (latest is not None and now_ns - latest[2] <= self.max_torque_age * 1e9
                and math.isfinite(latest[0]) and math.isfinite(latest[1])):
            left, right = latest[0], latest[1]
        else:
            self.zeroed_torques += 1
            if latest is None:
                self.zeroed_torques_before_first += 1
        try:
            self._step(left, right)
            self._publish_tick()
        except ValueError as err:
            self.get_logger().error(f'simulation failed: {err}')
            self.end_reason = str(err)
            self.exit_code = EXIT_ERROR

    def _finish(self, fell: bool, t: float) -> None:
        hold = self.hold_at_end and not fell
        if self.realtime_timer is not None and not hold:
            self.realtime_timer.cancel()
        self.wall_end = time.perf_counter()
        self.cpu_end = time.process_time()
        wall = self.wall_end - (self.wall_start or self.wall_end)
        factor = t / wall if wall > 0 else float('inf')
        if fell:
            self.end_reason = (f'fell at t = {t:.3f} s: |theta| = {abs(self.state[THETA]):.3f} '
                               f'rad >= fall_threshold {self.sim.fall_threshold:g} rad')
            self.get_logger().error(self.end_reason)
            self.exit_code = EXIT_FELL
        else:
            self.end_reason = f'end of the scenario at t = {t:g} s'
            if hold:
                # The launcher sees it on /diagnostics, stops the controllers, then this.
                self.ended, self.final_exit_code = True, EXIT_OK
                self.end_reason += ' (sensors held until the stop)'
            else:
                self.exit_code = EXIT_OK
        self.get_logger().info(
            f'{self.end_reason}; {self.k} control ticks in {wall:.2f} s wall '
            f'({factor:.1f}x real time); per tick: publish '
            f'{format_timing(self.publish_time.summary())}, '
            f'step {format_timing(self.step_time.summary())}, '
            f'wait for torques {format_timing(self.wait_time.summary())}')
        if hold:
            self.publish_diagnostics()   # the launcher waits for it

    # -- reporting ------------------------------------------------------------------------
    def stats(self) -> dict:
        """Return the timings and counters of the run so far (also in ``stats_file``)."""
        return run_stats(self)

    def write_stats(self) -> None:
        if self.stats_file:
            with open(self.stats_file, 'w', encoding='utf-8') as stream:
                json.dump(self.stats(), stream, indent=2)
                stream.write('\n')

    def wall_elapsed(self) -> float:
        if self.wall_start is None:
            return 0.0
        return (self.wall_end or time.perf_counter()) - self.wall_start

    def publish_diagnostics(self) -> None:
        """/diagnostics, once per second of wall time (every 0.1 s until the start)."""
        array = DiagnosticArray(status=[diagnostic_status(self)])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)


def main(args=None) -> int:
    """Entry point ``plant`` (``ros2 run wip_sim plant --ros-args -p scenario_file:=...``)."""
    # At the end of the scenario: rmw_fastrtps publishes synchronously (the default since
    # Humble), so the last samples are handed to the transport before publish() returns
    # and exiting right after the final /diagnostics loses nothing.
    return run_simulator_node(PlantNode, 'plant', args, config_status=EXIT_CONFIG,
                              on_end=PlantNode.publish_diagnostics)


if __name__ == '__main__':
    sys.exit(main())
