"""Messages of any package: fast builders, finiteness checks, orientation, CDR decoding.

Orientation quaternions are the ZYX (yaw, pitch, roll) Euler composition
R = Rz(ϕ) Ry(θ) Rx(roll) (REP 103, as tf2). A reader of an external message raises
:class:`InvalidMessage` (a ValueError) with the reason on malformed or non-finite content.
"""

from __future__ import annotations

import math
import os
from typing import Sequence

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

#: Quaternions whose norm is further than this from 1 are rejected as malformed [1]
#: (a normalised float quaternion is within 1e-15; 1e-3 tolerates single-precision drivers).
QUATERNION_NORM_TOLERANCE = 1e-3


class InvalidMessage(ValueError):
    """A message is malformed (missing field, wrong size) or carries non-finite numbers."""


# --------------------------------------------------------------------- building messages

#: The generated message classes check each field's type only when this is '1' (rosidl's
#: ``ROS_PYTHON_CHECK_FIELDS``); the builders below then use their constructors, checks and all.
_CHECK_FIELDS = os.environ.get('ROS_PYTHON_CHECK_FIELDS', '') == '1'
_NS_PER_S = 1_000_000_000


def _bare(cls):
    """Return an instance of a generated message class: no field set yet, type checks off."""
    msg = cls.__new__(cls)
    msg._check_fields = False
    return msg


def fast_header(stamp_ns: int, frame_id: str = '') -> Header:
    """std_msgs/Header with the stamp [ns] and frame, equal to :func:`.stamps.make_header`'s."""
    if _CHECK_FIELDS:
        return Header(stamp=Time(sec=int(stamp_ns) // _NS_PER_S,
                                 nanosec=int(stamp_ns) % _NS_PER_S), frame_id=frame_id)
    stamp = _bare(Time)
    stamp._sec, stamp._nanosec = divmod(int(stamp_ns), _NS_PER_S)
    header = _bare(Header)
    header._stamp, header._frame_id = stamp, frame_id
    return header


class StampedBuilder:
    """Builds a stamped message of one flat type: its header and every other field, in order.

    The project's messages of a control tick (an estimate, a reference, a command, ...) are
    built once per tick each. The generated constructor evaluates every default (a Header
    and a Time to drop), looks each keyword up and imports Header on every call: 4.4 us
    per message here, against 0.7 us for filling the instance's slots directly
    (docs/realtime.md). The result is the same message (``==``, the same CDR bytes).
    Refuses, at import, a type whose fields are not the header and ``fields``: a message
    definition that changed must not leave a field unset.
    """

    __slots__ = ('cls', 'fields', 'slots')

    def __init__(self, cls, fields: Sequence[str]) -> None:
        self.cls, self.fields = cls, tuple(fields)
        self.slots = tuple('_' + name for name in self.fields)
        expected = set(cls.__slots__) - {'_header', '_check_fields'}
        if '_header' not in cls.__slots__ or set(self.slots) != expected:
            raise TypeError(f'{cls.__name__}: fields {sorted(expected)} besides the header, '
                            f'the builder has {sorted(self.slots)}')

    def __call__(self, stamp_ns: int, frame_id: str, *values):
        if _CHECK_FIELDS:
            return self.cls(header=fast_header(stamp_ns, frame_id),
                            **dict(zip(self.fields, values)))
        msg = _bare(self.cls)
        msg._header = fast_header(stamp_ns, frame_id)
        for slot, value in zip(self.slots, values):
            setattr(msg, slot, value)
        return msg


def check_finite_record(what: str, record, skip: str = '') -> None:
    """:func:`check_finite_values` of a NamedTuple's fields but ``skip``, without building a dict.

    A dict of the fields is built only to name the bad ones.
    """
    if all(map(math.isfinite, record)):   # the common case
        return
    values = record._asdict()
    values.pop(skip, None)
    check_finite_values(what, **values)


def stamped(msg, stamp_ns: int, frame_id: str = ''):
    """``msg`` with its own header set, in place, to the stamp [ns] and frame; returns it.

    On the hot path instead of ``Msg(header=make_header(...))``: the generated constructors
    evaluate their defaults eagerly, so that also builds a Header and a Time to drop
    (1.8 us of 5.5 per message measured, six messages per control tick).
    """
    header = msg.header
    header.stamp.sec, header.stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
    if frame_id:
        header.frame_id = frame_id
    return msg


def check_finite_values(what: str, **values: float) -> None:
    if all(map(math.isfinite, values.values())):  # the common case, at C speed
        return
    bad = [f'{k}={v!r}' for k, v in values.items() if not math.isfinite(v)]
    raise InvalidMessage(f'{what}: non-finite {", ".join(bad)}')


# --------------------------------------------------------------------- orientation

def quaternion_from_euler(roll: float, pitch: float, yaw: float) -> tuple[float, ...]:
    """(x, y, z, w) of R = Rz(yaw) Ry(pitch) Rx(roll) [rad] (REP 103, as tf2)."""
    cr, sr = math.cos(0.5 * roll), math.sin(0.5 * roll)
    cp, sp = math.cos(0.5 * pitch), math.sin(0.5 * pitch)
    cy, sy = math.cos(0.5 * yaw), math.sin(0.5 * yaw)
    return (sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
            cr * cp * cy + sr * sp * sy)


def pitch_yaw_from_quaternion(x: float, y: float, z: float, w: float) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] of the ZYX decomposition; yaw in (−π, π].

    Inverse of :func:`quaternion_from_euler` for |pitch| < π/2 (the round trip is exact to
    about 1e-16 rad). The quaternion is normalised first; its roll is ignored (the WIP
    does not roll).
    """
    check_finite_values('orientation', x=x, y=y, z=z, w=w)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InvalidMessage(f'orientation: quaternion norm {norm!r} is not 1')
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    sin_pitch = 2.0 * (w * y - z * x)
    pitch = math.asin(max(-1.0, min(1.0, sin_pitch)))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return pitch, yaw


# --------------------------------------------------------------------- sensors

#: rosbags' type store of ROS 2 Jazzy's messages, built on the first raw message.
_typestore = None


def prepare_decoder(*typenames: str) -> None:
    """Build the type store and the decoders of ``typenames`` now.

    This takes about 0.16 s of CPU here, more on a slow machine, so it is done at a node's
    start rather than in the callback of its first sensor sample.
    """
    global _typestore  # noqa: PLW0603 - one store per process
    if _typestore is None:
        from rosbags.typesys import get_typestore, Stores
        _typestore = get_typestore(Stores.ROS2_JAZZY)
    for typename in typenames:
        _typestore.get_msgdef(typename)


def decode_serialized(msg, typename: str):
    """Decode a sensor message taken serialized (``create_subscription(..., raw=True)``).

    The result is an object with the message's fields (rosbags' CDR decoder, pinned
    version); a message object is returned as is (the intra-process bus and tests deliver
    objects).

    Why: for a 200 Hz sensor stream, rclpy building the Python message in its take costs
    more than the control math (the base's two streams: 5.2 % of a core taken as
    messages, 2.7 % taken serialized and decoded here; docs/realtime.md).
    """
    if msg.__class__ is not bytes:
        return msg
    if _typestore is None:
        prepare_decoder()
    try:
        if len(msg) < 4 or msg[0] != 0 or msg[1] not in (0, 1) or msg[2:4] != b'\x00\x00':
            raise ValueError('not a plain CDR encapsulation header')
        msgdef = _typestore.get_msgdef(typename)
        decode = msgdef.deserialize_cdr_le if msg[1] else msgdef.deserialize_cdr_be
        # A truncated message fails in decode. Bytes after the last field are the
        # serializer's and ignored: Fast CDR (rclpy, rmw_fastrtps) sizes an empty trailing
        # float64[] with its 8-byte alignment, so a JointState without efforts ends 8 bytes
        # early (rosbags' public deserialize_cdr allows 3 and rejects it).
        return decode(msg[4:], 0, msgdef.cls, _typestore)[0]
    except Exception as err:  # noqa: BLE001 - any decoding failure is a malformed message
        raise InvalidMessage(f'{typename}: undecodable CDR message of {len(msg)} bytes '
                             f'({type(err).__name__}: {err})') from None
