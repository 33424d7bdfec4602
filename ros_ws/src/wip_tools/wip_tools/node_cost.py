"""The six controller nodes' own cost per control tick, fed directly.

No DDS take, no wake-up by a message (``python -m wip_tools.node_cost``; ``scripts/bench`` runs
it).

The nodes are built as ``ros2 run wip_control controllers`` builds them (hardware-mode
parameters, the stand-in base's conventions, one executor, the intra-process bus). Each
tick calls the ESO's two sensor callbacks with serialized JointState and Imu stamped
now (and any other node's own subscription of them with the message deserialized, as
rclpy would take it for that subscription: the mixer's wiring checks where the ESO's
subscriptions do not serve them), drains the bus (estimate → reference → generator →
ARC → mixer → effort command, whose wheel torques run the MPC's due tick), spins the
executor every :data:`SPIN_EVERY` ticks for its due timers (the nodes' 1 Hz diagnostics)
and fires the deadlines the composed spin loop keeps (the mixer's and the MPC's, due only
when a chain is late); an outside
subscription of the effort command makes the mixer write it to DDS, as against a base.
The /wip/heartbeat is fed every 0.2 s. The vehicle stands still, upright (the cost of a
tick hardly depends on the state). Paced ticks first, until the safety layer has engaged
(its settle time is wall time); then the measured ticks.

The thread CPU time of each tick is measured, ``--pace 1`` with the ticks at 200 Hz
(sleeping between them, as in real time) or ``--pace 0`` back to back. Their ratio is what
the machine charges for running after an idle period (cold caches, a halted vCPU):
docs/realtime.md §2 (measured on the 2-core development machine). With it, per tick: the
measuring thread's context switches, migrations, minor faults and time waiting for a CPU,
and the CPU time of the whole process (``per_tick``).

``--split``: the tick's time by node as well (``split_us``): the time inside each node's
callbacks (its subscriptions', its values' and its deadlines'; a callback's time less that
of another node's callback it calls, such as the mixer's wiring checks served by the ESO's
sensor subscription), the harness's executor turns (the nodes' timers) and the rest of the
tick, the bus's deliveries and the harness.
Each call timed by the clock (``perf_counter``, about 0.1 µs a call: read the split beside
a plain run's median, not in place of it), back to back (``--pace 0``) where nothing else
runs within a tick.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import pathlib
import statistics
import sys
import tempfile
import time
import types

CONTROL_PERIOD = 0.005  # [s], 200 Hz
HEARTBEAT_EVERY = 40    # ticks between two /wip/heartbeat messages (0.2 s)
ENGAGE_TIMEOUT = 10.0   # [s] of paced ticks at most for the safety layer to engage
#: Ticks between two turns of the executor for its due timers (0.1 s; the only active ones
#: are the nodes' 1 Hz diagnostics). Not every tick: an idle turn is rclpy's cost, and it
#: slows the Python after it (docs/realtime.md); the composed process turns its executor
#: once per message taken, which rclpy's floor in scripts/bench measures.
SPIN_EVERY = 20


def measure(seconds: float, paced: bool, split: bool = False) -> dict:
    """Measure the thread CPU per tick of a controller node.

    In a process of its own (it initialises rclpy's default context): thread CPU per tick [us]
    (median, mean, p90) over ``seconds`` of 200 Hz ticks (the first fifth, start-up and
    warm-up, left out), and how many ticks ran; with ``split``, the mean time per tick in
    each node's callbacks and in the rest of the tick [us] (``split_us``, the module
    docstring).
    """
    import rclpy  # ROS only where measured

    from wip_runtime.composition import compose
    from wip_runtime.executors import make_executor
    from wip_control.nodes.controllers import NODE_CLASSES

    _init_rclpy()
    built: list = []
    timing = _Split() if split else None
    try:
        executor = make_executor()
        bus = compose(executor, [timing.build(node_class) if timing else node_class
                                 for node_class in NODE_CLASSES], built)
        feed = _SensorFeed({node.get_name(): node for node in built})
        time.sleep(1.0)    # DDS matching of the effort command
        mixer = feed.nodes['torque_mixer']
        engage_ticks = int(ENGAGE_TIMEOUT / CONTROL_PERIOD)
        ticks = max(50, int(seconds / CONTROL_PERIOD))
        costs, counted = [], None
        due = time.monotonic()
        for k in range(-engage_ticks, ticks):
            if k < 0 and str(mixer.monitor.state).endswith('ACTIVE'):
                continue        # engaged: on to the measured ticks
            if paced or k < 0:  # the safety layer engages after settle_time of wall time
                due += CONTROL_PERIOD
                delay = due - time.monotonic()
                if delay > 0.0:
                    time.sleep(delay)
            if k == 0:
                counted = _scheduler_counters()
            cost = (feed.tick(k, bus, executor) if timing is None
                    else timing.tick(feed, k, bus, executor, first=ticks // 5))
            if k >= 0:
                costs.append(cost)
        counters = _per_tick(counted, _scheduler_counters(), ticks)
        engaged = str(mixer.monitor.state)
        kept = sorted(costs[len(costs) // 5:])
        return {'paced': paced, 'ticks': ticks, 'safety_state': engaged,
                'median_us': 1e6 * statistics.median(kept),
                'mean_us': 1e6 * statistics.fmean(kept),
                'p90_us': 1e6 * kept[int(0.9 * (len(kept) - 1))],
                'effort_commands_to_dds': bus.published_dds,
                'per_tick': counters,
                'other_sensor_subscriptions': len(feed.others),
                **({'split_us': timing.result()} if timing else {})}
    finally:
        for node in built:
            node.destroy_node()
        rclpy.try_shutdown()


class _Split:
    """The time of the measured ticks inside each node's callbacks (``--split``)."""

    #: The name of what is not inside a node's callback: the bus's deliveries, the harness.
    REST = 'the rest (bus, harness)'
    #: The harness's turns of the executor for the nodes' due timers (SPIN_EVERY).
    TURNS = 'executor turns (timers)'

    def __init__(self) -> None:
        self.own: dict[str, float] = collections.defaultdict(float)
        self.nested = [0.0]      # per call being timed: the time of timed calls inside it
        self.ticks = 0
        self.tick_time = 0.0
        self._executor = None

    def build(self, node_class):
        """Return a factory of ``node_class`` whose callbacks are timed.

        Wrapped when the node is made, before the composition connects the bus and the
        shared sensor subscriptions to them: its subscriptions' callbacks, its direct-value
        callbacks and its deadlines'.
        """
        def factory():
            node = node_class()
            name = node.get_name()
            for subscription in node.subscriptions:
                subscription.callback = self._timed(subscription.callback, name)
            node.intra_subscriptions = [
                (msg_type, topic, self._timed(callback, name),
                 None if direct is None else self._timed(direct, name), value_type)
                for msg_type, topic, callback, direct, value_type in node.intra_subscriptions]
            for watchdog in getattr(node, 'watchdogs', ()):
                watchdog.callback = self._timed(watchdog.callback, name)
            return node
        return factory

    def _timed(self, callback, name: str):
        own, nested = self.own, self.nested

        def timed(*args, **kwargs):
            nested.append(0.0)
            start = time.perf_counter()
            try:
                return callback(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                own[name] += elapsed - nested.pop()
                nested[-1] += elapsed
        return timed

    def tick(self, feed: '_SensorFeed', k: int, bus, executor, first: int) -> float:
        """Run ``feed.tick``; count its cost from tick ``first`` on (the measured ticks)."""
        if k == first:
            self.own.clear()
            self.ticks, self.tick_time = 0, 0.0
        if self._executor is None:
            # What feed.tick uses of the executor, its turns, timed (rclpy's executor's own
            # attributes are read-only).
            self._executor = types.SimpleNamespace(
                spin_once=self._timed(executor.spin_once, self.TURNS))
        cost = feed.tick(k, bus, self._executor)
        if k >= first:
            self.tick_time += cost
            self.ticks += 1
        return cost

    def result(self) -> dict[str, float]:
        """Mean µs per tick inside each node's callbacks, the rest, and the whole tick.

        The tick's thread CPU time, as measured; the callbacks' by the clock (the same
        back to back, where nothing else runs in between).
        """
        ticks = max(1, self.ticks)
        split = {name: 1e6 * own / ticks for name, own in sorted(self.own.items())}
        split[self.REST] = 1e6 * (self.tick_time - sum(self.own.values())) / ticks
        split['tick'] = 1e6 * self.tick_time / ticks
        return split


def _scheduler_counters() -> dict[str, float] | None:
    """Return the measuring thread's scheduler counters, the process's CPU time (Linux).

    Context switches and migrations from ``/proc/thread-self/sched``, the time spent
    runnable but waiting for a CPU from its ``schedstat`` [ns], minor page faults of the
    thread, and the CPU time of all the process's threads [s] (the DDS threads that the
    effort command's write wakes). None where there is no such file.
    """
    import resource

    try:
        with open('/proc/thread-self/sched', encoding='ascii') as stream:
            fields = {name.strip(): value for name, value in
                      (line.split(':', 1) for line in stream if ':' in line)}
        with open('/proc/thread-self/schedstat', encoding='ascii') as stream:
            wait_ns = int(stream.read().split()[1])
    except (OSError, IndexError, ValueError):
        return None
    thread = resource.getrusage(resource.RUSAGE_THREAD)
    process = resource.getrusage(resource.RUSAGE_SELF)
    return {'voluntary_switches': float(fields['nr_voluntary_switches']),
            'involuntary_switches': float(fields['nr_involuntary_switches']),
            'migrations': float(fields['se.nr_migrations']),
            'runnable_wait_us': wait_ns * 1e-3, 'minor_faults': float(thread.ru_minflt),
            'process_cpu_us': 1e6 * (process.ru_utime + process.ru_stime)}


def _per_tick(before: dict | None, after: dict | None, ticks: int) -> dict | None:
    """Each counter's change from ``before`` to ``after`` per tick (None if unknown)."""
    if before is None or after is None:
        return None
    return {name: (after[name] - before[name]) / ticks for name in before}


def _init_rclpy() -> None:
    """Initialise rclpy with hardware mode's parameters and the stand-in base's."""
    import rclpy
    import yaml

    from wip_bringup.hardware_params import hardware_parameters
    from wip_bringup.params_files import _NoAliasDumper
    from wip_bringup.standin_run import BASE
    from wip_sim.core.scenario import load_scenario

    with tempfile.TemporaryDirectory(prefix='wip_node_cost_') as directory:
        params = pathlib.Path(directory) / 'params.yaml'
        params.write_text(yaml.dump(hardware_parameters(load_scenario(None)),
                                    Dumper=_NoAliasDumper), encoding='utf-8')
        base = pathlib.Path(directory) / 'base.yaml'
        base.write_text(yaml.safe_dump({'/**': {'ros__parameters': dict(BASE)}}),
                        encoding='utf-8')
        rclpy.init(args=['--ros-args', '--params-file', str(params), '--params-file',
                         str(base)])


class _SensorFeed:
    """The sensor messages of a standing vehicle, handed to the nodes' callbacks."""

    def __init__(self, nodes: dict):
        import rclpy
        from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus
        from std_msgs.msg import Float64MultiArray

        from wip_bringup.standin_run import BASE
        from wip_runtime.qos import RELIABLE_QOS
        from wip_sim.core.scenario import load_scenario
        from wip_sim.base_conventions import BaseConventions

        self.nodes = nodes
        eso = {s.topic_name: s.callback for s in nodes['eso'].subscriptions}
        self.on_joint_states, self.on_imu = eso['/joint_states'], eso['/imu/data']
        self.on_fix = eso['/gps/fix']
        # Other nodes' own subscriptions of the sensors (the mixer's wiring checks), each
        # taking a message of its own as rclpy would deliver it; none where the ESO's
        # subscriptions serve them (wip_runtime.composition.share_raw_subscriptions).
        self.others = [(s.msg_type, s.callback) for name, node in nodes.items() if name != 'eso'
                       for s in node.subscriptions
                       if s.topic_name in ('/joint_states', '/imu/data') and not s.raw]
        self.on_heartbeat = {s.topic_name: s.callback
                             for s in nodes['torque_mixer'].subscriptions}['/wip/heartbeat']
        self.listener = rclpy.create_node('node_cost_listener')
        self.listener.create_subscription(Float64MultiArray, '/effort_controller/commands',
                                          lambda _msg: None, RELIABLE_QOS)
        conventions = BaseConventions(BASE['joints'], BASE['left_joint'], BASE['right_joint'],
                                      BASE['left_wheel_sign'], BASE['right_wheel_sign'],
                                      BASE['imu_mounting_rpy'])
        self.joint, self.imu = JointState(), Imu()
        conventions.fill(self.joint, self.imu, (0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.0, 0.0,
                         0.0, 0.0, 9.81)
        # A fix at the datum every GPS period, as the base's receiver (the safety layer
        # engages only once the position is known).
        sensors = load_scenario(None).sensors
        self.fix = NavSatFix(latitude=sensors.gps_datum_latitude,
                             longitude=sensors.gps_datum_longitude,
                             altitude=sensors.gps_datum_altitude)
        self.fix.status.status = NavSatStatus.STATUS_FIX
        self.gps_every = max(1, round(1.0 / (sensors.gps_rate * CONTROL_PERIOD)))

    def tick(self, k: int, bus, executor) -> float:
        """Run control tick ``k``; return its thread CPU time [s]."""
        from rclpy.serialization import deserialize_message, serialize_message
        from sensor_msgs.msg import Imu, JointState
        from std_msgs.msg import Empty

        if k % HEARTBEAT_EVERY == 0:
            self.on_heartbeat(Empty())
            bus.drain()
        sec, nanosec = divmod(time.time_ns(), 10 ** 9)
        for msg in (self.joint, self.imu):
            msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        joint_bytes, imu_bytes = serialize_message(self.joint), serialize_message(self.imu)
        start = time.thread_time()
        if k % self.gps_every == 0:
            self.fix.header.stamp.sec, self.fix.header.stamp.nanosec = sec, nanosec
            self.on_fix(self.fix)
        self.on_joint_states(joint_bytes)
        for msg_type, callback in self.others:
            if msg_type is JointState:
                callback(deserialize_message(joint_bytes, JointState))
        bus.drain()
        self.on_imu(imu_bytes)
        for msg_type, callback in self.others:
            if msg_type is Imu:
                callback(deserialize_message(imu_bytes, Imu))
        bus.drain()
        if k % SPIN_EVERY == 0:
            executor.spin_once(timeout_sec=0.0)
        now = time.monotonic()
        for watchdog in bus.watchdogs:      # the deadlines the composed spin loop keeps
            watchdog.fire_if_due(now)
        bus.drain()
        return time.thread_time() - start


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog='python -m wip_tools.node_cost',
                                     description=' '.join(__doc__.split('\n\n')[:2]))
    parser.add_argument('--seconds', type=float, default=10.0,
                        help='ticks of 5 ms to run (default 10 s of them)')
    parser.add_argument('--pace', type=int, choices=(0, 1), default=1,
                        help='1: at 200 Hz, sleeping between ticks; 0: back to back')
    parser.add_argument('--split', action='store_true',
                        help="also the tick's time inside each node's callbacks (split_us)")
    args = parser.parse_args(argv)
    if not (math.isfinite(args.seconds) and 0.0 < args.seconds <= 3600.0):
        parser.error(f'--seconds: must be in (0, 3600], got {args.seconds}')
    print(json.dumps(measure(args.seconds, bool(args.pace), args.split)))
    return 0


if __name__ == '__main__':
    sys.exit(main())
