"""Driving the graph from outside (docs/driving.md): velocity commands and a path.

Each test runs the lockstep graph (single layout, the fastest) with a scenario of a
commanded reference kind, and a node of this process plays the user: a scripted teleop
driving a square on ``cmd_vel``, a planner sending one ``plan``. The lockstep clock is
the plant's, and it runs many times faster than the wall clock, so the scripted driver
paces itself on the stamps of the estimates it reads (one command per 0.05 s of simulated
time, stamped with the estimate's stamp), never on the wall clock. The assertions are on
the plant's ground truth (its final state, the run's outcome), not on timings.
"""

from __future__ import annotations

import math
import threading
import time

import pytest

pytest.importorskip('rclpy')
from ros_harness import spinning_in_background  # noqa: E402

pytestmark = [pytest.mark.ros, pytest.mark.slow]

SIDE = 1.0            # [m] of the square
SPEED = 0.3           # [m/s] forward command
TURN_RATE = 0.25      # [rad/s] largest turn command
COMMAND_PERIOD = 0.05  # [s] of simulated time between two commands
START_TIMEOUT = 120.0  # [s] wall, for the graph to start on a loaded 2-core machine
#: The route of a route publisher: 1.5 m ahead (+x), then 1 m to the left, from the robot's
#: start (on the stand-in base its first odometry pose: it is put down 0.5 m, 0.5 m,
#: 0.1 rad off the datum).
ROUTE = ((0.0, 0.0), (1.5, 0.0), (1.5, 1.0))


def write_scenario(path, reference: str, duration: float) -> str:
    # No disturbances: the closing error then measures the driving, not the collision.
    path.write_text(f'name: driving\nduration: {duration}\nreference: {reference}\n'
                    'initial_state: {pose: [0.0, 0.0, 0.0], x_v: 0.0, theta: 0.0}\n'
                    'disturbances: {yaw: [], longitudinal: [], tilt: []}\n')
    return str(path)


def run_in_thread(options, listening=None):
    """Run the graph in a thread; the plant starts once ``listening()`` (if given) is true.

    ``listening`` says that this process's driver has matched the graph's endpoints, as a
    real user's teleop or planner would before driving. Without it the run's first
    seconds race DDS discovery, whose delays lockstep multiplies (docs/testing.md).
    """
    from wip_bringup.graph_runner import GraphRunner
    from wip_bringup.launcher import EXIT_TIMEOUT, GraphError

    class DriverFirstRunner(GraphRunner):
        def start_plant(self) -> None:
            deadline = time.monotonic() + START_TIMEOUT
            while listening is not None and not listening():
                if time.monotonic() > deadline:
                    # The runner's own error: it stops every process and reports.
                    raise GraphError('the test driver never matched the graph', EXIT_TIMEOUT)
                self.probe.spin(0.05)
            super().start_plant()

    runner = DriverFirstRunner(options)
    outcome = {}
    thread = threading.Thread(target=lambda: outcome.setdefault('result', runner.run()))
    thread.start()
    return runner, thread, outcome


def wait_for(runner, thread, outcome, timeout: float):
    deadline = time.monotonic() + START_TIMEOUT + timeout
    while thread.is_alive() and time.monotonic() < deadline:
        thread.join(timeout=0.5)
    if thread.is_alive():
        for entry in runner.processes.values():
            entry.process.kill()
        thread.join(timeout=30.0)
        pytest.fail('the graph did not finish in time')
    return outcome['result']


def path_message(stamp, points):
    """nav_msgs/Path in ``map`` of ``points`` (x, y) [m], every pose stamped ``stamp``."""
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path
    path = Path()
    path.header.stamp, path.header.frame_id = stamp, 'map'
    for x, y in points:
        pose = PoseStamped()
        pose.header = path.header
        pose.pose.position.x, pose.pose.position.y = float(x), float(y)
        path.poses.append(pose)
    return path


def wrap(angle: float) -> float:
    return math.remainder(angle, 2.0 * math.pi)


class SquareDriver:
    """A scripted teleop: forward SIDE, turn left 90°, four times, then zero and silence.

    Closed loop on the state estimate, as a person watching the robot: the forward
    command falls with the distance left, the turn command with the heading left.
    """

    def __init__(self, node) -> None:
        from geometry_msgs.msg import TwistStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from wip_msgs.msg import StateEstimate
        self.node, self.TwistStamped = node, TwistStamped
        self.publisher = node.create_publisher(TwistStamped, 'cmd_vel', 10)
        # Best effort, depth 1: a late driver reads the newest estimate, not a queue.
        self.estimates = node.create_subscription(
            StateEstimate, '/wip/state_estimate', self.on_estimate,
            QoSProfile(depth=1, reliability=ReliabilityPolicy.BEST_EFFORT))
        self.leg, self.phase = 0, 'forward'
        self.corner = (0.0, 0.0)
        self.last_command_t = -math.inf
        self.done_t = None
        self.max_theta = 0.0
        self.commands = 0

    def listening(self) -> bool:
        """Whether the estimates reach this driver and its commands the reference node."""
        return (self.estimates.get_publisher_count() >= 1
                and self.publisher.get_subscription_count() >= 1)

    def on_estimate(self, msg) -> None:
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        self.max_theta = max(self.max_theta, abs(msg.theta))
        if t < self.last_command_t + COMMAND_PERIOD or not msg.settled:
            return
        heading = self.leg * 0.5 * math.pi
        v = omega = 0.0
        if self.phase == 'forward':
            along = ((msg.x - self.corner[0]) * math.cos(heading)
                     + (msg.y - self.corner[1]) * math.sin(heading))
            remaining = SIDE - along
            v = max(-0.1, min(SPEED, 0.6 * remaining))
            omega = max(-0.1, min(0.1, 0.5 * wrap(heading - msg.phi)))
            if abs(remaining) < 0.03 and abs(msg.v) < 0.05:
                self.phase = 'turn'
        elif self.phase == 'turn':
            error = wrap(heading + 0.5 * math.pi - msg.phi)
            omega = max(-TURN_RATE, min(TURN_RATE, 0.6 * error))
            if abs(error) < 0.03 and abs(msg.omega) < 0.05:
                # The next side starts at the square's next corner (not where the
                # vehicle stopped): the driver aims at a fixed square.
                self.corner = (self.corner[0] + SIDE * round(math.cos(heading)),
                               self.corner[1] + SIDE * round(math.sin(heading)))
                self.leg += 1
                self.phase = 'forward' if self.leg < 4 else 'stopping'
                if self.leg == 4:
                    self.done_t = t
        elif self.phase == 'stopping' and t > self.done_t + 1.0:
            return  # silence: the reference's command timeout keeps it at rest
        cmd = self.TwistStamped()
        cmd.header.stamp = msg.header.stamp
        cmd.twist.linear.x, cmd.twist.angular.z = float(v), float(omega)
        self.publisher.publish(cmd)
        self.last_command_t = t
        self.commands += 1


@pytest.mark.wallclock
def test_teleop_drives_a_square_and_the_vehicle_ends_at_its_start(tmp_path, test_node):
    from wip_bringup.graph import EXIT_OK, GraphOptions
    # cmd_vel_timeout 2 s: lockstep runs ~10x real time, so this process's wall-clock
    # delays count ten times in simulated time (the default 0.5 s is for a real robot).
    scenario = write_scenario(tmp_path / 'teleop.yaml',
                              '{kind: cmd_vel, cmd_vel_timeout: 2.0}', 110.0)
    driver = SquareDriver(test_node)
    with spinning_in_background(test_node.executor_for_test, step=0.005):
        runner, thread, outcome = run_in_thread(GraphOptions(
            scenario=scenario, out=str(tmp_path / 'run'), quiet=True, layout='single'),
            listening=driver.listening)
        result = wait_for(runner, thread, outcome, 300.0)
    assert result.exit_code == EXIT_OK, result.message
    assert driver.done_t is not None, f'the square was not finished: leg {driver.leg}'
    final = result.plant_stats['final_state']
    closing = math.hypot(final['x'], final['y'])
    print(f'square: {driver.commands} commands, done at {driver.done_t:.1f} s; closing '
          f'error {closing:.3f} m; final heading {wrap(final["phi"]):+.3f} rad; max |theta| '
          f'(estimate) {driver.max_theta:.3f} rad; final theta {final["theta"]:+.4f} rad')
    assert closing < 0.3
    assert abs(wrap(final['phi'])) < 0.1
    assert abs(final['theta']) < 0.02 and abs(final['v']) < 0.02, final
    assert driver.max_theta < 0.15


def test_a_path_is_followed_to_its_end(tmp_path, test_node):
    from nav_msgs.msg import Path
    from wip_msgs.msg import StateEstimate
    from wip_bringup.graph import EXIT_OK, GraphOptions
    scenario = write_scenario(tmp_path / 'path.yaml', '{kind: path}', 40.0)
    goal = [(1.5, 0.0), (1.5, 1.5)]
    publisher = test_node.create_publisher(Path, 'plan', 10)
    sent = []

    def on_estimate(msg) -> None:
        # The plan goes out on the first estimate after the reference node listens, and
        # again three times 0.25 s apart: DDS matches the two sides of a topic each on its
        # own, and a reader that has not yet matched loses a message (docs/node-graph.md, "The node
        # graph"). Each copy replaces the last from the reference's pose, still on the
        # first leg then, so the path is the same.
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        if publisher.get_subscription_count() < 1 or len(sent) >= 4 or (
                sent and t < sent[-1] + 0.25):
            return
        publisher.publish(path_message(msg.header.stamp, goal))
        sent.append(t)
    estimates = test_node.create_subscription(StateEstimate, '/wip/state_estimate',
                                              on_estimate, 1)
    with spinning_in_background(test_node.executor_for_test, step=0.005):
        runner, thread, outcome = run_in_thread(GraphOptions(
            scenario=scenario, out=str(tmp_path / 'run'), quiet=True, layout='single'),
            listening=lambda: (estimates.get_publisher_count() >= 1
                               and publisher.get_subscription_count() >= 1))
        result = wait_for(runner, thread, outcome, 200.0)
    assert result.exit_code == EXIT_OK, result.message
    assert sent, 'the path was never sent'
    assert sent[0] < 1.0, f'the path went out late, at {sent[0]} s: the start did not wait'
    final = result.plant_stats['final_state']
    error = math.hypot(final['x'] - goal[-1][0], final['y'] - goal[-1][1])
    print(f'path sent at {sent} s; final position error {error:.3f} m, '
          f'theta {final["theta"]:+.4f} rad, v {final["v"]:+.4f} m/s')
    assert error < 0.15
    assert abs(final['theta']) < 0.02 and abs(final['v']) < 0.02, final


def test_a_route_published_every_second_is_driven_to_its_end_in_lockstep(tmp_path, test_node):
    # A route publisher repeating its route once a second of simulated time (paced on the
    # estimates' stamps, as the path test above): each copy is the same path, so the robot
    # drives it once to its end (1.5 m ahead, then 1 m left of its start) and stands there.
    from nav_msgs.msg import Path
    from wip_msgs.msg import StateEstimate
    from wip_bringup.graph import EXIT_OK, GraphOptions
    scenario = write_scenario(tmp_path / 'route.yaml', '{kind: path}', 45.0)
    publisher = test_node.create_publisher(Path, 'plan', 10)
    sent = []

    def on_estimate(msg) -> None:
        t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        if publisher.get_subscription_count() < 1 or (sent and t < sent[-1] + 1.0):
            return
        publisher.publish(path_message(msg.header.stamp, ROUTE))
        sent.append(t)
    estimates = test_node.create_subscription(StateEstimate, '/wip/state_estimate',
                                              on_estimate, 1)
    with spinning_in_background(test_node.executor_for_test, step=0.005):
        runner, thread, outcome = run_in_thread(GraphOptions(
            scenario=scenario, out=str(tmp_path / 'run'), quiet=True, layout='single'),
            listening=lambda: (estimates.get_publisher_count() >= 1
                               and publisher.get_subscription_count() >= 1))
        result = wait_for(runner, thread, outcome, 200.0)
    assert result.exit_code == EXIT_OK, result.message
    final = result.plant_stats['final_state']
    error = math.hypot(final['x'] - ROUTE[-1][0], final['y'] - ROUTE[-1][1])
    print(f'{len(sent)} copies of the route sent; final position error {error:.3f} m, '
          f'theta {final["theta"]:+.4f} rad, v {final["v"]:+.4f} m/s')
    # Sent every second of the 45 s; lockstep outruns this process, so some seconds are
    # skipped on a loaded machine: at least one copy after the end is reached (~25 s).
    assert len(sent) >= 10 and sent[-1] > 30.0, sent
    assert error < 0.15
    assert abs(final['theta']) < 0.02 and abs(final['v']) < 0.02, final


@pytest.mark.wallclock
def test_teleop_drives_the_standin_base_in_real_time_and_odom_comes_out(tmp_path, test_node):
    # Hardware mode against the stand-in base (full plant, its own process, wall clock):
    # 5 s of 0.3 m/s forward on cmd_vel at 10 Hz, then silence. The reference starts at
    # the estimated pose, so the robot's initial offset (0.5 m, 0.5 m, 0.1 rad from the
    # scenario's start) is not driven out; it rolls forward about 1.5 m (1 s ramp up,
    # 4 s at 0.3 m/s, the 1 s brake after the timeout) and stays up at rest.
    # The teleop's node exists before the graph starts (test_node: the run uses its
    # $ROS_DOMAIN_ID): a participant that joins once the robot is released makes DDS
    # discovery stall the controllers' publications for ~0.33 s (docs/real-base.md, "Running on a
    # real base"), which was seen to topple the robot; the arming delay covers start-up.
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry
    from wip_bringup.standin_run import (BASE, line_scenario, run_against_standin,
                                         SHORT_ARM_DELAY)
    sent, odom = [], []
    test_node.create_subscription(Odometry, '/odom', odom.append, 10)
    publisher = test_node.create_publisher(TwistStamped, 'cmd_vel', 10)

    def during(_runner, _processes) -> None:
        start = time.monotonic()
        while time.monotonic() < start + 5.0:       # a teleop repeating at 10 Hz
            cmd = TwistStamped()
            cmd.header.stamp = test_node.get_clock().now().to_msg()
            cmd.twist.linear.x = SPEED
            publisher.publish(cmd)
            sent.append(time.monotonic())
            time.sleep(max(0.0, start + 0.1 * len(sent) - time.monotonic()))
        # Then until the odometry has stood still for the 2 s the criterion below looks at
        # (the command timeout, the 1 s brake, the sway), 8 s at most as before: the run
        # then ends 0.5 s later, not after a fixed 8 s.
        deadline = time.monotonic() + 8.0
        while time.monotonic() < deadline and not standing_for(odom, 2.0):
            time.sleep(0.05)

    # The paper's plant model: with the full one the controllers' speed loop oscillates
    # (about +-0.2 m/s with a 6 s period, tests/wip_sim/test_standin_base.py), which is not
    # what this test is about.
    scenario = dict(line_scenario(kind='cmd_vel'), plant={'model': 'paper'})
    with spinning_in_background(test_node.executor_for_test):
        run = run_against_standin(tmp_path / 'standin', BASE, 40.0, scenario=scenario,
                                  during=during, end_after_during=0.5, arm_delay=SHORT_ARM_DELAY)
    result, stats = run.result, run.stats
    assert result.exit_code == 0, result.message
    assert stats['released'] and not stats['fell'], stats.get('end_reason')
    assert len(sent) >= 40, 'the commands were not sent'
    truth = {k: list(v) for k, v in stats['truth'].items()}
    theta_max = max(abs(v) for v in truth['theta'])
    # From the release (the stand-in's t = 0) to the end: the commanded 1.5 m, plus the
    # few centimetres the robot rolls while it catches its initial tilt.
    x, y, t, v = truth['x'], truth['y'], truth['t'], truth['v']
    travelled = math.hypot(x[-1] - x[0], y[-1] - y[0])
    last = [abs(v[i]) for i in range(len(t)) if t[i] > t[-1] - 2.0]
    print(f'stand-in: {len(sent)} commands, travelled {travelled:.2f} m, max |v| over the '
          f'last 2 s {max(last):.3f} m/s, max |theta| {theta_max:.3f} rad, /odom messages '
          f'{len(odom)}')
    assert 1.0 < travelled < 2.0
    assert max(last) < 0.05 and theta_max < 0.3
    assert odom and odom[-1].header.frame_id == 'odom' and odom[-1].child_frame_id == 'base_link'


def standing_for(odom, seconds: float, speed: float = 0.02) -> bool:
    """Whether the odometry messages of the last ``seconds`` (by their stamps) are at rest."""
    messages = list(odom)      # a copy: the subscription appends from another thread
    if not messages:
        return False
    stamps = [m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec for m in messages]
    if stamps[-1] - stamps[0] < seconds:
        return False
    return all(abs(m.twist.twist.linear.x) < speed and abs(m.twist.twist.angular.z) < speed
               for m, t in zip(messages, stamps) if t >= stamps[-1] - seconds)


class RoutePublisher:
    """A route publisher or a replanning planner on ``plan``, reading ``/odom`` as Nav2 does.

    ``make(x, y, start)`` returns the path to send, from the robot's latest odometry pose
    (x, y) and its first one ``start``. Once a second until the robot stands within
    ``ARRIVED`` of ``goal(start)`` or ``deadline`` [s] passes.
    """

    ARRIVED = 0.08   # [m] from the goal, at under 0.02 m/s

    def __init__(self, node, make, goal) -> None:
        from nav_msgs.msg import Odometry, Path
        self.node, self.make, self.goal = node, make, goal
        self.publisher = node.create_publisher(Path, 'plan', 10)
        self.odom = []
        node.create_subscription(Odometry, '/odom', self.odom.append, 10)
        self.sent, self.start, self.arrived_after = [], None, None

    def message(self, points):
        return path_message(self.node.get_clock().now().to_msg(), points)

    def __call__(self, _runner, _processes, deadline: float = 120.0) -> None:
        began = time.monotonic()
        while not self.odom and time.monotonic() < began + 10.0:
            time.sleep(0.05)
        if not self.odom:
            return
        first = self.odom[-1].pose.pose.position
        self.start = (first.x, first.y)
        while time.monotonic() < began + deadline:
            pose, twist = self.odom[-1].pose.pose.position, self.odom[-1].twist.twist
            gx, gy = self.goal(self.start)
            if (math.hypot(pose.x - gx, pose.y - gy) < self.ARRIVED
                    and abs(twist.linear.x) < 0.02):
                self.arrived_after = time.monotonic() - began
                return
            self.publisher.publish(self.message(self.make(pose.x, pose.y, self.start)))
            self.sent.append(time.monotonic() - began)
            time.sleep(max(0.0, began + len(self.sent) - time.monotonic()))


def drive_standin_on_plan(tmp_path, test_node, publisher):
    """Hardware mode against the stand-in base (paper plant model) on ``reference.kind: path``."""
    from wip_bringup.standin_run import (BASE, line_scenario, run_against_standin,
                                         SHORT_ARM_DELAY)
    scenario = dict(line_scenario(kind='path', path_speed=SPEED), plant={'model': 'paper'})
    with spinning_in_background(test_node.executor_for_test):
        run = run_against_standin(tmp_path / 'standin', BASE, 200.0, scenario=scenario,
                                  during=publisher, end_after_during=3.0,
                                  arm_delay=SHORT_ARM_DELAY)
    result, stats = run.result, run.stats
    assert result.exit_code == 0, result.message
    assert stats['released'] and not stats['fell'], stats.get('end_reason')
    assert publisher.start is not None, 'no /odom reached the route publisher'
    truth = stats['truth']
    goal = publisher.goal(publisher.start)
    # The stand-in's ground truth is in the map frame of the estimate (GPS about the datum).
    error = math.hypot(truth['x'][-1] - goal[0], truth['y'][-1] - goal[1])
    last = [abs(v) for t, v in zip(truth['t'], truth['v']) if t > truth['t'][-1] - 2.0]
    print(f'{len(publisher.sent)} paths sent; arrived after {publisher.arrived_after} s; '
          f'final position {error:.3f} m from the goal; max |v| over the last 2 s '
          f'{max(last):.3f} m/s; max |theta| {max(abs(v) for v in truth["theta"]):.3f} rad')
    return error, last


@pytest.mark.wallclock
def test_a_route_published_every_second_is_driven_to_its_end_on_the_standin(
        tmp_path, test_node):
    # Before, each copy restarted the reference at the route's first point: the robot
    # turned on the spot near its start. Criteria on the end position only (the run's
    # timing depends on the machine's load): within 0.25 m of the route's end, at rest.
    publisher = RoutePublisher(
        test_node, lambda _x, _y, s: [(s[0] + dx, s[1] + dy) for dx, dy in ROUTE],
        lambda s: (s[0] + ROUTE[-1][0], s[1] + ROUTE[-1][1]))
    error, last = drive_standin_on_plan(tmp_path, test_node, publisher)
    assert len(publisher.sent) >= 10, 'the route was not published once a second'
    assert publisher.arrived_after is not None, 'the robot never stood at the route end'
    assert error < 0.25 and max(last) < 0.05


@pytest.mark.wallclock
def test_a_replanning_planner_drives_the_standin_to_its_goal(tmp_path, test_node):
    # Each second a new straight path from the robot's odometry pose to a goal 2 m ahead
    # and 1 m to the left; same criteria as the route's.
    goal = lambda s: (s[0] + 2.0, s[1] + 1.0)  # noqa: E731
    publisher = RoutePublisher(test_node, lambda x, y, s: [(x, y), goal(s)], goal)
    error, last = drive_standin_on_plan(tmp_path, test_node, publisher)
    assert len(publisher.sent) >= 5, 'the planner did not replan'
    assert publisher.arrived_after is not None, 'the robot never stood at the goal'
    assert error < 0.25 and max(last) < 0.05
