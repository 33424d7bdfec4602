"""Geometry of the viewer topics (wip_viewer.viewer_core): closed forms, no ROS."""

import math

import numpy as np
import pytest

from wip_viewer.viewer_core import (PathBuffer, planar_pose_covariance, predicted_track,
                                 quaternion_yaw_pitch, RateGate, vehicle_geometry,
                                 ViewerParams)


def rotate(q, v):
    """Rotate vector v by the unit quaternion q = (x, y, z, w)."""
    x, y, z, w = q
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=float)
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


@pytest.mark.parametrize('phi,theta', [(0.0, 0.0), (0.7, 0.1), (-2.5, -0.3), (3.1, 0.05)])
def test_body_axis_leans_forward_along_the_heading_by_theta(phi, theta):
    q = quaternion_yaw_pitch(phi, theta)
    assert math.isclose(sum(c * c for c in q), 1.0, rel_tol=1e-12)
    # REP 103: θ > 0 leans forward, i.e. the body's z axis tips towards the heading.
    expected_up = [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi),
                   math.cos(theta)]
    np.testing.assert_allclose(rotate(q, [0, 0, 1]), expected_up, atol=1e-12)
    # The body's x axis is the heading, pitched down by θ.
    np.testing.assert_allclose(rotate(q, [1, 0, 0]),
                               [math.cos(theta) * math.cos(phi),
                                math.cos(theta) * math.sin(phi), -math.sin(theta)],
                               atol=1e-12)


def test_vehicle_wheels_sit_on_the_axle_across_the_heading_and_touch_the_ground():
    config = ViewerParams(wheel_radius=0.2, track_width=0.5, com_height=0.6)
    phi, theta = 0.9, 0.12
    g = vehicle_geometry(1.0, 2.0, phi, theta, config)
    left, right = np.array(g.left_wheel), np.array(g.right_wheel)
    np.testing.assert_allclose((left + right) / 2, [1.0, 2.0, 0.2], atol=1e-12)
    np.testing.assert_allclose(left - right, 0.5 * np.array([-math.sin(phi), math.cos(phi),
                                                             0.0]), atol=1e-12)
    # A cylinder's axis (its z) lies along the axle; its radius is r: it touches z = 0.
    axis = rotate(g.wheel_orientation, [0, 0, 1])
    np.testing.assert_allclose(axis, [-math.sin(phi), math.cos(phi), 0.0], atol=1e-12)
    assert g.wheel_size[0] / 2 == pytest.approx(left[2])
    # Body centre l from the axle along the tilted axis.
    centre = np.array(g.body_center) - np.array([1.0, 2.0, 0.2])
    assert np.linalg.norm(centre) == pytest.approx(0.6)
    assert math.degrees(math.acos(centre[2] / 0.6)) == pytest.approx(math.degrees(theta))


def test_predicted_track_integrates_the_predicted_speed_along_the_turning_heading():
    ts, n = 0.05, 20
    v = np.full(n, 0.4)
    axle, top = predicted_track(0.0, 0.0, 0.0, 0.0, v, np.zeros(n), ts, 0.6, 0.2)
    assert axle.shape == (n + 1, 3) and top.shape == (n + 1, 3)
    assert axle[-1, 0] == pytest.approx(0.4 * ts * n) and abs(axle[-1, 1]) < 1e-12
    np.testing.assert_allclose(top[:, 2], 0.2 + 1.2)  # upright: body top 2 l above the axle
    # Turning at ω: a chord of the circle of radius υ/ω (forward Euler: slightly outside).
    omega = 0.5
    axle, _ = predicted_track(0.0, 0.0, 0.0, omega, v, np.zeros(n), ts, 0.6, 0.2)
    radius = 0.4 / omega
    distance = np.hypot(axle[-1, 0], axle[-1, 1] - radius)
    assert distance == pytest.approx(radius, rel=0.02)
    # Tilted forward by θ: the body top leads the axle by 2 l sin θ.
    theta = np.full(n, 0.1)
    axle, top = predicted_track(0.0, 0.0, 0.0, 0.0, v, theta, ts, 0.6, 0.2)
    np.testing.assert_allclose(top[:, 0] - axle[:, 0], 1.2 * math.sin(0.1))
    empty = predicted_track(0.0, 0.0, 0.0, 0.0, [], [], ts, 0.6, 0.2)
    assert empty[0].shape == (0, 3)


def test_path_buffer_thins_to_the_resolution_and_keeps_the_newest_points():
    path = PathBuffer(resolution=0.095, max_points=5)
    added = [path.add(i, 0.01 * i, 0.0, 0.0) for i in range(100)]  # 1 m in 1 cm steps
    assert sum(added) == 5 + 5  # every 10th point kept, then only the last 5 remain
    assert len(path.points) == 5 and path.dropped == 5
    xs = [p[1] for p in path.points]
    assert all(b - a >= 0.095 for a, b in zip(xs, xs[1:]))
    assert xs[-1] == pytest.approx(0.9)
    assert not path.add(1000, float('nan'), 0.0, 0.0)


def test_rate_gate_passes_one_message_per_period_of_stamps():
    gate = RateGate(25.0)  # 40 ms
    stamps = [int(i * 5e6) for i in range(201)]  # 200 Hz for 1 s
    passed = [s for s in stamps if gate.ready(s)]
    assert len(passed) == 26  # t = 0, 40 ms, ..., 1 s
    assert all(b - a == 40_000_000 for a, b in zip(passed, passed[1:]))
    assert gate.ready(0)  # a clock reset starts over


def test_covariance_is_unknown_without_a_position_std():
    assert planar_pose_covariance(0.0) == [0.0] * 36
    cov = np.array(planar_pose_covariance(0.5)).reshape(6, 6)
    assert cov[0, 0] == cov[1, 1] == 0.25
    assert np.all(np.diag(cov)[2:5] >= 1e6) and cov[5, 5] == 0.0
    assert np.count_nonzero(cov - np.diag(np.diag(cov))) == 0


def test_stamp_is_read_from_the_cdr_bytes_without_deserializing():
    rclpy = pytest.importorskip('rclpy')  # noqa: F841 - the message classes need it
    from rclpy.serialization import serialize_message
    from wip_msgs.msg import GroundTruth
    from wip_viewer.viewer_core import cdr_stamp_ns
    message = GroundTruth(x=1.0)
    message.header.stamp.sec, message.header.stamp.nanosec = 1_700_000_123, 999_999_999
    message.header.frame_id = 'map'
    assert cdr_stamp_ns(serialize_message(message)) == 1_700_000_123_999_999_999
    with pytest.raises(ValueError, match='>= 12 bytes'):
        cdr_stamp_ns(b'\x00\x01\x00\x00')


def test_the_viewer_runs_when_someone_will_look():
    from wip_bringup.graph import GraphOptions
    from wip_bringup.view_options import viewer_wanted
    assert not viewer_wanted(GraphOptions())
    assert viewer_wanted(GraphOptions(record='bag'))
    assert viewer_wanted(GraphOptions(foxglove_port=0))
    assert viewer_wanted(GraphOptions(viewer=True))
    assert not viewer_wanted(GraphOptions(record='bag', viewer=False))
