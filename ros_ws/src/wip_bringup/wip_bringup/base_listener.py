"""check_base's listener: the base's JointState and Imu, kept for a few seconds."""

from __future__ import annotations

import collections
import contextlib
import math
import signal
import threading
import time

from wip_control.nodes.hardware_inputs import mounting_inverse

from .base_checks import (AUTO_STILL_BAND, body_angles, Conventions, Reading, TWO_PI,
                          unwrap_mean)

#: The base's topics check_base listens to (before remapping).
LISTENED_TOPICS = ('/joint_states', '/imu/data')


@contextlib.contextmanager
def _sigint_deferred():
    """Hold a SIGINT until the block ends, then raise it there (the main thread only).

    A KeyboardInterrupt inside rclpy's Executor constructor leaves an object whose
    ``__del__`` prints a traceback; held, the interrupt comes after the constructor, and the
    spinning thread started in the block inherits the signal blocked.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, previous)


class BaseListener:
    """Listener of the base's JointState and Imu.

    Subscribes to the base's JointState and Imu in a background thread and keeps the
    samples of the last few seconds.
    """

    HISTORY = 5.0  # [s]

    def __init__(self, conventions: Conventions, remaps: list[tuple[str, str]],
                 domain_id: int | None = None) -> None:
        import rclpy
        self.conventions = conventions
        self.inverse_mount = mounting_inverse(conventions.mounting)
        self._rclpy = rclpy
        args = ['--ros-args']
        for source, target in remaps:
            args += ['-r', f'{source}:={target}']
        self.context = rclpy.Context()
        self.node = self.executor = self.thread = None
        self._stop = threading.Event()
        rclpy.init(args=args, context=self.context,
                   **({'domain_id': domain_id} if domain_id is not None else {}))
        try:
            with _sigint_deferred():
                self._start()
        except BaseException:
            # A SIGINT here (the subscriptions are visible before the thread runs) must
            # not leave the thread spinning into interpreter shutdown: a daemon thread
            # inside rclpy's C++ then aborts the process ('terminate called without an
            # active exception'), seen under load in the ros2 run contract test.
            self.close()
            raise

    def _start(self) -> None:
        """Start the node, its subscriptions and the thread that spins it."""
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import qos_profile_sensor_data
        from sensor_msgs.msg import Imu, JointState
        self.node = self._rclpy.create_node('check_base', context=self.context,
                                            start_parameter_services=False)
        self.lock = threading.Lock()
        self.joints: collections.deque = collections.deque()   # (t, names, positions)
        self.imu: collections.deque = collections.deque()      # (t, q, gravity or None)
        # Sensor-data QoS (best effort) matches reliable and best-effort publishers.
        self.node.create_subscription(JointState, LISTENED_TOPICS[0], self._on_joints,
                                      qos_profile_sensor_data)
        self.node.create_subscription(Imu, LISTENED_TOPICS[1], self._on_imu,
                                      qos_profile_sensor_data)
        self.topics = tuple(self.node.resolve_topic_name(t) for t in LISTENED_TOPICS)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set() and self._rclpy.ok(context=self.context):
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # noqa: BLE001 - shutting down
                if self._stop.is_set():
                    return
                raise

    def _trim(self, queue: collections.deque, now: float) -> None:
        while queue and queue[0][0] < now - self.HISTORY:
            queue.popleft()

    def _on_joints(self, msg) -> None:
        now = time.monotonic()
        with self.lock:
            self.joints.append((now, tuple(msg.name), tuple(float(p) for p in msg.position)))
            self._trim(self.joints, now)

    def _on_imu(self, msg) -> None:
        now = time.monotonic()
        q = msg.orientation
        quaternion = (q.x, q.y, q.z, q.w)
        if msg.orientation_covariance[0] == -1.0 or not all(map(math.isfinite, quaternion)) \
                or sum(v * v for v in quaternion) < 0.5:
            quaternion = None
        a = msg.linear_acceleration
        gravity = (a.x, a.y, a.z)
        if msg.linear_acceleration_covariance[0] == -1.0 or not all(
                map(math.isfinite, gravity)) or sum(v * v for v in gravity) < 1.0:
            gravity = None
        with self.lock:
            self.imu.append((now, quaternion, gravity))
            self._trim(self.imu, now)

    def have_data(self) -> bool:
        with self.lock:
            return bool(self.joints) and bool(self.imu)

    def reading(self, window: float) -> Reading:
        """Means over the last ``window`` seconds (at least the newest sample of each)."""
        now = time.monotonic()
        c = self.conventions
        with self.lock:
            joints = [j for j in self.joints if j[0] >= now - window] or list(self.joints)[-1:]
            imu = [m for m in self.imu if m[0] >= now - window] or list(self.imu)[-1:]
        names = joints[-1][1] if joints else ()
        left = right = None
        lefts, rights = [], []
        for _, sample_names, positions in joints:
            if len(positions) != len(sample_names):
                continue
            index = {n: i for i, n in enumerate(sample_names)}
            if c.left_joint in index:
                lefts.append(c.left_sign * positions[index[c.left_joint]])
            if c.right_joint in index:
                rights.append(c.right_sign * positions[index[c.right_joint]])
        if lefts:
            left = sum(lefts) / len(lefts)
        if rights:
            right = sum(rights) / len(rights)
        angles = [body_angles(q, self.inverse_mount) for _, q, _ in imu if q is not None]
        if angles:
            roll = unwrap_mean([a[0] for a in angles])
            pitch = sum(a[1] for a in angles) / len(angles)
            yaw = unwrap_mean([a[2] for a in angles])
        else:
            roll = pitch = yaw = float('nan')
        gravities = [g for _, _, g in imu if g is not None]
        gravity = (tuple(sum(g[i] for g in gravities) / len(gravities) for i in range(3))
                   if gravities else None)
        return Reading(left, right, roll, pitch, yaw, gravity, tuple(names),
                       len(joints) + len(imu))

    def still(self, duration: float) -> bool:
        """--auto: every reading within AUTO_STILL_BAND over the last ``duration`` s."""
        now = time.monotonic()
        with self.lock:
            joints = [j for j in self.joints if j[0] >= now - duration]
            imu = [m for m in self.imu if m[0] >= now - duration]
            if not self.joints or not self.imu or \
                    self.joints[0][0] > now - duration or self.imu[0][0] > now - duration:
                return False
        series: list[list[float]] = []
        for _, names, positions in joints:
            for i, value in enumerate(positions):
                while len(series) <= i:
                    series.append([])
                series[i].append(value)
        angles = [body_angles(q, self.inverse_mount) for _, q, _ in imu if q is not None]
        for k in range(3):
            series.append([math.remainder(a[k] - angles[0][k], TWO_PI) for a in angles])
        return all(max(s) - min(s) <= AUTO_STILL_BAND for s in series if s)

    def close(self) -> None:
        self._stop.set()
        if self.thread is not None:
            deadline = time.monotonic() + 2.0
            while True:
                try:
                    self.thread.join(timeout=max(0.0, deadline - time.monotonic()))
                    break
                except RuntimeError:  # start() interrupted before the thread said it runs
                    if time.monotonic() > deadline:
                        break
                    time.sleep(0.01)
        if self.executor is not None:
            # Bounded: rclpy's default waits without limit for a spin_once still running
            # in the listener thread.
            self.executor.shutdown(timeout_sec=2.0)
        if self.node is not None:
            self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)
