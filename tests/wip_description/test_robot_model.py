"""The robot model (wip_description.robot_model) read back by an independent URDF parser.

urdf_parser_py (PyPI) loads the generated robot_description; the joints, masses and
inertias it finds must be the parameters', and the model's derived quantities (m_v, J_θ,
J_ϕ of eq. (1), core/params.py) must follow from the URDF's bodies alone.
"""

import math

import numpy as np
import pytest
from urdf_parser_py.urdf import URDF

from wip_description.params import ModelParams
from wip_description.robot_model import RobotModel, urdf

#: Parameters unlike the defaults and unlike each other, so that a swapped field shows.
PARAMS = ModelParams(body_mass=31.0, com_height=0.47, body_pitch_inertia_com=3.3,
                       chassis_mass=6.5, wheel_mass=1.9, wheel_radius=0.23,
                       wheel_inertia=0.041, track_width=0.58, yaw_inertia=0.71)


def _load(model: RobotModel) -> URDF:
    return URDF.from_xml_string(urdf(model))


@pytest.mark.parametrize('relative_to_body', [True, False])
def test_parser_finds_the_joints_of_the_params_file(relative_to_body):
    model = RobotModel(PARAMS, left_joint='drive_l', right_joint='drive_r', left_sign=1,
                       right_sign=-1, encoders_relative_to_body=relative_to_body)
    robot = _load(model)
    assert robot.get_root() == 'base_link'
    joints = {j.name: j for j in robot.joints}
    assert set(joints) == {'chassis_joint', 'body_pitch_joint', 'drive_l', 'drive_r'}
    assert joints['chassis_joint'].type == 'fixed'
    assert joints['chassis_joint'].origin.xyz == [0.0, 0.0, PARAMS.wheel_radius]
    assert joints['body_pitch_joint'].type == 'continuous'
    assert joints['body_pitch_joint'].axis == [0.0, 1.0, 0.0]
    wheel_parent = 'body' if relative_to_body else 'chassis'
    for name, side, sign in (('drive_l', 1.0, 1.0), ('drive_r', -1.0, -1.0)):
        joint = joints[name]
        assert joint.type == 'continuous' and joint.parent == wheel_parent
        assert joint.origin.xyz == [0.0, side * PARAMS.track_width / 2.0, 0.0]
        # A positive joint angle times the wheel's sign rolls forward: axis sign * y.
        assert joint.axis == [0.0, sign, 0.0]


def test_parser_finds_the_masses_and_inertias_of_the_parameters():
    robot = _load(RobotModel(PARAMS))
    links = {link.name: link for link in robot.links}
    body, chassis = links['body'].inertial, links['chassis'].inertial
    assert body.mass == PARAMS.body_mass and chassis.mass == PARAMS.chassis_mass
    assert body.origin.xyz == [0.0, 0.0, PARAMS.com_height]
    assert body.inertia.iyy == PARAMS.body_pitch_inertia_com
    assert body.inertia.izz == PARAMS.yaw_inertia
    for name in ('left_wheel', 'right_wheel'):
        wheel = links[name].inertial
        assert wheel.mass == PARAMS.wheel_mass
        assert wheel.inertia.iyy == PARAMS.wheel_inertia          # about the axle (y)
        assert wheel.inertia.ixx == wheel.inertia.izz == PARAMS.wheel_inertia / 2.0
        assert links[name].visual.geometry.radius == PARAMS.wheel_radius
    assert links['base_link'].inertial is None


def test_model_quantities_follow_from_the_urdf_bodies():
    # m_v, J_θ about the axle and J_ϕ at θ = 0 recomputed from what the parser read: the
    # URDF holds the model the controllers use, not just numbers with the right names.
    robot = _load(RobotModel(PARAMS))
    links = {link.name: link.inertial for link in robot.links}
    joints = {j.name: j for j in robot.joints}
    r = joints['chassis_joint'].origin.xyz[2]
    wheels = [links['left_wheel'], links['right_wheel']]
    m_v = (links['body'].mass + links['chassis'].mass
           + sum(w.mass + w.inertia.iyy / r ** 2 for w in wheels))
    l_com = links['body'].origin.xyz[2]
    j_theta = links['body'].inertia.iyy + links['body'].mass * l_com ** 2
    half = [abs(joints[n].origin.xyz[1]) for n in ('left_wheel_joint', 'right_wheel_joint')]
    j_phi = (links['body'].inertia.izz + links['chassis'].inertia.izz
             + sum((w.mass + w.inertia.iyy / r ** 2) * h ** 2 for w, h in zip(wheels, half)))
    assert m_v == pytest.approx(PARAMS.effective_mass, rel=1e-12)
    assert j_theta == pytest.approx(PARAMS.pitch_inertia, rel=1e-12)
    assert j_phi == pytest.approx(PARAMS.yaw_inertia_total, rel=1e-12)


def _rotate(quaternion, point):
    x, y, z, w = quaternion
    u = np.array([x, y, z])
    p = np.asarray(point, dtype=float)
    return p + 2.0 * w * np.cross(u, p) + 2.0 * np.cross(u, np.cross(u, p))


@pytest.mark.parametrize('sign', [1, -1])
def test_joint_transforms_roll_the_wheel_and_tilt_the_body_forward(sign):
    model = RobotModel(PARAMS, left_sign=sign, right_sign=sign)
    r, l_com = PARAMS.wheel_radius, PARAMS.com_height
    # The wheel's top point after a quarter turn of sign * joint angle: forward (+x), so
    # rolling on the ground it moves the robot forward.
    for name in ('left_wheel_joint', 'right_wheel_joint'):
        xyz, q = model.joint(name).transform(sign * math.pi / 2.0)
        assert np.allclose(_rotate(q, (0.0, 0.0, r)), (r, 0.0, 0.0), atol=1e-15)
        assert math.isclose(math.hypot(*q), 1.0)
    # A positive tilt θ moves the body's centre of mass forward by l sin θ.
    theta = 0.3
    _, q = model.joint('body_pitch_joint').transform(theta)
    assert np.allclose(_rotate(q, (0.0, 0.0, l_com)),
                       (l_com * math.sin(theta), 0.0, l_com * math.cos(theta)), atol=1e-15)
    assert model.joint('chassis_joint').transform(1.0) == ((0.0, 0.0, r), (0.0, 0.0, 0.0, 1.0))


def test_names_are_escaped_and_bad_names_or_signs_refused():
    robot = _load(RobotModel(PARAMS, left_joint='l&"wheel"', right_joint="r<'wheel'>"))
    assert {'l&"wheel"', "r<'wheel'>"} <= {j.name for j in robot.joints}
    for kwargs in ({'left_joint': 'w', 'right_joint': 'w'}, {'left_joint': ''},
                   {'right_joint': 'chassis_joint'}, {'left_sign': 0}):
        with pytest.raises(ValueError, match='wheel'):
            RobotModel(PARAMS, **kwargs)
