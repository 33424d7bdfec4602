"""check_base's checks: a base's readings against what the eso node's parameters predict.

Pure arithmetic on readings (no ROS): the conventions the eso node assumes, one reading
(means over a window), and the checks of each step; the steps and their thresholds:
docs/check_base.md.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from wip_runtime.rotations import quaternion_from_euler, quaternion_multiply, rotate_vector_into
from wip_control.nodes.hardware_inputs import check_mounting_rpy, check_wheel_sign

from .launcher import EXIT_USAGE, GraphError

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
