"""Property-based fuzzing of every subscription callback of every controller node.

Hypothesis builds arbitrary messages of each subscription's type from the type's own
field list: numbers finite, non-finite (NaN, ±inf), huge (±1e300) or tiny; arrays empty,
short, long; strings arbitrary or the expected joint names; header stamps at t = 0, on
the control grid, in the past (negative), far in the future, unnormalised (nanosec ≥ 1e9),
in any order. Each example is a sequence of such messages handed to the callbacks the
nodes registered (``node.subscriptions``), each followed by the node's timer callbacks
(real-time ticks, diagnostics), called directly so that an exception escaping a callback
fails the test. The nodes are in-process, in both clock modes, and keep their state from
one example to the next (a long random history).

Properties:
- no callback raises;
- every float of every message a node publishes is finite (the ESO's ε excepted: it is
  inf at the very start of the paper's ramp, by design, see conversions.py);
- the torque outputs (WheelTorques, the Float64MultiArray for ros2_control) are within
  ±mixer.max_wheel_torque, and a WheelTorques with ``zeroed`` is exactly zero;
- after the fuzzing, a node still computes a finite output from plausible input (it was
  not poisoned), checked for the mixer, whose output is the one that reaches a robot;
- a parameter set at run time to a bad value (wrong type, NaN, inf, out of range) is
  rejected with a reason, and a node's configuration stays valid.
"""

import importlib
import math
import re

from hypothesis import example, given, HealthCheck, settings, strategies as st
import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('wip_msgs.msg')

from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import Imu, JointState, NavSatFix, NavSatStatus  # noqa: E402
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from std_msgs.msg import Float64MultiArray  # noqa: E402
from wip_msgs.msg import (YawTorque, DriveTorque, StateEstimate as StateEstimateMsg,  # noqa: E402
                          WheelTorques)

from wip_description.sensors import local_to_geodetic, SensorParams  # noqa: E402
from wip_control.nodes.arc_node import ArcNode  # noqa: E402
from wip_runtime.rotations import quaternion_from_euler  # noqa: E402
from wip_runtime.executors import make_executor, spin_once_guarded  # noqa: E402
from wip_runtime.qos import CLOCK_QOS  # noqa: E402
from wip_runtime.stamps import make_header  # noqa: E402
from wip_control.nodes.eso_node import EsoNode  # noqa: E402
from wip_control.nodes.mpc_node import MpcNode  # noqa: E402
from wip_control.nodes.reference_node import ReferenceNode  # noqa: E402
from wip_control.nodes.torque_mixer_node import TorqueMixerNode  # noqa: E402
from wip_control.nodes.trajectory_generator_node import TrajectoryGeneratorNode  # noqa: E402

pytestmark = pytest.mark.ros

NODES = (ReferenceNode, EsoNode, TrajectoryGeneratorNode, ArcNode, MpcNode, TorqueMixerNode)
MAX_WHEEL_TORQUE = 15.0        # [N m], the default mixer.max_wheel_torque
H_NS = 5_000_000               # control period [ns]
#: Examples per node and mode (12 node/mode pairs): the whole file runs in about 15 s.
EXAMPLES = 100
_SENSORS = SensorParams()
DATUM = (_SENSORS.gps_datum_latitude, _SENSORS.gps_datum_longitude, _SENSORS.gps_datum_altitude)


# ----------------------------------------------------------------------------- strategies

special = st.sampled_from([0.0, -0.0, math.nan, math.inf, -math.inf, 1e300, -1e300, 1e-300,
                           1.0, -1.0, 0.5])
doubles = st.one_of(special, st.floats(-10.0, 10.0), st.floats(allow_nan=True,
                                                               allow_infinity=True))
# float32 fields must fit a float32 (rclpy checks); non-finite values are allowed.
floats32 = st.one_of(st.sampled_from([0.0, math.nan, math.inf, -math.inf, 3.0e38]),
                     st.floats(-1e3, 1e3, width=32))
INT_RANGES = {'int8': (-2 ** 7, 2 ** 7 - 1), 'uint8': (0, 2 ** 8 - 1),
              'int16': (-2 ** 15, 2 ** 15 - 1), 'uint16': (0, 2 ** 16 - 1),
              'int32': (-2 ** 31, 2 ** 31 - 1), 'uint32': (0, 2 ** 32 - 1),
              'int64': (-2 ** 63, 2 ** 63 - 1), 'uint64': (0, 2 ** 64 - 1),
              'octet': (0, 255), 'byte': (0, 255)}
names = st.one_of(st.sampled_from(['left_wheel_joint', 'right_wheel_joint', '', 'caster']),
                  st.text(max_size=8))
# Stamps: the grid around t = 0 (so exact-time sets complete), past, far future, odd.
stamps = st.one_of(
    st.builds(lambda k: make_header(k * 20 * H_NS).stamp, st.integers(0, 2)),
    st.builds(lambda k: make_header(k * H_NS).stamp, st.integers(0, 40)),
    st.builds(lambda k: make_header(k * 20 * H_NS).stamp, st.integers(0, 5)),
    st.builds(lambda s, n: _time(s, n), st.integers(-2 ** 31, 2 ** 31 - 1),
              st.integers(0, 2 ** 32 - 1)))


def _time(sec, nanosec):
    from builtin_interfaces.msg import Time
    return Time(sec=sec, nanosec=nanosec)


def _type(name):
    package, _, kind = name.partition('/')
    return getattr(importlib.import_module(f'{package}.msg'), kind)


def scalar(kind, field):
    if kind in ('double', 'float64'):
        return doubles
    if kind in ('float', 'float32'):
        return floats32
    if kind in INT_RANGES:
        low, high = INT_RANGES[kind]
        return st.one_of(st.integers(low, high), st.sampled_from([low, high, 0, 1]))
    if kind == 'boolean':
        return st.booleans()
    if kind.startswith('string'):
        return names if field == 'name' else st.text(max_size=8)
    if '/' in kind:
        return message(_type(kind))
    raise NotImplementedError(kind)


def field_strategy(kind, field):
    fixed = re.fullmatch(r'(.+)\[(\d+)\]', kind)
    if fixed:
        element = scalar(fixed.group(1), field)
        return st.lists(element, min_size=int(fixed.group(2)), max_size=int(fixed.group(2)))
    sequence = re.fullmatch(r'sequence<([^,>]+)(?:, \d+)?>', kind)
    if sequence:
        return st.lists(scalar(sequence.group(1), field), max_size=4)
    return scalar(kind, field)


_MESSAGES = {}


def message(msg_type):
    """Arbitrary instances of a ROS message type, from its field list."""
    if msg_type not in _MESSAGES:
        fields = msg_type.get_fields_and_field_types()
        strategies = {}
        for field, kind in fields.items():
            if kind == 'builtin_interfaces/Time' and field == 'stamp':
                strategies[field] = stamps
            elif kind == 'std_msgs/Header':
                strategies[field] = st.builds(
                    lambda stamp, frame: _header(stamp, frame), stamps, st.text(max_size=4))
            else:
                strategies[field] = st.deferred(lambda k=kind, f=field: field_strategy(k, f))
        _MESSAGES[msg_type] = st.fixed_dictionaries(strategies).map(
            lambda values, t=msg_type: t(**values))
    return _MESSAGES[msg_type]


def _imu(header, pitch, yaw):
    msg = Imu(header=header)
    try:
        q = quaternion_from_euler(0.0, pitch, yaw)
    except ValueError:                     # cos(inf): a driver would send NaN
        q = (math.nan,) * 4
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = q
    return msg


def _fix(header, north, east):
    lat, lon, alt = local_to_geodetic(east, north, *DATUM)
    return NavSatFix(header=header, latitude=lat, longitude=lon, altitude=alt,
                     status=NavSatStatus(status=NavSatStatus.STATUS_FIX))


headers = st.builds(lambda stamp: _header(stamp, ''), stamps)
#: Well-formed messages with arbitrary numbers, so that the fuzzing reaches the nodes'
#: computations (an arbitrary quaternion is almost never of unit norm, arbitrary joint
#: names almost never the wheels').
PLAUSIBLE = {
    'sensor_msgs/Imu': st.builds(_imu, headers, doubles, doubles),
    'sensor_msgs/JointState': st.builds(
        lambda h, names, pos: JointState(header=h, name=names, position=pos),
        headers, st.sampled_from([['left_wheel_joint', 'right_wheel_joint'],
                                  ['right_wheel_joint', 'left_wheel_joint']]),
        st.lists(doubles, min_size=2, max_size=2)),
    'sensor_msgs/NavSatFix': st.builds(_fix, headers, st.floats(-1e3, 1e3),
                                       st.floats(-1e3, 1e3)),
}


def any_message(msg_type):
    """Arbitrary messages of ``msg_type``, and well-formed ones where that matters."""
    name = msg_type.__module__.split('.')[0] + '/' + msg_type.__name__
    if name in PLAUSIBLE:
        return st.one_of(message(msg_type), PLAUSIBLE[name])
    return message(msg_type)


def _header(stamp, frame):
    from std_msgs.msg import Header
    return Header(stamp=stamp, frame_id=frame)


def plausible_estimate(stamp_ns):
    return StateEstimateMsg(header=make_header(stamp_ns), theta=0.01, settled=True,
                            epsilon=0.01)


# ----------------------------------------------------------------------------- checks

def assert_finite(msg, path=''):
    """Every float (and float array) of ``msg`` is finite; recurses into nested messages."""
    for name, kind in msg.get_fields_and_field_types().items():
        value = getattr(msg, name)
        where = f'{path}{type(msg).__name__}.{name}'
        if isinstance(msg, StateEstimateMsg) and name == 'epsilon':
            continue                                     # inf at the ramp start, by design
        if kind in ('double', 'float'):
            assert math.isfinite(value), f'{where} = {value}'
        elif re.match(r'(sequence<)?(double|float)', kind):
            assert all(math.isfinite(v) for v in value), f'{where} = {list(value)}'
        elif '/' in kind and not kind.startswith('sequence'):
            assert_finite(value, f'{where}.')


def assert_torques_within_limits(msg):
    if isinstance(msg, WheelTorques):
        assert abs(msg.left) <= MAX_WHEEL_TORQUE and abs(msg.right) <= MAX_WHEEL_TORQUE, msg
        if msg.zeroed:
            assert (msg.left, msg.right) == (0.0, 0.0) and msg.reason
    if isinstance(msg, Float64MultiArray):
        assert len(msg.data) == 2 and all(abs(v) <= MAX_WHEEL_TORQUE for v in msg.data)


class Outputs:
    """Records what a node publishes, by replacing each publisher's publish method."""

    def __init__(self, node):
        self.messages = []
        for publisher in node.publishers:
            publish = publisher.publish

            def recorded(msg, _publish=publish, _type=publisher.msg_type):
                # A message published serialized (the mixer's effort command) is checked
                # as the message a subscriber receives.
                self.messages.append(deserialize_message(msg, _type)
                                     if isinstance(msg, bytes) else msg)
                _publish(msg)
            publisher.publish = recorded


#: The real-time nodes' clock in the fuzzing [ns]: an hour after the epoch, as a robot
#: whose clock starts at boot.
FUZZ_NOW_NS = 3600 * 10**9


def make_node(context, node_cls, mode):
    params = {'clock_mode': mode, 'use_sim_time': mode == 'lockstep',
              'diagnostics_period': 0.0}
    if node_cls is TorqueMixerNode:
        params['safety.settle_time'] = 0.0
        # The recovery check resets at once after the fuzzing's e-stop messages.
        params['safety.estop_hold_time'] = 0.0
    node = node_cls(context=context, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    if mode == 'realtime':
        # A fixed node clock: real-time nodes judge stamps against it (a stamp ahead of it
        # is refused), so with the wall clock the same derandomized examples passed or
        # failed depending on the date (a random stamp in the past blocks every later,
        # older one).
        node.now_ns = lambda: FUZZ_NOW_NS
    return node


# ----------------------------------------------------------------------------- fuzzing

@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
@pytest.mark.parametrize('node_cls', NODES, ids=lambda c: c.__name__)
def test_arbitrary_messages_into_every_callback_never_raise_or_output_bad_torque(
        context, node_cls, mode):
    node = make_node(context, node_cls, mode)
    try:
        # rclpy's own /clock subscription (use_sim_time) is not the node's callback: it
        # raises on a negative time; test_a_callback_error_does_not_end_the_spin_loop.
        subscriptions = sorted((s for s in node.subscriptions
                                if type(getattr(s.callback, '__self__', None)).__name__
                                != 'TimeSource'), key=lambda s: s.topic_name)
        timers = list(node.timers)
        outputs = Outputs(node)
        if not subscriptions:
            # The real-time reference node has only its timer.
            assert node_cls is ReferenceNode and mode == 'realtime'
            for _ in range(3):
                for timer in timers:
                    timer.callback()
            assert outputs.messages and all(assert_finite(m) is None for m in outputs.messages)
            return
        calls = st.lists(st.one_of(*[
            st.tuples(st.just(i), any_message(s.msg_type))
            for i, s in enumerate(subscriptions)]),
            min_size=1, max_size=12)

        # derandomize: the same examples on every run. With random ones, a run now and then
        # never formed a complete lockstep input set of the ESO (joint states, IMU and GPS
        # of one stamp), and the check below that the computation was reached failed. That
        # still happened once in a whole-suite run (Hypothesis generated other examples
        # there than alone), so the ESO's complete set is also given as an explicit example.
        explicit = complete_sensor_set(subscriptions)

        @settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
                  suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
        @given(calls=calls)
        @(example(calls=explicit) if explicit else lambda test: test)
        def fuzz(calls):
            first = len(outputs.messages)
            for index, msg in calls:
                subscriptions[index].callback(msg)     # any exception fails the test
                for timer in timers:
                    timer.callback()
            for out in outputs.messages[first:]:
                assert_finite(out)
                assert_torques_within_limits(out)
        fuzz()
        computed = [m for m in outputs.messages if not isinstance(m, DiagnosticArray)]
        # The fuzzing reached the computation, not only the input checks.
        assert computed, f'{node_cls.__name__} never published an output'
        if node_cls is TorqueMixerNode:
            # Not poisoned: plausible input gives a finite, non-zeroed command again.
            assert_mixer_recovers(node, subscriptions, timers, outputs, mode)
    finally:
        node.destroy_node()


def complete_sensor_set(subscriptions):
    """(index, message) of one complete sensor set at stamp 0, if the node takes the sensors.

    Joint states, IMU and a GPS fix of one stamp (a GPS tick): an estimate in either clock
    mode. An empty list for a node without those three inputs.
    """
    index = {s.topic_name: i for i, s in enumerate(subscriptions)}
    if not {'/joint_states', '/imu/data', '/gps/fix'} <= index.keys():
        return []
    header = make_header(0)
    return [(index['/joint_states'], JointState(
                header=header, name=['left_wheel_joint', 'right_wheel_joint'],
                position=[0.0, 0.0])),
            (index['/imu/data'], _imu(header, 0.01, 0.2)),
            (index['/gps/fix'], _fix(header, 0.0, 0.0))]


def assert_mixer_recovers(node, subscriptions, timers, outputs, mode):
    by_topic = {s.topic_name: s.callback for s in subscriptions}
    by_topic['/wip/estop'](_bool(False))
    node.reset_estop('test')
    stamp = 10 ** 18                     # after any stamp the fuzzing may have sent
    for k in range(3):
        s = stamp + k * 20 * H_NS
        by_topic['/wip/state_estimate'](plausible_estimate(s))
        by_topic['/wip/drive_torque'](DriveTorque(header=make_header(s), tau_v=2.0))
        by_topic['/wip/yaw_torque'](YawTorque(header=make_header(s), tau_omega=0.2))
        for timer in timers:
            timer.callback()
    last = [m for m in outputs.messages if isinstance(m, WheelTorques)][-1]
    assert not last.zeroed, last.reason
    assert last.left + last.right == pytest.approx(2.0) and math.isfinite(last.left)


def _bool(value):
    from std_msgs.msg import Bool
    return Bool(data=value)


# ----------------------------------------------------------------------------- parameters

bad_values = st.one_of(st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, 1e300,
                                        -1e300, '', 'x', True, -5, [], [math.nan]]),
                       st.floats(allow_nan=True), st.text(max_size=3))


@pytest.mark.parametrize('node_cls', NODES, ids=lambda c: c.__name__)
def test_a_bad_parameter_value_at_run_time_is_rejected_with_a_reason(context, node_cls):
    node = make_node(context, node_cls, 'realtime')
    try:
        names = sorted(n for n in node._parameters if n != 'use_sim_time')
        before = {n: node.get_parameter(n).value for n in names}

        @settings(max_examples=60, deadline=None, database=None)
        @given(name=st.sampled_from(names), value=bad_values)
        def fuzz(name, value):
            result = node.set_parameters([Parameter(name, value=value)])[0]
            if result.successful:
                # Accepted: then it was a valid value of a run-time parameter, and the
                # node's config object agrees with it.
                config = node.parameters.config
                field = name.split('.', 1)[1]
                got = getattr(config, field)
                assert got == value or (isinstance(got, tuple) and list(got) == value)
                assert not (isinstance(value, float) and not math.isfinite(value))
            else:
                assert result.reason, f'{name} = {value!r} rejected without a reason'
        fuzz()
        # Read-only parameters never changed.
        for name in names:
            descriptor = node.describe_parameter(name)
            if descriptor.read_only:
                assert node.get_parameter(name).value == before[name] or (
                    list(node.get_parameter(name).value) == list(before[name])), name
    finally:
        node.destroy_node()


# ----------------------------------------------------------------------------- spin loop

def test_a_callback_error_does_not_end_the_spin_loop(context):
    """A callback error does not end the spin loop.

    rclpy's time source raises on a /clock with a negative time (not the node's code):
    the nodes' spin loop (``run_node``) logs it and goes on with the next messages. The
    reference node's own clock is driven by its /clock ticker, which reports that sample
    as invalid instead; the raising subscription here is what rclpy's time source does in
    the other nodes (``rclpy.time.Time.from_msg``).
    """
    import time
    from builtin_interfaces.msg import Time
    from rclpy.time import Time as RosTime
    from rosgraph_msgs.msg import Clock
    from wip_msgs.msg import ReferenceState
    node = make_node(context, ReferenceNode, 'lockstep')
    node.create_subscription(Clock, '/clock', lambda msg: RosTime.from_msg(msg.clock),
                             CLOCK_QOS)
    io = rclpy.create_node('fuzz_clock_harness', context=context)
    executor = make_executor(context=context)
    try:
        executor.add_node(node)
        executor.add_node(io)
        out = []
        io.create_subscription(ReferenceState, '/wip/reference', out.append, 10)
        clock = io.create_publisher(Clock, '/clock', CLOCK_QOS)
        deadline = time.monotonic() + 60.0   # discovery on a slow, shared machine
        while clock.get_subscription_count() < 2 or io.count_publishers('/wip/reference') < 1:
            assert time.monotonic() < deadline, 'discovery'
            spin_once_guarded(executor, node, 0.01)
        results = []
        for sec in (-1, 0, 1):
            clock.publish(Clock(clock=Time(sec=sec)))
            while not out or out[-1].header.stamp.sec != sec:
                assert time.monotonic() < deadline, f'no reference for /clock {sec}'
                results.append(spin_once_guarded(executor, node, 0.01))
        assert results.count(False) == 1       # the negative /clock, once
        assert node.get_clock().now().nanoseconds == 1_000_000_000
        assert node.diagnostics.dropped[('clock', 'invalid')] == 1
    finally:
        executor.shutdown()
        io.destroy_node()
        node.destroy_node()


# ----------------------------------------------------------------------------- overflow

def _by_topic(node):
    return {s.topic_name: s.callback for s in node.subscriptions}


def test_overflowing_finite_input_does_not_poison_the_arc(context):
    """An overflowing finite input does not poison the ARC.

    ω̂ = 1.7e308 and ωd = −1.7e308 are finite, but eω = ω̂ − ωd overflows to inf and,
    with ω̇d = f̂1 (regressor 0), (13) gives α̂ = inf·0 = NaN; a NaN α̂ would then clip
    τω to +max_yaw_torque at every later step. The node drops that input and keeps α̂.
    """
    from wip_msgs.msg import VelocityCommand
    node = make_node(context, ArcNode, 'lockstep')
    try:
        outputs = Outputs(node)
        callbacks = _by_topic(node)
        alpha = node.controller.alpha_hat
        callbacks['/wip/velocity_command'](VelocityCommand(header=make_header(0),
                                                           omega_d=-1.7e308))
        callbacks['/wip/state_estimate'](StateEstimateMsg(header=make_header(0), omega=1.7e308))
        assert node.controller.alpha_hat == alpha and outputs.messages == []
        assert node.diagnostics.dropped[('state_estimate', 'invalid')] == 1
        callbacks['/wip/velocity_command'](VelocityCommand(header=make_header(H_NS)))
        callbacks['/wip/state_estimate'](StateEstimateMsg(header=make_header(H_NS)))
        out = outputs.messages[-1]
        # At rest on the command (eω = 0, regressor 0): τω = 0 exactly, with a finite α̂.
        assert (out.tau_omega, out.alpha_hat) == (0.0, alpha)
    finally:
        node.destroy_node()


def test_overflowing_finite_input_does_not_poison_the_trajectory_generator(context):
    """An overflowing finite input does not poison the trajectory generator.

    Positions of 1e308 m and −1e308 m are finite, but the error between them is inf
    and ωd NaN: the node drops the input, keeps the derivative filter's state, and the
    next sample is normal.
    """
    from wip_msgs.msg import ReferenceState
    node = make_node(context, TrajectoryGeneratorNode, 'lockstep')
    try:
        outputs = Outputs(node)
        callbacks = _by_topic(node)
        callbacks['/wip/reference'](ReferenceState(header=make_header(0), x=1e308, v=0.5))
        callbacks['/wip/state_estimate'](StateEstimateMsg(header=make_header(0), x=-1e308))
        assert outputs.messages == []
        assert node.diagnostics.dropped[('state_estimate', 'invalid')] == 1
        callbacks['/wip/reference'](ReferenceState(header=make_header(H_NS), v=0.5))
        callbacks['/wip/state_estimate'](StateEstimateMsg(header=make_header(H_NS)))
        assert len(outputs.messages) == 1
        assert_finite(outputs.messages[0])
    finally:
        node.destroy_node()


def test_overflowing_finite_input_restarts_the_eso_instead_of_poisoning_it(context):
    """An overflowing finite input restarts the ESO instead of poisoning it.

    A wheel angle of 5e307 rad (x_v ~ 1e307 m) is finite but overflows the observer
    (f̂2 = inf, then NaN): no estimate is published, and the observer restarts from the
    next measurement instead of staying NaN for good.
    """
    node = make_node(context, EsoNode, 'realtime')
    try:
        outputs = Outputs(node)
        callbacks = _by_topic(node)

        def sample(stamp, angle):
            callbacks['/joint_states'](JointState(
                header=make_header(stamp), name=['left_wheel_joint', 'right_wheel_joint'],
                position=[angle, angle]))
            callbacks['/imu/data'](_imu(make_header(stamp), 0.01, 0.2))
        sample(0, 0.0)
        # (5e307 rad: the default gyro estimator's x_v ESO has gains up to ~1e3 per
        # sample, so 1e306 no longer overflows it; the paper's ESOs overflow at 1e306.)
        sample(H_NS, 5e307)
        sample(2 * H_NS, 5e307)
        sample(3 * H_NS, 0.0)
        sample(4 * H_NS, 0.001)
        estimates = [m for m in outputs.messages if isinstance(m, StateEstimateMsg)]
        for m in estimates:
            assert_finite(m)
        # 0: normal. H: the jump to 1e307 m overflows: dropped, restart. 2H: restarted at
        # the measured 1e305 m (finite, published). 3H: the jump back overflows: dropped,
        # restart. 4H: restarted at the measured 0 m.
        assert [m.header.stamp.nanosec for m in estimates] == [0, 2 * H_NS, 4 * H_NS]
        # x_v = r (φ + θ) = r (0.001 + 0.01) rad (encoders relative to the body), r < 0.5 m.
        assert 0.0 < estimates[-1].x_v < 0.006
        assert node.diagnostics.dropped[('imu', 'invalid')] >= 1
    finally:
        node.destroy_node()
