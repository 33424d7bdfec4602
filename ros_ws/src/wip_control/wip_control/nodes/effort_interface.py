"""The effort interface of a base: wheel joints, command order and signs, as node parameters."""

from __future__ import annotations

import dataclasses

from rclpy.node import Node
from wip_description.wiring import check_effort_joints, EffortCommand, WheelJoints, WheelSigns
from wip_runtime.parameters import RosParams


@dataclasses.dataclass(frozen=True)
class EffortInterface:
    """The wheels of a base as a node that commands efforts sees them."""

    left_joint: str
    right_joint: str
    joints: tuple[str, ...]  # order of the effort command's data
    left_sign: float  # +1 or -1: see wip_description.wiring.WheelSigns
    right_sign: float


def declare_effort_interface(node: Node) -> EffortInterface:
    """Declare and read the parameters of the effort interface.

    These are the parameters of WheelJoints, EffortCommand and WheelSigns (the
    mixer and the stand-in base read the same ones). Raise ParamError if ``joints`` does
    not list ``left_joint`` and ``right_joint`` once each.
    """
    wheels = RosParams(node, '', WheelJoints).config
    left, right = wheels.left_joint, wheels.right_joint
    # joints defaults to (left_joint, right_joint) as set, so renaming both is enough.
    joints = tuple(RosParams(node, '', EffortCommand,
                                    defaults=EffortCommand((left, right))).config.joints)
    check_effort_joints(left, right, joints)
    signs = RosParams(node, '', WheelSigns).config
    return EffortInterface(left, right, joints, float(signs.left_wheel_sign),
                           float(signs.right_wheel_sign))
