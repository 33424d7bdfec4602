"""What rclpy costs before any control math.

A process that only receives a base's sensor stream (``sensor_msgs/JointState`` and ``Imu`` at 200
Hz each, as the stand-in base sends them) with empty callbacks, on the EventsExecutor the
controllers use: taken as message objects (rclpy builds each), or serialized (``raw=True``, as the
eso node takes them and decodes only then).

``scripts/bench`` prints its CPU share beside the controllers': the part of the
controllers' cost that no change to the nodes can remove, short of not receiving the
sensors. ``loop``: taken serialized, and each IMU sample answered with one effort command
(std_msgs/Float64MultiArray, serialized, reliable, to a subscription in the base's process,
as the mixer sends it): the floor of any controller process, which must also send.
Run as ``python -m wip_tools.rclpy_floor publish|receive|receive-raw|loop SECONDS``;
measured by :func:`measure_floor`, which starts both in a fresh DDS domain and ends them.
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import time

RATE = 200.0  # [Hz] of each sensor stream
WARM_UP = 2.0  # [s] before measuring: discovery and the first messages
#: Topic of the effort command in the ``loop`` case.
COMMAND_TOPIC = '/effort_controller/commands'


def _publish(seconds: float) -> None:
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray
    from wip_runtime.qos import RELIABLE_QOS
    rclpy.init()
    node = rclpy.create_node('floor_base')
    node.create_subscription(Float64MultiArray, COMMAND_TOPIC, lambda _msg: None,
                             RELIABLE_QOS)
    joints = node.create_publisher(JointState, '/joint_states', qos_profile_sensor_data)
    imu = node.create_publisher(Imu, '/imu/data', qos_profile_sensor_data)
    state = JointState(name=['wheel_r', 'wheel_l'], position=[0.0, 0.0], velocity=[0.0, 0.0],
                       effort=[0.0, 0.0])
    sample = Imu()

    def tick() -> None:
        joints.publish(state)
        imu.publish(sample)
    node.create_timer(1.0 / RATE, tick)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)


def _receive(seconds: float, raw: bool, reply: bool = False) -> dict:
    import rclpy
    from rclpy.qos import qos_profile_sensor_data
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, JointState
    from std_msgs.msg import Float64MultiArray
    from wip_runtime.executors import make_executor
    from wip_runtime.qos import RELIABLE_QOS
    rclpy.init()
    node = rclpy.create_node('floor_receiver')
    count = [0]

    def received(_msg) -> None:
        count[0] += 1
    on_imu = received
    if reply:
        command = node.create_publisher(Float64MultiArray, COMMAND_TOPIC, RELIABLE_QOS)
        payload = serialize_message(Float64MultiArray(data=[0.0, 0.0]))

        def on_imu(_msg) -> None:
            count[0] += 1
            command.publish(payload)
    node.create_subscription(JointState, '/joint_states', received, qos_profile_sensor_data,
                             raw=raw)
    node.create_subscription(Imu, '/imu/data', on_imu, qos_profile_sensor_data, raw=raw)
    executor = make_executor()
    executor.add_node(node)
    end = time.monotonic() + WARM_UP
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
    first, usage, start = count[0], resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
    while time.monotonic() < start + seconds:
        executor.spin_once(timeout_sec=0.1)
    after, wall = resource.getrusage(resource.RUSAGE_SELF), time.monotonic() - start
    cpu = (after.ru_utime - usage.ru_utime) + (after.ru_stime - usage.ru_stime)
    messages = count[0] - first
    return {'executor': type(executor).__name__, 'raw': raw, 'reply': reply,
            'messages_per_s': messages / wall,
            'cpu_fraction': cpu / wall,
            'cpu_per_message_us': 1e6 * cpu / messages if messages else None,
            'context_switches_per_s': (after.ru_nvcsw - usage.ru_nvcsw) / wall}


def measure_floor(seconds: float = 10.0, raw: bool = False, reply: bool = False) -> dict:
    """Both processes in a DDS domain of their own; the receiver's measurement.

    ``raw``: the messages are taken serialized; ``reply``: serialized, and each IMU
    sample answered with an effort command (the ``loop`` case).
    """
    from wip_bringup.processes import choose_domain_id, graph_environment
    env = graph_environment(choose_domain_id())
    module = [sys.executable, '-m', 'wip_tools.rclpy_floor']
    base = subprocess.Popen(module + ['publish', str(seconds + WARM_UP + 8.0)], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        mode = 'loop' if reply else 'receive-raw' if raw else 'receive'
        receiver = subprocess.run(module + [mode, str(seconds)],
                                  env=env,
                                  capture_output=True, text=True,
                                  timeout=seconds + WARM_UP + 60.0)
    finally:
        base.kill()
        base.wait()
    if receiver.returncode != 0:
        return {'failed': receiver.stderr.strip().splitlines()[-1:]}
    return json.loads(receiver.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 2 or argv[0] not in ('publish', 'receive', 'receive-raw', 'loop'):
        print('usage: python -m wip_tools.rclpy_floor publish|receive|receive-raw|loop '
              'SECONDS', file=sys.stderr)
        return 2
    from wip_runtime.launched import end_with_launcher
    end_with_launcher()
    if argv[0] == 'publish':
        _publish(float(argv[1]))
    else:
        print(json.dumps(_receive(float(argv[1]), raw=argv[0] != 'receive',
                                  reply=argv[0] == 'loop')))
    return 0


if __name__ == '__main__':
    sys.exit(main())
