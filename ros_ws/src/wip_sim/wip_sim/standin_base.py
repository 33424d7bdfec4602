"""Stand-in base: a simulated two-wheeled base that speaks only ros2_control-style topics.

A test fixture and a tool: the controllers in hardware mode (``scripts/run_graph --mode
hardware``) run against it exactly as against a real base, and ``scripts/check_base`` can
be tried on it. It is its own process with its own simulation: the core
:class:`~wip_sim.core.plant.Plant` of the scenario (model and true parameters, RK4 at
``rates.plant_rate``), its disturbances and sensor noise, stepped on a wall-clock timer at
``rates.control_rate`` (the sensor rate of the base). It knows nothing of the project's
own topics.

Topics (the usual names of a ros2_control base; remap them with ``-r``)
-------------------------------------------------------------------------
Sensors are published best effort (sensor-data QoS), the command is subscribed reliable.

Publishes
    ``/joint_states`` (sensor_msgs/JointState): the wheel joints in the order of ``joints``,
    position [rad] and velocity [rad/s] in each JOINT's own sign convention
    (``left_wheel_sign``, ``right_wheel_sign``: −1 for a joint whose positive direction
    rolls the robot backwards), effort [N m] = the torque the motor applied over the
    period that ended at the sample (the command held, after the scenario's
    ``plant.motor_time_constant``), as a motor driver's effort state reports it;
    ``/imu/data`` (sensor_msgs/Imu, frame ``imu_frame``): the orientation of the IMU frame
    in ENU (REP 145), q_imu = q_body ⊗ q_mount with q_mount from ``imu_mounting_rpy``
    (the same convention as the eso node's parameter, see
    ``wip_control.nodes.hardware_inputs``); angular velocity [rad/s] in the IMU frame;
    linear acceleration [m/s²]: the reaction to gravity only, in the IMU frame (the
    body's own acceleration is left out: enough for a mounting check at rest);
    ``/gps/fix`` (sensor_msgs/NavSatFix) every control_rate / ``sensors.gps_rate`` ticks,
    about the datum ``datum.*``;
    ``/odom`` (nav_msgs/Odometry, frame ``odom_frame``) when ``publish_odometry`` is true:
    the true planar pose and speeds (the map frame of the simulation);
    ``/diagnostics`` at 1 Hz (10 Hz until the first command releases it).
Subscribes
    ``/effort_controller/commands`` (std_msgs/Float64MultiArray): one effort [N m] per joint
    of ``joints``, in that order, like ``effort_controllers/JointGroupEffortController``.
    Like that controller it has NO command timeout: the last valid command is held
    forever (that is what the mixer's safety layer is for). A command of the wrong size
    or with a non-finite value is rejected (counted and logged) and the previous one
    stays.

Held until engaged
------------------
A balancing robot cannot stand by itself before its controller runs: someone holds it.
With ``hold_until_engaged`` (default true) the simulation is frozen at the scenario's
initial state (still publishing its sensors) until the first command with a non-zero
effort arrives — the hand lets go when the controller engages. Its time t = 0 is that
moment. After a fall (|θ| >= the scenario's ``fall_threshold``) the body lies still
(the state is frozen), the node logs an error, keeps publishing and recording the
commands it receives for ``exit_after_fall`` seconds, then exits with code 1
(the tools' table: the vehicle fell).

Parameters (read-only)
----------------------
scenario_file ('' = the paper's Section V: plant, initial state about the reference at
t = 0, disturbances, sensors, rates, fall threshold), joints, left_joint, right_joint,
left_wheel_sign, right_wheel_sign, imu_mounting_rpy [rad], imu_frame, gps_frame,
odom_frame, publish_odometry, datum.latitude/longitude/altitude (default the scenario's),
hold_until_engaged, exit_after_fall [s], duration [s] (0: until SIGINT; counted from the
release), expected_command_period [s] (default 1/rates.control_rate: the period of the
controllers' mixer, for the deadline statistics), truth_period [s] (sampling of the
ground truth in the stats file), stats_file (JSON written at exit; '' = none),
position_fault.kind/start/duration/offset (a jump or a freeze of /gps/fix and /odom, for
the tests of the position checks).

Statistics (``stats_file``): ticks and their wall-clock periods (``stalls``: the ticks
that came more than 4 periods late, with the simulated time), commands received and
rejected, the gaps between commands, the age of the held command at each tick
(``command_age``; a *deadline miss* is a tick whose newest command is older than 1.5
``expected_command_period``: the mixer missed at least one of its ticks), the release
time, the fall, the commands received after the fall, and the ground truth (t, x, y, ϕ,
θ, υ) every ``truth_period``.

Exit codes: 0 (SIGINT or ``duration`` reached), 1 runtime error, 2 invalid parameters,
3 the robot fell.
"""

from __future__ import annotations

import json
import math
import sys
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Imu, JointState, NavSatFix
from std_msgs.msg import Float64MultiArray

from wip_control.core.model import OMEGA, PHI, THETA, V, X, Y
from wip_sim.core.scenario import load_scenario
from wip_sim.core.simulation import Simulation
from wip_sim.simulator_main import run_simulator_node
from wip_runtime.rotations import quaternion_from_euler
from wip_runtime.diagnostics import create_diagnostics_timer
from wip_control.nodes.effort_interface import declare_effort_interface
from wip_runtime.parameters import RosParams
from wip_description.wiring import DatumParams, ImuMounting
from wip_runtime.cli import EXIT_FAILED, EXIT_INTERNAL, EXIT_OK, EXIT_USAGE

from .base_conventions import BaseConventions
from .sensor_messages import gps_message, imu_message, write_fix
from .settings import CommandTiming, PositionFault, StandinParams

# The tools' table (wip_runtime.cli): a fall is 1, a bad parameter 2, a simulation
# that failed (non-finite state) an internal error, 3.
EXIT_FELL, EXIT_CONFIG, EXIT_ERROR = EXIT_FAILED, EXIT_USAGE, EXIT_INTERNAL
SPIN_TIMEOUT = 0.1  # [s]
DIAGNOSTICS_PERIOD = 1.0  # [s] wall
#: A tick whose newest command is older than this many command periods is a deadline miss.
DEADLINE_FACTOR = 1.5
#: A tick that comes this many periods after the previous one is a stall of the base
#: process itself (its physics pause with it: the simulation advances one period a tick).
STALL_FACTOR = 4.0
#: Most plant steps one late tick may catch up (0.5 s at 200 Hz; see ``_steps_due``).
MAX_CATCH_UP_STEPS = 100


def percentiles(values: list[float]) -> dict[str, float | int | None]:
    """count, mean, p50, p99, max of ``values`` (seconds -> milliseconds)."""
    ordered = sorted(values)
    n = len(ordered)
    if n == 0:
        return {'count': 0, 'mean_ms': None, 'p50_ms': None, 'p99_ms': None, 'max_ms': None}
    return {'count': n, 'mean_ms': 1e3 * math.fsum(ordered) / n,
            'p50_ms': 1e3 * ordered[n // 2],
            'p99_ms': 1e3 * ordered[min(n - 1, int(0.99 * n))], 'max_ms': 1e3 * ordered[-1]}


class StandinBase(Node):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('standin_base', **kwargs)
        self.exit_code: int | None = None
        settings = RosParams(self, '', StandinParams).config
        self.scenario = scenario = load_scenario(settings.scenario_file or None)
        wheels = declare_effort_interface(self)
        self.left_joint, self.right_joint = wheels.left_joint, wheels.right_joint
        self.joints = list(wheels.joints)
        self.left_sign, self.right_sign = wheels.left_sign, wheels.right_sign
        self.mounting = RosParams(self, '', ImuMounting).config.imu_mounting_rpy
        self.publish_odometry = settings.publish_odometry
        # The datum defaults to the scenario's (sensors.gps_datum_*).
        datum = RosParams(self, 'datum', DatumParams,
                                 defaults=DatumParams.of(scenario.sensors)).config
        self.datum = (datum.latitude, datum.longitude, datum.altitude)
        self.position_fault = RosParams(self, 'position_fault', PositionFault).config
        self._frozen_position: tuple[float, float] | None = None
        self.hold = settings.hold_until_engaged
        self.exit_after_fall = settings.exit_after_fall
        self.duration = settings.duration
        self.command_period = RosParams(
            self, '', CommandTiming,
            defaults=CommandTiming(scenario.control_period)).config.expected_command_period
        self.truth_period = settings.truth_period
        self.stats_file = settings.stats_file
        self.sensor_bunch = settings.sensor_bunch
        self._bunch: list[tuple[bytes, bytes]] = []
        self.sim = Simulation(scenario)
        self.dt = self.sim.dt_control
        self.gravity = scenario.plant.parameters.gravity
        self.index = {name: i for i, name in enumerate(self.joints)}
        self.sign = {self.left_joint: self.left_sign, self.right_joint: self.right_sign}
        self.conventions = BaseConventions(self.joints, self.left_joint, self.right_joint,
                                           self.left_sign, self.right_sign, self.mounting)
        self._init_run_state()
        self._create_interfaces(settings)
        self.get_logger().info(
            f'stand-in base: scenario {scenario.name!r}, plant model '
            f'{scenario.plant.model.model!r}, {1.0 / self.dt:g} Hz, joints {self.joints}, '
            f'signs (left {self.left_sign:+g}, right {self.right_sign:+g}), IMU mounting '
            f'{list(self.mounting)} rad; '
            + ('held until the first non-zero command' if self.hold else 'free from t = 0'))

    @property
    def state(self) -> tuple:
        """The true state now (layout of ``core.model``)."""
        return self.sim.state

    def _init_run_state(self) -> None:
        self.k = 0                      # ticks published
        self.steps = 0                  # plant steps (control periods) since the release
        self.t = 0.0                    # simulated time since the release [s]
        self.released = not self.hold
        self.release_wall: float | None = None if self.hold else 0.0
        #: time.monotonic() of the release (CLOCK_MONOTONIC: comparable across processes)
        self.release_monotonic: float | None = None if self.hold else time.monotonic()
        self.ticks_at_release = 0       # ticks published before the release
        #: perf_counter time of the plant's t = 0 (set at the first step after the release).
        self._physics_origin: float | None = None
        self.fell = False
        self.fall_time: float | None = None
        self.fall_wall: float | None = None
        self.efforts = [0.0] * len(self.joints)   # the held command (joint order)
        self.tau = (0.0, 0.0)                     # (τl, τr) applied, REP 103 [N m]
        self.last_command_at: float | None = None
        self.start_wall = time.perf_counter()
        self.tick_walls: list[float] = []
        self.stalls: list[dict[str, float]] = []
        self.publish_times: list[float] = []
        self.command_gaps: list[float] = []
        self.command_ages: list[float] = []
        self.commands = 0
        self.rejected = 0
        self.reject_reasons: dict[str, int] = {}
        self.nonzero_after_fall = 0
        self.commands_after_fall = 0
        self.truth: dict[str, list[float]] = {k: [] for k in ('t', 'x', 'y', 'phi', 'theta',
                                                                'v', 'tau_left', 'tau_right')}
        self._next_truth = 0.0
        self.end_reason = ''

    def _create_interfaces(self, settings: StandinParams) -> None:
        # Sensors: best effort, like drivers with sensor-data QoS (a reliable publisher can
        # block in publish() for 0.33 s while a new subscriber matches: measured here);
        # the command: reliable, like JointGroupEffortController's subscription.
        sensor_qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT)
        qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
        self.joint_pub = self.create_publisher(JointState, 'joint_states', sensor_qos)
        self.imu_pub = self.create_publisher(Imu, 'imu/data', sensor_qos)
        self.gps_pub = self.create_publisher(NavSatFix, 'gps/fix', sensor_qos)
        self.odom_pub = (self.create_publisher(Odometry, 'odom', sensor_qos)
                         if self.publish_odometry else None)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_subscription(Float64MultiArray, 'effort_controller/commands',
                                 self._on_command, qos)
        self.create_timer(self.dt, self._tick)
        create_diagnostics_timer(self, self._publish_diagnostics, DIAGNOSTICS_PERIOD,
                                 starting=lambda: not self.released)
        self._joint_msg = JointState()
        self._imu_msg = imu_message(self.scenario.sensors, settings.imu_frame,
                                    acceleration=True)
        self._gps_msg = gps_message(self.scenario.sensors, settings.gps_frame)
        self._odom_msg = Odometry()
        self._odom_msg.header.frame_id = settings.odom_frame
        self._odom_msg.child_frame_id = 'base_link'

    # -- commands -------------------------------------------------------------------------
    def _reject(self, reason: str) -> None:
        self.rejected += 1
        self.reject_reasons[reason] = self.reject_reasons.get(reason, 0) + 1
        if self.reject_reasons[reason] <= 3:
            self.get_logger().error(f'command rejected ({reason}); holding the previous one')

    def _on_command(self, msg: Float64MultiArray) -> None:
        now = time.perf_counter()
        data = list(msg.data)
        if len(data) != len(self.joints):
            self._reject(f'{len(data)} values for {len(self.joints)} joints')
            return
        if not all(math.isfinite(v) for v in data):
            self._reject('non-finite value')
            return
        if self.last_command_at is not None:
            self.command_gaps.append(now - self.last_command_at)
        self.last_command_at = now
        self.commands += 1
        self.efforts = data
        if self.fell:
            self.commands_after_fall += 1
            self.nonzero_after_fall += any(v != 0.0 for v in data)
        if not self.released and any(v != 0.0 for v in data):
            self.released = True
            self.release_wall = now - self.start_wall
            self.release_monotonic = time.monotonic()
            self.ticks_at_release = self.k
            self.get_logger().info(f'first non-zero command {data}: released at '
                                   f'{self.release_wall:.3f} s')

    def wheel_torques(self) -> tuple[float, float]:
        """(τl, τr) [N m], REP 103, of the held joint efforts."""
        left = self.sign[self.left_joint] * self.efforts[self.index[self.left_joint]]
        right = self.sign[self.right_joint] * self.efforts[self.index[self.right_joint]]
        return left, right

    # -- one tick ---------------------------------------------------------------------------
    def _tick(self) -> None:
        if self.exit_code is not None:
            return
        now = time.perf_counter()
        if self.tick_walls and now - self.tick_walls[-1] > STALL_FACTOR * self.dt:
            self.stalls.append({'t': round(self.t, 4),
                                'wall_gap_s': round(now - self.tick_walls[-1], 4)})
        self.tick_walls.append(now)
        if self.last_command_at is not None and self.released and not self.fell:
            self.command_ages.append(now - self.last_command_at)
        try:
            if self.released and not self.fell:
                self.tau = self.wheel_torques()
                for _ in range(self._steps_due(now)):
                    self.sim.step(self.steps, *self.tau)
                    self.steps += 1
                    self.t = self.steps * self.dt
                    self._log_truth()
                    if self.sim.fallen():
                        self.fell = True
                        self.fall_time, self.fall_wall = self.t, now
                        self.end_reason = (f'fell at t = {self.t:.3f} s after the release: '
                                           f'|theta| {abs(self.state[THETA]):.3f} rad >= '
                                           f'{self.sim.fall_threshold:g} rad')
                        self.get_logger().error(self.end_reason)
                        break
            publish_start = time.perf_counter()
            self._publish(self._sample_stamp_ns(self.get_clock().now().nanoseconds,
                                                publish_start))
            self.publish_times.append(time.perf_counter() - publish_start)
            self.k += 1
        except ValueError as err:
            self.end_reason = f'simulation failed: {err}'
            self.get_logger().error(self.end_reason)
            self.exit_code = EXIT_ERROR
            return
        if self.fell and now - self.fall_wall >= self.exit_after_fall:
            self.exit_code = EXIT_FELL
        elif self.duration > 0.0 and self.released and self.t >= self.duration - 1e-9:
            self.end_reason = f'duration {self.duration:g} s reached'
            self.get_logger().info(self.end_reason)
            self.exit_code = EXIT_OK

    def _steps_due(self, now: float) -> int:
        """Plant steps for this tick: the physics follows the wall clock.

        A real robot keeps moving while its driver stalls; the samples are stamped with the
        wall clock. Were the stand-in to advance one step per tick whatever the gap, a
        30 ms stall of its process would publish 5 ms of motion over a 30 ms stamp gap:
        to the controllers, the robot would seem to have nearly stopped (seen: υ̂ 0.53 →
        0.06 m/s, a full Δτ step of the MPC, a fall). So a late tick catches up on the
        steps it missed (the held torque applied, as a ros2_control effort controller
        holds its last command), at most MAX_CATCH_UP_STEPS.
        """
        if self._physics_origin is None:
            self._physics_origin = now - self.t
        # One step per tick on time (a tick up to 0.9 period late included: timer jitter
        # is not a stall, and the plant never runs ahead of the wall clock).
        due = math.floor((now - self._physics_origin - self.t) / self.dt + 1.1)
        if due > MAX_CATCH_UP_STEPS:   # the rest is lost: the stamps stay on the wall clock
            self._physics_origin += (due - MAX_CATCH_UP_STEPS) * self.dt
        return min(MAX_CATCH_UP_STEPS, max(1, due))

    def _sample_stamp_ns(self, now_ns: int, now: float) -> int:
        """Return the stamp of the sample published now: the instant it was read.

        ``now_ns`` is the ROS clock and ``now`` perf_counter at the same moment. As a real
        driver stamps the time it read a sample, on its loop's grid: the state just
        stepped to, ``t``, is the tick's reading at ``origin + t − dt`` (its step takes the
        held command from then on), published by a late tick after that. The tick's own
        time would put the timer's jitter into the stamps but not into the uniform steps
        (docs/identification.md §7). An early tick stamps its own time (never the future).
        """
        if self._physics_origin is None:
            return now_ns
        lag = now - (self._physics_origin + self.t - self.dt)
        return now_ns - max(0, round(lag * 1e9))

    def _log_truth(self) -> None:
        if self.t + 1e-9 < self._next_truth:
            return
        self._next_truth += self.truth_period
        s = self.state
        for key, value in (('t', self.t), ('x', s[X]), ('y', s[Y]), ('phi', s[PHI]),
                           ('theta', s[THETA]), ('v', s[V]), ('tau_left', self.tau[0]),
                           ('tau_right', self.tau[1])):
            self.truth[key].append(value)

    def _publish(self, stamp_ns: int) -> None:
        state = self.state
        sec, nanosec = divmod(stamp_ns, 1_000_000_000)
        # Delays, noise and bias: the runner's readings of this tick.
        reading = self.sim.read_sensors(self.k)
        joint, imu = self._joint_msg, self._imu_msg
        applied = self.sim.last_torques if self.steps else self.tau
        self.conventions.fill(joint, imu, reading.encoders, reading.wheel_rates, applied,
                              *reading.imu, *reading.imu_rates, self.gravity)
        joint.header.stamp.sec, joint.header.stamp.nanosec = sec, nanosec
        imu.header.stamp.sec, imu.header.stamp.nanosec = sec, nanosec
        if self.sensor_bunch == 1:
            self.joint_pub.publish(joint)
            self.imu_pub.publish(imu)
        else:
            # The messages are reused objects: keep this sample's bytes for the bunch.
            self._bunch.append((serialize_message(joint), serialize_message(imu)))
            if len(self._bunch) >= self.sensor_bunch:
                for joint_bytes, imu_bytes in self._bunch:
                    self.joint_pub.publish(joint_bytes)
                    self.imu_pub.publish(imu_bytes)
                self._bunch.clear()

        if reading.gps_due:
            fix = self._gps_msg
            fix.header.stamp.sec, fix.header.stamp.nanosec = sec, nanosec
            write_fix(fix, self._faulty(reading.gps), self.datum)
            self.gps_pub.publish(fix)
        if self.odom_pub is not None:
            odom = self._odom_msg
            odom.header.stamp.sec, odom.header.stamp.nanosec = sec, nanosec
            odom.pose.pose.position.x, odom.pose.pose.position.y = self._faulty(
                (state[X], state[Y]))
            q = quaternion_from_euler(0.0, 0.0, state[PHI])
            o = odom.pose.pose.orientation
            o.x, o.y, o.z, o.w = q
            odom.twist.twist.linear.x, odom.twist.twist.angular.z = state[V], state[OMEGA]
            self.odom_pub.publish(odom)

    def _faulty(self, position):
        """Return the position as published: with the injected fault if due."""
        fault = self.position_fault
        if fault.kind == 'none' or position is None:
            return position
        active = self.released and self.t >= fault.start and (
            fault.duration == 0.0 or self.t < fault.start + fault.duration)
        if not active:
            self._frozen_position = None if self.t >= fault.start else tuple(position)
            return position
        if fault.kind == 'offset':
            return (position[0] + fault.offset[0], position[1] + fault.offset[1])
        if self._frozen_position is None:
            self._frozen_position = tuple(position)
        return self._frozen_position

    # -- reporting ------------------------------------------------------------------------
    def stats(self) -> dict:
        periods = [b - a for a, b in zip(self.tick_walls, self.tick_walls[1:])]
        limit = DEADLINE_FACTOR * self.command_period
        misses = sum(age > limit for age in self.command_ages)
        wall = (self.tick_walls[-1] - self.tick_walls[0]) if len(self.tick_walls) > 1 else 0.0
        released_at = self.release_wall
        return {
            'scenario': self.scenario.name,
            'plant_model': self.scenario.plant.model.model,
            'rate_hz': 1.0 / self.dt,
            'ticks': self.k,
            # Sensor samples published after the release (one of each sensor a tick).
            'ticks_after_release': self.k - self.ticks_at_release if self.released else 0,
            'wall_time_s': wall,
            'tick_period': percentiles(periods),
            'stalls': self.stalls,
            'publish_time': percentiles(self.publish_times),
            'released': self.released,
            'release_wall_s': released_at,
            'release_monotonic_s': self.release_monotonic,
            'sim_time_s': self.t,
            'fell': self.fell,
            'fall_time_s': self.fall_time,
            'end_reason': self.end_reason,
            'exit_code': self.exit_code,
            'commands': self.commands,
            'command_rate_hz': (len(self.command_gaps) / math.fsum(self.command_gaps)
                                if self.command_gaps else None),
            'rejected_commands': self.rejected,
            'reject_reasons': self.reject_reasons,
            'command_gap': percentiles(self.command_gaps),
            'command_age': percentiles(self.command_ages),
            'expected_command_period_s': self.command_period,
            'deadline_misses': misses,
            'deadline_miss_limit_s': limit,
            'ticks_checked': len(self.command_ages),
            'commands_after_fall': self.commands_after_fall,
            'nonzero_commands_after_fall': self.nonzero_after_fall,
            'last_command': list(self.efforts),
            'truth': self.truth,
        }

    def write_stats(self) -> None:
        if self.stats_file:
            with open(self.stats_file, 'w', encoding='utf-8') as stream:
                json.dump(self.stats(), stream)
                stream.write('\n')

    def _publish_diagnostics(self) -> None:
        if self.fell:
            level, message = DiagnosticStatus.ERROR, self.end_reason
        elif not self.released:
            level, message = DiagnosticStatus.WARN, 'held: waiting for a non-zero command'
        else:
            level, message = DiagnosticStatus.OK, f'running, t = {self.t:.2f} s'
        values = {'sim time [s]': f'{self.t:.3f}', 'commands': str(self.commands),
                  'rejected commands': str(self.rejected),
                  'command [N m]': str([round(v, 4) for v in self.efforts]),
                  'theta [rad]': f'{self.state[THETA]:.4f}'}
        status = DiagnosticStatus(level=level, name=f'{self.get_fully_qualified_name()}: '
                                  'stand-in base', message=message, hardware_id='standin',
                                  values=[KeyValue(key=k, value=v) for k, v in values.items()])
        array = DiagnosticArray(status=[status])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_pub.publish(array)


def main(args=None) -> int:
    """Entry point ``standin_base`` (``ros2 run wip_sim standin_base --ros-args ...``)."""
    return run_simulator_node(StandinBase, 'standin_base', args, config_status=EXIT_CONFIG)


if __name__ == '__main__':
    sys.exit(main())
