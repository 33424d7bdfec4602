"""``scripts/check_base``: check a real base's signs, joint names and IMU mounting by hand.

Before the controllers drive a real base, this tool reads the base's sensor_msgs/JointState
and sensor_msgs/Imu with the parameters the eso node will use (the same ``--scenario``,
``--params-file`` and ``--remap`` as ``scripts/run_graph --mode hardware``), guides you
through five motions made by hand, and reports, as numbers, what each reading did against
what the parameters predict. It never commands the wheels.

Steps
-----
0. **connect**: both topics arrive; ``left_joint`` and ``right_joint`` are in the
   JointState (with positions); the Imu has an orientation.
1. **upright**: hold the robot upright and still. With ``imu_mounting_rpy`` the body must
   read roll ≈ 0 and pitch ≈ 0 (|·| < 0.15 rad); if the Imu reports a linear acceleration,
   the measured gravity direction in the IMU frame is compared with the one the mounting
   predicts (angle < 0.2 rad).
2. **tilt**: tilt the robot forward (its top toward the direction it drives) by about 10°
   and hold it. Expected: pitch +0.17 rad (sign positive, 0.05-0.5 rad accepted), roll
   and yaw unchanged; a tilt that shows up as roll means the mounting's yaw is wrong. The
   distance rolled x_v must not change (the wheels did not roll): with encoders that
   measure against the body, x_v = r ((φl + φr)/2 + θ) stays, and a change of −r·Δθ
   means ``encoders_relative_to_body`` is wrong (reported as a warning: a hand may also
   roll the robot a little).
3. **left wheel**: lift the robot (wheels free) and roll the LEFT wheel forward (the
   direction that drives the robot forward) by one turn. Expected: φl +2π rad (a travel
   r·Δφ = 2πr), φr unchanged. A negative change: ``left_wheel_sign`` is wrong; the right
   joint moving instead: the joint names are swapped; far from one turn: the joint is not
   in radians of the wheel (gear ratio?).
4. **right wheel**: the same for the right wheel.
5. **turn**: put the robot down and turn it counter-clockwise (seen from above) by about
   90° on the spot. Expected: IMU yaw +π/2 (0.5-1.5 times accepted), and the wheel
   odometry's yaw r (Δφr − Δφl)/d within 20 % of the IMU's (else ``model.track_width`` or
   ``model.wheel_radius`` is off: the report gives the track width that would match).

Modes
-----
interactive (default): each step waits for Enter twice (ready, done) on stdin; ``s``
skips the step, ``q`` quits. ``--script``: the same from a pipe, with machine-readable
prompt lines ``CHECK_BASE WAIT <step> <ready|done>`` on stdout. ``--auto``: no input;
each step waits until the readings are still, then for the motion (a change of at least
a third of the expected one) and until they are still again (``--timeout`` per step);
a motion starts from the upright pose of step 1 (the robot put back after the tilt).

Each reading is the mean over the last ``--window`` seconds (default 0.3 s).

Output: one line per check (``OK``, ``WARN``, ``FAIL``, ``SKIP``) with the numbers, and
with ``--json FILE`` all of it as JSON. Exit status: 0 every check OK (warnings allowed),
1 a check failed (also: no data from the base within the timeout), 2 bad arguments,
3 internal error, 130 interrupted.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import math
import signal
import sys
import threading
import time
from typing import Any, Callable, TextIO

from wip_control.core.config import ConfigError
from wip_control.core.controller_settings import load_controller_settings
from wip_control.nodes.conversions import quaternion_from_euler
from wip_control.nodes.hardware_inputs import (check_mounting_rpy, check_wheel_sign,
                                               mounting_inverse, quaternion_multiply,
                                               rotate_vector_into)

from .hardware import hardware_parameters, load_params_file, node_parameters, parse_remap
from .params_check import check_run_inputs, unmatched_remaps
from .params_files import CONTROLLER_NODES
from .launcher import GraphError, use_user_ros_environment
from wip_control.tools.cli import add_exit_codes

# The exit-code table of every tool (wip_control.tools.cli); no data from the base is a
# failed check (the connection check).
EXIT_OK, EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_NO_DATA = EXIT_FAILED
OK, WARN, FAIL, SKIP = 'OK', 'WARN', 'FAIL', 'SKIP'
TWO_PI = 2.0 * math.pi
#: Body roll/pitch accepted as "upright" [rad] (a robot held by hand, about 9°).
UPRIGHT_TOLERANCE = 0.15
#: Gravity direction vs the mounting's prediction [rad] (11°: a hand-held robot).
GRAVITY_TOLERANCE = 0.2
#: The expected forward tilt [rad] (about 10°) and what counts as one.
TILT_EXPECTED = math.radians(10.0)
TILT_RANGE = (0.05, 0.5)
#: Changes below this [rad] count as "did not move" (wheel joints, IMU angles).
STILL_CHANGE = 0.05
#: A "turn" or "one wheel turn" within this factor of the expected angle is accepted.
MAGNITUDE_RANGE = (0.5, 1.5)
#: Odometry yaw vs IMU yaw accepted ratio.
ODOMETRY_RATIO_RANGE = (0.8, 1.25)
#: --auto: still means every angle within this band [rad] over the stillness window [s].
AUTO_STILL_BAND = 0.01
AUTO_STILL_TIME = 0.5


# ----------------------------------------------------------------------------- conventions

@dataclasses.dataclass(frozen=True)
class Conventions:
    """What the eso node assumes about the base (its parameters)."""

    left_joint: str
    right_joint: str
    left_sign: float
    right_sign: float
    mounting: tuple[float, float, float]
    wheel_radius: float
    track_width: float
    relative_to_body: bool

    @classmethod
    def from_parameters(cls, values: dict[str, Any]) -> 'Conventions':
        """From the eso node's flattened parameters (as :func:`eso_parameters` gives)."""
        try:
            return cls(
                left_joint=str(values.get('left_joint', 'left_wheel_joint')),
                right_joint=str(values.get('right_joint', 'right_wheel_joint')),
                left_sign=check_wheel_sign('left_wheel_sign', values.get('left_wheel_sign', 1)),
                right_sign=check_wheel_sign('right_wheel_sign',
                                            values.get('right_wheel_sign', 1)),
                mounting=check_mounting_rpy('imu_mounting_rpy',
                                            values.get('imu_mounting_rpy', (0.0, 0.0, 0.0))),
                wheel_radius=float(values['model.wheel_radius']),
                track_width=float(values['model.track_width']),
                relative_to_body=bool(values.get('encoders_relative_to_body', True)))
        except ValueError as err:
            raise GraphError(f'parameters: {err}', EXIT_USAGE) from err


def eso_parameters(scenario_path: str | None, params_files: list[str]) -> dict[str, Any]:
    """Return the eso node's parameters in hardware mode: the scenario's, then the files'."""
    try:
        scenario = load_controller_settings(scenario_path)
    except ConfigError as err:
        raise GraphError(str(err), EXIT_USAGE) from err
    extra = [load_params_file(path) for path in params_files]
    generated = hardware_parameters(scenario)
    # The same files run_graph --mode hardware takes: checked against every controller.
    for line in check_run_inputs(params_files, extra, CONTROLLER_NODES, generated, []):
        print(f'check_base: warning: {line}', file=sys.stderr)
    return node_parameters('eso', generated, extra)


# ----------------------------------------------------------------------------- readings

@dataclasses.dataclass
class Reading:
    """Mean readings over a window, in the eso node's conventions."""

    left: float | None         # φl [rad] (signed), None if the joint is missing
    right: float | None
    roll: float                # body roll, pitch, yaw [rad] after the mounting correction
    pitch: float
    yaw: float
    gravity: tuple[float, float, float] | None   # specific force in the IMU frame [m/s²]
    names: tuple[str, ...]
    samples: int


def body_angles(q_imu, inverse_mount) -> tuple[float, float, float]:
    """(roll, pitch, yaw) [rad] of the body from the IMU quaternion (x, y, z, w)."""
    x, y, z, w = q_imu
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    q = (x / norm, y / norm, z / norm, w / norm)
    if inverse_mount is not None:
        q = quaternion_multiply(q, inverse_mount)
    x, y, z, w = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def angle_between(a, b) -> float:
    """Angle [rad] between two 3-vectors."""
    dot = sum(p * q for p, q in zip(a, b))
    na = math.sqrt(sum(p * p for p in a))
    nb = math.sqrt(sum(q * q for q in b))
    return math.acos(max(-1.0, min(1.0, dot / (na * nb))))


def unwrap_mean(angles: list[float]) -> float:
    """Mean of angles [rad] near each other (yaw may cross ±π)."""
    ref = angles[0]
    return ref + sum(math.remainder(a - ref, TWO_PI) for a in angles) / len(angles)


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


# ----------------------------------------------------------------------------- checks

@dataclasses.dataclass
class Check:
    step: str
    name: str
    status: str
    measured: Any
    expected: Any
    message: str

    def line(self) -> str:
        return f'{self.status:4s} {self.step}/{self.name}: {self.message}'


def _fmt(value: float | None, unit: str = 'rad') -> str:
    return 'n/a' if value is None or not math.isfinite(value) else f'{value:+.3f} {unit}'


def check_connection(reading: Reading, c: Conventions) -> list[Check]:
    out = []
    for side, joint, value in (('left', c.left_joint, reading.left),
                               ('right', c.right_joint, reading.right)):
        if joint in reading.names and value is not None:
            out.append(Check('connect', f'{side}_joint', OK, joint, joint,
                             f'joint {joint!r} found in {list(reading.names)}'))
        else:
            out.append(Check('connect', f'{side}_joint', FAIL, list(reading.names), joint,
                             f'joint {joint!r} ({side}_joint) not in the JointState (names: '
                             f'{list(reading.names)}): set {side}_joint to one of them'))
    if math.isfinite(reading.pitch):
        out.append(Check('connect', 'imu_orientation', OK, True, True, 'IMU orientation '
                         'received'))
    else:
        out.append(Check('connect', 'imu_orientation', FAIL, False, True, 'the Imu carries no '
                         'orientation (orientation_covariance[0] = -1 or a zero quaternion): '
                         'the eso node needs one (use an orientation filter, e.g. '
                         'imu_filter_madgwick, with an ENU world frame)'))
    return out


def check_upright(reading: Reading, c: Conventions) -> list[Check]:
    out = []
    bad = max(abs(reading.roll), abs(reading.pitch))
    status = OK if bad < UPRIGHT_TOLERANCE else FAIL
    message = (f'body roll {_fmt(reading.roll)}, pitch {_fmt(reading.pitch)} with '
               f'imu_mounting_rpy {list(c.mounting)}: expected 0 +- {UPRIGHT_TOLERANCE}')
    if status == FAIL:
        message += ('; the mounting rotation does not match the IMU (an IMU upside down '
                    'reads roll +-pi: add pi to the mounting roll)')
    out.append(Check('upright', 'body_level', status, [reading.roll, reading.pitch],
                     [0.0, 0.0], message))
    if reading.gravity is None:
        out.append(Check('upright', 'gravity', SKIP, None, None, 'the Imu reports no linear '
                         'acceleration: gravity direction not checked'))
    else:
        g = reading.gravity
        expected = rotate_vector_into(quaternion_from_euler(*c.mounting), (0.0, 0.0, 1.0))
        angle = angle_between(g, expected)
        norm = math.sqrt(sum(v * v for v in g))
        unit = tuple(v / norm for v in g)
        status = OK if angle < GRAVITY_TOLERANCE else FAIL
        out.append(Check('upright', 'gravity', status, list(unit), list(expected),
                         f'gravity (specific force) in the IMU frame '
                         f'({unit[0]:+.2f}, {unit[1]:+.2f}, {unit[2]:+.2f}), expected from the '
                         f'mounting ({expected[0]:+.2f}, {expected[1]:+.2f}, '
                         f'{expected[2]:+.2f}): {angle:.3f} rad apart'
                         + ('' if status == OK else
                            f' > {GRAVITY_TOLERANCE}: imu_mounting_rpy is wrong')))
    return out


def check_tilt(before: Reading, after: Reading, c: Conventions) -> list[Check]:
    d_pitch = after.pitch - before.pitch
    d_roll = math.remainder(after.roll - before.roll, TWO_PI)
    low, high = TILT_RANGE
    if low <= d_pitch <= high:
        status, advice = OK, ''
    elif -high <= d_pitch <= -low:
        status, advice = FAIL, ('sign wrong: the pitch decreased; the IMU mounting '
                                '(imu_mounting_rpy) is turned half a turn about z')
    elif abs(d_roll) >= low:
        status, advice = FAIL, ("the tilt shows as roll: the mounting's yaw is off by a "
                                'quarter turn')
    else:
        status, advice = FAIL, f'no forward tilt of {low}-{high} rad seen'
    out = [Check('tilt', 'pitch', status, d_pitch, TILT_EXPECTED,
                 f'pitch change {_fmt(d_pitch)}, expected about {TILT_EXPECTED:+.3f} rad '
                 f'(positive); roll change {_fmt(d_roll)}' + (f': {advice}' if advice else ''))]
    if None not in (before.left, before.right, after.left, after.right):
        r = c.wheel_radius
        d_left, d_right = after.left - before.left, after.right - before.right
        mean = 0.5 * (d_left + d_right)
        d_xv = r * (mean + (d_pitch if c.relative_to_body else 0.0))
        other = r * (mean + (0.0 if c.relative_to_body else d_pitch))
        fits_other = abs(other) < 0.5 * abs(d_xv)
        opposite = d_left * d_right < 0.0 and min(abs(d_left), abs(d_right)) > 0.5 * low
        status = OK if abs(d_xv) <= 0.3 * r * max(abs(d_pitch), low) or not (
            fits_other or opposite) else WARN
        message = (f'distance rolled x_v changed by {_fmt(d_xv, "m")} while tilting '
                   f'(expected 0: the wheels did not roll)')
        if status == WARN and opposite:
            message += (f'; the two wheel joints turned in opposite directions '
                        f'({_fmt(d_left)}, {_fmt(d_right)}) as the body tilted: a wheel sign '
                        'is wrong (see the wheel steps)')
        elif status == WARN:
            message += (f'; with encoders_relative_to_body '
                        f'{str(not c.relative_to_body).lower()} it would be '
                        f'{_fmt(other, "m")}: check that parameter')
        out.append(Check('tilt', 'encoders_relative_to_body', status, d_xv, 0.0, message))
    return out


def check_wheel(side: str, before: Reading, after: Reading, c: Conventions) -> list[Check]:
    step = f'{side}_wheel'
    if None in (before.left, before.right, after.left, after.right):
        return [Check(step, 'joint', FAIL, None, None, 'wheel joints missing: see connect')]
    d = {'left': after.left - before.left, 'right': after.right - before.right}
    other = 'right' if side == 'left' else 'left'
    moved, still = d[side], d[other]
    sign_param = f'{side}_wheel_sign'
    current = c.left_sign if side == 'left' else c.right_sign
    r = c.wheel_radius
    low, high = MAGNITUDE_RANGE
    out = []
    if abs(still) > STILL_CHANGE and abs(still) > abs(moved):
        out.append(Check(step, 'joint_name', FAIL, d, {side: TWO_PI, other: 0.0},
                         f'the {other} joint moved ({_fmt(still)}) and the {side} one '
                         f'({_fmt(moved)}): left_joint and right_joint are swapped (set '
                         f'left_joint: {c.right_joint!r}, right_joint: {c.left_joint!r})'))
        return out
    out.append(Check(step, 'joint_name', OK if abs(still) <= STILL_CHANGE else WARN, still, 0.0,
                     f'{other} joint change {_fmt(still)} (expected 0)'))
    if abs(moved) < STILL_CHANGE:
        out.append(Check(step, 'sign', FAIL, moved, TWO_PI, f'the {side} joint did not move '
                         f'({_fmt(moved)})'))
        return out
    if moved < 0.0:
        out.append(Check(step, 'sign', FAIL, moved, TWO_PI,
                         f'{side} wheel: {_fmt(moved)} ({_fmt(r * moved, "m")} of travel) for '
                         f'one turn forward, expected {TWO_PI:+.3f} rad (+{TWO_PI * r:.3f} m '
                         f'= 2 pi r): sign wrong: set {sign_param} to {int(-current)}'))
    else:
        out.append(Check(step, 'sign', OK, moved, TWO_PI,
                         f'{side} wheel: {_fmt(moved)} ({_fmt(r * moved, "m")} of travel) for '
                         f'one turn forward, expected {TWO_PI:+.3f} rad (+{TWO_PI * r:.3f} m '
                         f'= 2 pi r)'))
    ratio = abs(moved) / TWO_PI
    out.append(Check(step, 'magnitude', OK if low <= ratio <= high else WARN, ratio, 1.0,
                     f'{ratio:.2f} turns measured for about 1'
                     + ('' if low <= ratio <= high else
                        ': is the joint position in radians of the WHEEL (a gear ratio?), '
                        'and was it one turn?')))
    return out


def check_turn(before: Reading, after: Reading, c: Conventions) -> list[Check]:
    d_yaw = math.remainder(after.yaw - before.yaw, TWO_PI)
    expected = math.pi / 2
    low, high = MAGNITUDE_RANGE
    if low * expected <= d_yaw <= high * expected:
        status, advice = OK, ''
    elif -high * expected <= d_yaw <= -low * expected:
        status, advice = FAIL, ('sign wrong: the yaw decreased for a counter-clockwise '
                                'turn: the IMU mounting is upside down (add pi to its roll)')
    else:
        status, advice = FAIL, 'no quarter turn seen'
    out = [Check('turn', 'imu_yaw', status, d_yaw, expected,
                 f'IMU yaw change {_fmt(d_yaw)}, expected about {expected:+.3f} rad '
                 '(counter-clockwise positive)' + (f': {advice}' if advice else ''))]
    if None not in (before.left, before.right, after.left, after.right) and status == OK:
        d_odo = c.wheel_radius * ((after.right - before.right)
                                  - (after.left - before.left)) / c.track_width
        ratio = d_odo / d_yaw
        lo, hi = ODOMETRY_RATIO_RANGE
        good = lo <= ratio <= hi
        message = (f'wheel odometry yaw r (dphi_r - dphi_l)/d = {_fmt(d_odo)} vs IMU '
                   f'{_fmt(d_yaw)} (ratio {ratio:.2f})')
        if not good:
            if ratio <= 0.0:
                message += ': opposite signs: a wheel sign or the joint names are wrong'
            else:
                message += (f': model.track_width {c.track_width:g} m or model.wheel_radius '
                            f'{c.wheel_radius:g} m is off (track width '
                            f'{c.track_width * ratio:.3f} m would match)')
        out.append(Check('turn', 'odometry', OK if good else FAIL, d_odo, d_yaw, message))
    return out


# ----------------------------------------------------------------------------- the session

STEPS = (
    ('upright', 'Hold the robot upright (balanced, wheels on the ground) and still.', None),
    ('tilt', 'Tilt the robot FORWARD (its top toward the direction it drives) by about '
             '10 degrees and hold it there.', 'pitch'),
    ('left_wheel', 'Lift the robot so that the wheels turn freely. Roll the LEFT wheel '
                   'FORWARD (the way that drives the robot forward) by one full turn.',
     'left'),
    ('right_wheel', 'Still lifted: roll the RIGHT wheel FORWARD by one full turn.', 'right'),
    ('turn', 'Put the robot on the ground and turn it COUNTER-CLOCKWISE (seen from above) '
             'by about 90 degrees on the spot.', 'yaw'),
)
#: --auto: the motion is seen when its quantity changed by this much [rad].
AUTO_MOTION = {'pitch': TILT_EXPECTED / 3, 'left': TWO_PI / 3, 'right': TWO_PI / 3,
               'yaw': math.pi / 6}


class Aborted(Exception):
    pass


class Session:
    """One check of a base; see the module docstring."""

    def __init__(self, listener: BaseListener, conventions: Conventions, mode: str,
                 window: float, timeout: float, stdin: TextIO, stdout: TextIO) -> None:
        self.listener = listener
        self.c = conventions
        self.mode = mode
        self.window = window
        self.timeout = timeout
        self.stdin = stdin
        self.stdout = stdout
        self.checks: list[Check] = []
        self.upright_pitch: float | None = None

    def say(self, text: str) -> None:
        print(text, file=self.stdout, flush=True)

    def confirm(self, step: str, phase: str, prompt: str) -> bool:
        """Wait for the user; False: skip the step."""
        if self.mode == 'script':
            self.say(f'CHECK_BASE WAIT {step} {phase}')
        else:
            self.say(f'  -> {prompt} [Enter; s = skip, q = quit]')
        line = self.stdin.readline()
        if not line:
            raise Aborted('end of input')
        answer = line.strip().lower()
        if answer == 'q':
            raise Aborted('quit')
        return answer != 's'

    def wait_for(self, condition: Callable[[], bool], timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if condition():
                return True
            time.sleep(0.05)
        return False

    @staticmethod
    def quantity(reading: Reading, name: str) -> float | None:
        if name == 'pitch':
            return reading.pitch
        if name == 'yaw':
            return reading.yaw
        if name == 'left':
            return reading.left
        return reading.right

    def upright_and_still(self) -> bool:
        """--auto: the start pose of a motion: still, and as level as in step 1."""
        if not self.listener.still(AUTO_STILL_TIME):
            return False
        level = self.upright_pitch if self.upright_pitch is not None else 0.0
        return abs(self.listener.reading(self.window).pitch - level) < STILL_CHANGE

    def auto_motion(self, quantity: str) -> tuple[Reading, Reading] | None:
        """--auto: upright and still -> before; the quantity moves; still again -> after."""
        if not self.wait_for(self.upright_and_still, self.timeout):
            return None
        before = self.listener.reading(self.window)
        start = self.quantity(before, quantity)
        if start is None:
            return before, before

        def moved() -> bool:
            now = self.quantity(self.listener.reading(0.1), quantity)
            if now is None:
                return False
            change = (math.remainder(now - start, TWO_PI) if quantity == 'yaw'
                      else now - start)
            return abs(change) >= AUTO_MOTION[quantity]
        if not self.wait_for(moved, self.timeout):
            return None
        if not self.wait_for(lambda: self.listener.still(AUTO_STILL_TIME), self.timeout):
            return None
        return before, self.listener.reading(self.window)

    def run(self) -> int:
        c = self.c
        self.say(f'check_base: {c.left_joint!r} (sign {int(c.left_sign):+d}) and '
                 f'{c.right_joint!r} (sign {int(c.right_sign):+d}) on '
                 f'{self.listener.topics[0]}, IMU on {self.listener.topics[1]} mounted '
                 f'{list(c.mounting)} rad; wheel radius {c.wheel_radius:g} m, track width '
                 f'{c.track_width:g} m')
        if not self.wait_for(self.listener.have_data, self.timeout):
            self.say(f'FAIL connect: no JointState on {self.listener.topics[0]} and Imu on '
                     f'{self.listener.topics[1]} within {self.timeout:g} s (is the base '
                     'running, on this ROS_DOMAIN_ID? remap the topics with --remap)')
            return EXIT_NO_DATA
        time.sleep(self.window)
        self.add(check_connection(self.listener.reading(self.window), c))
        for number, (step, prompt, quantity) in enumerate(STEPS, start=1):
            self.say(f'\nstep {number}/{len(STEPS)} ({step}): {prompt}')
            if quantity is None:           # a pose, not a motion
                if self.mode == 'auto':
                    if not self.wait_for(lambda: self.listener.still(AUTO_STILL_TIME),
                                         self.timeout):
                        self.add([Check(step, 'timeout', FAIL, None, None,
                                        'the readings never stood still')])
                        continue
                elif not self.confirm(step, 'done', 'when it is upright and still'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                upright = self.listener.reading(self.window)
                self.upright_pitch = upright.pitch
                self.add(check_upright(upright, c))
                continue
            if self.mode == 'auto':
                pair = self.auto_motion(quantity)
                if pair is None:
                    self.add([Check(step, 'timeout', FAIL, None, None,
                                    f'no motion seen within {self.timeout:g} s')])
                    continue
                before, after = pair
            else:
                if not self.confirm(step, 'ready', 'when ready, before the motion'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                before = self.listener.reading(self.window)
                if not self.confirm(step, 'done', 'when done, holding still'):
                    self.add([Check(step, 'skipped', SKIP, None, None, 'skipped')])
                    continue
                after = self.listener.reading(self.window)
            if step == 'tilt':
                self.add(check_tilt(before, after, c))
            elif step == 'turn':
                self.add(check_turn(before, after, c))
            else:
                self.add(check_wheel(step.split('_')[0], before, after, c))
        failed = [k for k in self.checks if k.status == FAIL]
        self.say(f'\n{"ALL OK" if not failed else f"{len(failed)} CHECK(S) FAILED"}: '
                 f'{sum(k.status == OK for k in self.checks)} OK, '
                 f'{sum(k.status == WARN for k in self.checks)} WARN, {len(failed)} FAIL, '
                 f'{sum(k.status == SKIP for k in self.checks)} SKIP')
        return EXIT_FAILED if failed else EXIT_OK

    def add(self, checks: list[Check]) -> None:
        for check in checks:
            self.checks.append(check)
            self.say(check.line())


#: The base's topics check_base listens to (before remapping).
LISTENED_TOPICS = ('/joint_states', '/imu/data')


def split_ros_arguments(argv: list[str]) -> tuple[list[str], list[str]]:
    """Split a command line into the tool's own arguments and remappings.

    (the tool's own arguments, 'FROM:=TO' remappings) of a command line that may hold
    ``--ros-args ... [--]`` blocks, as ``ros2 run`` passes them.
    """
    own: list[str] = []
    remaps: list[str] = []
    in_ros = False
    words = iter(argv)
    for word in words:
        if word == '--ros-args':
            in_ros = True
        elif in_ros and word == '--':
            in_ros = False
        elif in_ros and word in ('-r', '--remap'):
            remaps.append(next(words, ''))
        elif not in_ros:
            own.append(word)
    return own, remaps


EXAMPLES = """\
Examples
--------
    scripts/check_base --params-file my_base.yaml              # guided, by hand
    scripts/check_base --params-file my_base.yaml --remap /imu/data:=/imu/filtered
    scripts/check_base --params-file my_base.yaml --json checks.json"""


def main(argv: list[str] | None = None, stdin: TextIO | None = None,
         stdout: TextIO | None = None) -> int:
    parser = argparse.ArgumentParser(prog='scripts/check_base', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog=EXAMPLES)
    parser.add_argument('--scenario', help='scenario YAML whose controller_model gives '
                        'wheel_radius and track_width (default: paper Section V)')
    parser.add_argument('--params-file', action='append', default=[], dest='params_files',
                        metavar='FILE', help="the base's params file(s), as for run_graph "
                        '--mode hardware (repeatable; later wins)')
    parser.add_argument('--remap', action='append', default=[], dest='remaps',
                        metavar='FROM:=TO', help='topic remapping, as for run_graph')
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument('--script', action='store_true',
                      help='machine-readable prompts; confirmations are lines on stdin')
    mode.add_argument('--auto', action='store_true',
                      help='no confirmations: wait for stillness and motion (timeouts)')
    parser.add_argument('--timeout', type=float, default=60.0, metavar='S',
                        help='wait for data and, with --auto, for each motion [s]')
    parser.add_argument('--window', type=float, default=0.3, metavar='S',
                        help='averaging window of a reading [s]')
    parser.add_argument('--json', metavar='FILE', help='write the checks as JSON')
    # ``ros2 run wip_bringup check_base [options] --ros-args -r a:=b`` passes ROS arguments
    # after the tool's own: remappings among them are honoured like --remap, the rest
    # (log levels, parameters) do not concern a listener and are ignored.
    own, ros_remaps = split_ros_arguments(sys.argv[1:] if argv is None else list(argv))
    add_exit_codes(parser)
    args = parser.parse_args(own)
    args.remaps = [*args.remaps, *ros_remaps]
    stdin = stdin or sys.stdin
    stdout = stdout or sys.stdout
    try:
        conventions = Conventions.from_parameters(eso_parameters(args.scenario,
                                                                 args.params_files))
        remaps = [parse_remap(text) for text in args.remaps]
        for line in unmatched_remaps(remaps, LISTENED_TOPICS):
            print(f'check_base: warning: {line}', file=sys.stderr)
        if not (args.timeout > 0.0 and args.window > 0.0):
            raise GraphError('--timeout and --window must be > 0', EXIT_USAGE)
        # The base is on the user's domain and network: not on scripts/_env.sh's private
        # defaults for simulations (ROS's defaults where the user set nothing).
        network = use_user_ros_environment()
    except GraphError as err:
        print(f'check_base: error: {err}', file=sys.stderr)
        return err.exit_code
    mode_name = 'auto' if args.auto else 'script' if args.script else 'interactive'
    if threading.current_thread() is threading.main_thread():
        # Ctrl-C / SIGINT stops the check (exit 130) however the process was started: a
        # program started in the background by a non-interactive shell inherits SIGINT
        # ignored, and Python then never raises KeyboardInterrupt (the check waited for
        # data forever). rclpy's nodes install their own handler for the same reason.
        signal.signal(signal.SIGINT, signal.default_int_handler)
    # Once Ctrl-C is handled: whoever reads this line may interrupt the check.
    print(f'check_base: ROS network: {network.describe()}', file=sys.stderr, flush=True)
    listener = session = None
    try:
        # Inside the try: an interrupt while the listener starts (its subscriptions are
        # visible before its thread runs) still closes it before the interpreter exits.
        listener = BaseListener(conventions, remaps)
        session = Session(listener, conventions, mode_name, args.window, args.timeout,
                          stdin, stdout)
        status = session.run()
    except Aborted as err:
        print(f'check_base: stopped ({err})', file=stdout, flush=True)
        status = EXIT_INTERRUPTED
    except KeyboardInterrupt:
        status = EXIT_INTERRUPTED
    finally:
        if listener is not None:
            listener.close()
    if args.json:
        report = {'status': status, 'conventions': dataclasses.asdict(conventions),
                  'domain_id': network.domain_id,
                  'checks': [dataclasses.asdict(k) for k in session.checks] if session
                  else []}
        with open(args.json, 'w', encoding='utf-8') as stream:
            json.dump(report, stream, indent=2, default=str)
            stream.write('\n')
    return status


if __name__ == '__main__':
    from wip_control.tools.cli import exit_with
    exit_with(main, 'check_base')
