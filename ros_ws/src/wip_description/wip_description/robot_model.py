"""The robot model as a URDF, generated from the model parameters, and its joints.

Links and joints (frames REP 103/105: x forward, y left, z up):

- ``base_link``: on the ground under the wheel axle's centre, heading ϕ (the frame of
  /odom's child); no mass (KDL ignores a root link's inertia).
- ``chassis`` (fixed joint ``chassis_joint``, at the axle height r): the part that does not
  tilt (axle, motors), mass m_c.
- ``body`` (continuous joint ``body_pitch_joint`` about y at the axle): the pendulum, mass
  m_p with its centre of mass l above the axle; its angle is the tilt θ (positive leaning
  forward).
- the two wheels (continuous joints named ``left_joint``/``right_joint``, at ±d/2 along y):
  mass m_w, spin inertia J_w. Their axis is ±y by the wheel's sign, so that a positive
  joint angle times the sign rolls the robot forward, as ``signed_wheel_angles`` reads
  /joint_states. With encoders on the body (``encoders_relative_to_body``, they measure the
  wheel minus the tilt) the wheels hang from ``body``, else from ``chassis``: a joint
  angle of /joint_states is then exactly its URDF joint's position.

Inertias: the model gives the body's pitch inertia I_c about its centre of mass and the
yaw inertia J_v of body and chassis together; the URDF puts J_v on the body (izz) and
takes its roll inertia equal to I_c (ixx, the model has none); the chassis is a point
mass. A wheel is a thin disc: J_w about its axle, J_w / 2 about a diameter.

Pure Python, no ROS import: the viewer publishes :func:`urdf` on ``robot_description`` and
computes the joints' transforms with :meth:`RobotModel.joint_transform`.
"""

from __future__ import annotations

import dataclasses
import math
from xml.sax.saxutils import quoteattr

from .params import ModelParams

#: Width [m] of the wheels and depth [m] of the body box drawn (the model has neither).
WHEEL_WIDTH = 0.06
BODY_DEPTH = 0.12


@dataclasses.dataclass(frozen=True)
class Joint:
    """One joint: ``parent`` -> ``child`` at ``xyz`` [m], rotating about ``axis`` (movable)."""

    name: str
    kind: str                                  # 'fixed' or 'continuous'
    parent: str
    child: str
    xyz: tuple[float, float, float]
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)

    def transform(self, position: float = 0.0
                  ) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
        """Return (translation, quaternion x, y, z, w) of child in parent at ``position`` [rad].

        The joints' origins have no rotation (rpy 0), so the rotation is the axis-angle
        of the position alone.
        """
        if self.kind == 'fixed':
            return self.xyz, (0.0, 0.0, 0.0, 1.0)
        s, c = math.sin(position / 2.0), math.cos(position / 2.0)
        ax, ay, az = self.axis
        return self.xyz, (ax * s, ay * s, az * s, c)


@dataclasses.dataclass(frozen=True)
class RobotModel:
    """The WIP's links and joints for the given parameters (see the module docstring)."""

    params: ModelParams
    left_joint: str = 'left_wheel_joint'
    right_joint: str = 'right_wheel_joint'
    left_sign: int = 1
    right_sign: int = 1
    encoders_relative_to_body: bool = False
    name: str = 'wip'

    def __post_init__(self) -> None:
        names = {self.left_joint, self.right_joint, 'chassis_joint', 'body_pitch_joint'}
        if len(names) != 4 or not (self.left_joint.strip() and self.right_joint.strip()):
            raise ValueError(f'wheel joint names must be distinct, non-empty and not '
                             f'chassis_joint/body_pitch_joint: {self.left_joint!r}, '
                             f'{self.right_joint!r}')
        if self.left_sign not in (1, -1) or self.right_sign not in (1, -1):
            raise ValueError(f'wheel signs must be 1 or -1, got {self.left_sign!r}, '
                             f'{self.right_sign!r}')

    @property
    def joints(self) -> tuple[Joint, ...]:
        p = self.params
        wheel_parent = 'body' if self.encoders_relative_to_body else 'chassis'
        half = p.track_width / 2.0
        return (
            Joint('chassis_joint', 'fixed', 'base_link', 'chassis', (0.0, 0.0, p.wheel_radius)),
            Joint('body_pitch_joint', 'continuous', 'chassis', 'body', (0.0, 0.0, 0.0)),
            Joint(self.left_joint, 'continuous', wheel_parent, 'left_wheel', (0.0, half, 0.0),
                  (0.0, float(self.left_sign), 0.0)),
            Joint(self.right_joint, 'continuous', wheel_parent, 'right_wheel',
                  (0.0, -half, 0.0), (0.0, float(self.right_sign), 0.0)),
        )

    def joint(self, name: str) -> Joint:
        return next(j for j in self.joints if j.name == name)


def _f(value: float) -> str:
    # repr: the shortest text that reads back as the same float (the tests compare exactly).
    return repr(float(value))


def _v(values) -> str:
    return ' '.join(_f(v) for v in values)


def _inertial(mass: float, xyz, ixx: float, iyy: float, izz: float) -> str:
    return (f'    <inertial>\n      <origin xyz="{_v(xyz)}" rpy="0 0 0"/>\n'
            f'      <mass value="{_f(mass)}"/>\n'
            f'      <inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(iyy)}" iyz="0" '
            f'izz="{_f(izz)}"/>\n    </inertial>\n')


def _visual(geometry: str, xyz, rpy, material: str) -> str:
    return (f'    <visual>\n      <origin xyz="{_v(xyz)}" rpy="{_v(rpy)}"/>\n'
            f'      <geometry>{geometry}</geometry>\n'
            f'      <material name="{material}"/>\n    </visual>\n')


def urdf(model: RobotModel) -> str:
    """Return the URDF (XML text) of ``model``."""
    p = model.params
    r, l_com, d = p.wheel_radius, p.com_height, p.track_width
    box = f'<box size="{_v((BODY_DEPTH, 0.8 * d, 2.0 * l_com))}"/>'
    cylinder = f'<cylinder radius="{_f(r)}" length="{_f(WHEEL_WIDTH)}"/>'
    # A cylinder's axis is its z: turned onto the wheel's y axis.
    wheel_rpy = (-math.pi / 2.0, 0.0, 0.0)
    links = {
        'base_link': '',
        'chassis': (_inertial(p.chassis_mass, (0.0, 0.0, 0.0), 0.0, 0.0, 0.0)
                    + _visual(f'<box size="{_v((BODY_DEPTH, 0.8 * d, 0.08))}"/>',
                              (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 'dark')),
        'body': (_inertial(p.body_mass, (0.0, 0.0, l_com), p.body_pitch_inertia_com,
                           p.body_pitch_inertia_com, p.yaw_inertia)
                 + _visual(box, (0.0, 0.0, l_com), (0.0, 0.0, 0.0), 'body')),
    }
    for wheel in ('left_wheel', 'right_wheel'):
        links[wheel] = (_inertial(p.wheel_mass, (0.0, 0.0, 0.0), p.wheel_inertia / 2.0,
                                  p.wheel_inertia, p.wheel_inertia / 2.0)
                        + _visual(cylinder, (0.0, 0.0, 0.0), wheel_rpy, 'dark'))
    out = ['<?xml version="1.0"?>\n', f'<robot name={quoteattr(model.name)}>\n',
           '  <material name="body"><color rgba="0.2 0.45 0.8 1"/></material>\n',
           '  <material name="dark"><color rgba="0.15 0.15 0.15 1"/></material>\n']
    for name, body in links.items():
        out.append(f'  <link name="{name}">\n{body}  </link>\n' if body
                   else f'  <link name="{name}"/>\n')
    for joint in model.joints:
        out.append(f'  <joint name={quoteattr(joint.name)} type="{joint.kind}">\n'
                   f'    <parent link="{joint.parent}"/>\n    <child link="{joint.child}"/>\n'
                   f'    <origin xyz="{_v(joint.xyz)}" rpy="0 0 0"/>\n')
        if joint.kind != 'fixed':
            out.append(f'    <axis xyz="{_v(joint.axis)}"/>\n')
        out.append('  </joint>\n')
    out.append('</robot>\n')
    return ''.join(out)
