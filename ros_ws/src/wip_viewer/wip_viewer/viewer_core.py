"""Geometry of the viewer topics, without ROS (see ``wip_viewer.viewer_node``).

Frames (REP 103/105): ``map`` is the world frame of the planar model, x east-ish / y left
/ z up; ``base_link`` sits on the ground under the wheel axle's centre, x forward (the
heading ϕ), y left, z up. The body pitches about base_link's y axis: the model's tilt θ is
positive leaning forward (the top moves along +x), which is a positive rotation about +y.

Everything here is pure numpy: the node only copies these numbers into messages.
"""

from __future__ import annotations

import dataclasses
import math
import struct

import numpy as np

from wip_runtime.config import param


@dataclasses.dataclass(frozen=True)
class ViewerParams:
    """Parameters of the viewer node (ROS parameters ``viewer.<field>``)."""

    pose_rate: float = param(25.0, 'Hz', 'rate of the Odometry and marker messages (of '
                             'message stamps: simulated time in lockstep)',
                             minimum=0.1, maximum=200.0)
    path_rate: float = param(2.0, 'Hz', 'rate of the Path messages (whole paths: kept low, '
                             'they grow with the run)', minimum=0.05, maximum=50.0)
    path_resolution: float = param(0.05, 'm', 'a travelled-path point is added once the '
                                   'vehicle moved this far from the previous one',
                                   minimum=0.0, maximum=10.0)
    max_path_points: int = param(20000, '1', 'longest path kept; the oldest points are '
                                 'dropped beyond it', minimum=2, maximum=1000000)
    wheel_radius: float = param(0.20, 'm', 'r, wheel radius drawn', minimum=0.01,
                                maximum=5.0)
    track_width: float = param(0.5, 'm', 'd, distance between the wheels drawn',
                               minimum=0.01, maximum=10.0)
    com_height: float = param(0.6, 'm', 'l, axle to the body centre of mass; the body is '
                              'drawn 2 l long', minimum=0.01, maximum=10.0)
    position_std: float = param(0.0, 'm', 'standard deviation of the estimated position '
                                'put in the estimate Odometry covariance (0: unknown, the '
                                'covariance is left all zero)', minimum=0.0, maximum=1000.0)
    frame_id: str = param('map', '', 'world frame of every viewer message')
    child_frame_id: str = param('base_link', '', 'frame of the vehicle (Odometry child '
                                'frame)')
    robot_model: bool = param(True, '1', 'publish robot_description (URDF of the model.* '
                              'parameters) and its joints and the truth on /tf, /tf_static')
    frame_prefix: str = param('', '', "prefix of the model's and the truth's frames "
                              "('robot1/' under a namespace), as robot_state_publisher's "
                              'frame_prefix')


#: Topics the viewer node publishes (also recorded by ``scripts/run_graph --record``).
VIEWER_TOPICS = {
    '/wip/odom/estimate': 'nav_msgs/msg/Odometry',
    '/wip/odom/truth': 'nav_msgs/msg/Odometry',
    '/wip/markers/vehicle': 'visualization_msgs/msg/MarkerArray',
    '/wip/markers/prediction': 'visualization_msgs/msg/MarkerArray',
    '/wip/path/reference': 'nav_msgs/msg/Path',
    '/wip/path/travelled': 'nav_msgs/msg/Path',
    '/wip/path/estimated': 'nav_msgs/msg/Path',
}
#: The robot model's topics (``viewer.robot_model``; recorded too): tf's two global ones and
#: the URDF, under the vehicle's namespace like robot_state_publisher's.
MODEL_TOPICS = {
    '/tf': 'tf2_msgs/msg/TFMessage',
    '/tf_static': 'tf2_msgs/msg/TFMessage',
    '/robot_description': 'std_msgs/msg/String',
}
#: Those of them that are transient local: a reader that comes late still gets them.
LATCHED_TOPICS = ('/tf_static', '/robot_description')
#: Covariance put on the planar pose's unobserved axes (z, roll, pitch) [m², rad²]: the
#: usual "very large" of a 2-D pose (the variances are not estimated at all).
UNOBSERVED_VARIANCE = 1e6


def quaternion_yaw_pitch(yaw: float, pitch: float) -> tuple[float, float, float, float]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch): heading, then the body's forward lean."""
    cy, sy = math.cos(yaw / 2.0), math.sin(yaw / 2.0)
    cp, sp = math.cos(pitch / 2.0), math.sin(pitch / 2.0)
    # Hamilton product (0, 0, sy, cy) * (0, sp, 0, cp).
    return (-sy * sp, cy * sp, sy * cp, cy * cp)


def planar_pose_covariance(position_std: float) -> list[float]:
    """Row-major 6x6 covariance of (x, y, z, roll, pitch, yaw) of a 2-D estimate.

    All zero (ROS: unknown) when ``position_std`` is 0; else σ² on x and y, the very large
    :data:`UNOBSERVED_VARIANCE` on z, roll and pitch, and yaw left unknown (0).
    """
    cov = np.zeros((6, 6))
    if position_std > 0.0:
        cov[0, 0] = cov[1, 1] = position_std ** 2
        cov[2, 2] = cov[3, 3] = cov[4, 4] = UNOBSERVED_VARIANCE
    return cov.ravel().tolist()


@dataclasses.dataclass
class BodyGeometry:
    """Where to draw the vehicle: body centre, its orientation, the two wheel centres."""

    body_center: tuple[float, float, float]
    body_orientation: tuple[float, float, float, float]
    body_size: tuple[float, float, float]
    left_wheel: tuple[float, float, float]
    right_wheel: tuple[float, float, float]
    wheel_orientation: tuple[float, float, float, float]
    wheel_size: tuple[float, float, float]


def vehicle_geometry(x: float, y: float, phi: float, theta: float,
                     config: ViewerParams) -> BodyGeometry:
    """Return the vehicle at axle centre (x, y) on the ground, heading ϕ, tilt θ.

    The axle is at height r; the body is a box of length 2 l whose bottom is on the axle,
    pitched by θ about the axle (its centre at l from the axle along the tilted z axis);
    the wheels are cylinders of radius r at ±d/2 along base_link's y axis.
    """
    r, half_track, l_com = config.wheel_radius, config.track_width / 2.0, config.com_height
    forward = np.array([math.cos(phi), math.sin(phi), 0.0])
    left = np.array([-math.sin(phi), math.cos(phi), 0.0])
    axle = np.array([x, y, r])
    # Body z axis after Rz(ϕ) Ry(θ): sin θ along the heading, cos θ up.
    up = math.sin(theta) * forward + np.array([0.0, 0.0, math.cos(theta)])
    center = axle + l_com * up
    # A cylinder marker's axis is its z: turn it onto base_link's y (roll of -90°) after ϕ.
    cz, sz = math.cos(phi / 2.0), math.sin(phi / 2.0)
    s = math.sqrt(0.5)
    # (0, 0, sz, cz) * (-s, 0, 0, s)
    wheel_q = (-cz * s, -sz * s, sz * s, cz * s)
    return BodyGeometry(
        body_center=tuple(center.tolist()),
        body_orientation=quaternion_yaw_pitch(phi, theta),
        body_size=(0.12, 0.8 * config.track_width, 2.0 * l_com),
        left_wheel=tuple((axle + half_track * left).tolist()),
        right_wheel=tuple((axle - half_track * left).tolist()),
        wheel_orientation=wheel_q,
        wheel_size=(2.0 * r, 2.0 * r, 0.06),
    )


def predicted_track(x: float, y: float, phi: float, omega: float,
                    predicted_v, predicted_theta, sampling_period: float,
                    com_height: float, wheel_radius: float
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Where the MPC's prediction puts the vehicle: axle points and body-top points.

    The MPC predicts the longitudinal motion only (υ, θ, θ̇ over its horizon, spacing
    Ts); the heading is advanced at the current yaw rate ω. Axle point k+1 = point k +
    υ_k Ts along ϕ_k (forward Euler, as the MPC's discrete model); the body top is 2 l
    from the axle, tilted by θ_k. Returns two (N+1, 3) arrays starting at the current pose
    (the current tilt is the first prediction's).
    """
    v = np.asarray(predicted_v, dtype=float)
    theta = np.asarray(predicted_theta, dtype=float)
    n = min(len(v), len(theta))
    if n == 0 or not sampling_period > 0.0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    v, theta = v[:n], theta[:n]
    headings = phi + omega * sampling_period * np.arange(n + 1)
    steps = v * sampling_period
    xs = x + np.concatenate([[0.0], np.cumsum(steps * np.cos(headings[:-1]))])
    ys = y + np.concatenate([[0.0], np.cumsum(steps * np.sin(headings[:-1]))])
    axle = np.column_stack([xs, ys, np.full(n + 1, wheel_radius)])
    tilt = np.concatenate([[theta[0]], theta])
    top = axle + 2.0 * com_height * np.column_stack([
        np.sin(tilt) * np.cos(headings), np.sin(tilt) * np.sin(headings), np.cos(tilt)])
    return axle, top


class PathBuffer:
    """Points of a path, thinned to one per ``resolution`` [m] and at most ``max_points``."""

    def __init__(self, resolution: float, max_points: int) -> None:
        self.resolution = float(resolution)
        self.max_points = int(max_points)
        self.points: list[tuple[int, float, float, float]] = []  # (stamp ns, x, y, yaw)
        self.changed = False
        #: Points removed from the front so far (max_points), for a cache kept beside them.
        self.dropped = 0

    def add(self, stamp_ns: int, x: float, y: float, yaw: float) -> bool:
        """Append the point if far enough from the last one; True if appended."""
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            return False
        if self.points:
            _, x0, y0, _ = self.points[-1]
            if math.hypot(x - x0, y - y0) < self.resolution:
                return False
        self.points.append((int(stamp_ns), float(x), float(y), float(yaw)))
        if len(self.points) > self.max_points:
            excess = len(self.points) - self.max_points
            del self.points[:excess]
            self.dropped += excess
        self.changed = True
        return True


def cdr_stamp_ns(data: bytes) -> int:
    """Return the ``header.stamp`` [ns] of a serialized message, read from its CDR bytes.

    The ``header.stamp`` [ns] of a serialized message whose first field is a
    std_msgs/Header, read from its CDR bytes without deserializing the message.

    CDR: a 4-byte encapsulation header (byte 1: 0x01 little-endian, 0x00 big-endian), then
    builtin_interfaces/Time as int32 sec and uint32 nanosec. The viewer decodes a message
    only when it will publish from it (1 in 8 at 200 Hz inputs and 25 Hz outputs): rclpy's
    deserialization is most of a subscription's cost.
    """
    if len(data) < 12:
        raise ValueError(f'a serialized message with a header has >= 12 bytes, got {len(data)}')
    sec, nanosec = struct.unpack_from('<iI' if data[1] & 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nanosec


class RateGate:
    """True at most once per ``1/rate`` of message stamps.

    Publishes on input, no timer: deterministic in lockstep, where the viewer sees exactly the
    simulated stamps.
    """

    def __init__(self, rate: float) -> None:
        self.period_ns = int(round(1e9 / float(rate)))
        self.last_ns: int | None = None

    def ready(self, stamp_ns: int) -> bool:
        if self.last_ns is not None and stamp_ns < self.last_ns:
            self.last_ns = None  # a clock reset (a new run, a replay looping): start over
        if self.last_ns is None or stamp_ns - self.last_ns >= self.period_ns:
            self.last_ns = int(stamp_ns)
            return True
        return False
