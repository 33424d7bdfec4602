"""Messages of any package: fast builders, finiteness checks, orientation, CDR decoding.

A reader of an external message raises :class:`InvalidMessage` (a ValueError) with the
reason on malformed or non-finite content; an orientation read from a message is checked
here, then decomposed by :mod:`wip_runtime.rotations` (REP 103's ZYX Euler angles).
"""

from __future__ import annotations

import math
from math import isfinite
import os
import struct
from typing import Sequence

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

from .rotations import pitch_yaw_of_quaternion, quaternion_norm

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
    and a Time to drop), looks each keyword up and imports Header on every call, against
    filling the instance's slots directly (docs/realtime.md). The result is the same
    message (``==``, the same CDR bytes). ``build(stamp_ns, frame_id, *values)`` is a
    function written for the type once (as :func:`collections.namedtuple` writes its
    ``__new__``): straight-line slot assignments, no loop over the fields per message.
    Refuses, at import, a type whose fields are not the header and ``fields``: a message
    definition that changed must not leave a field unset.
    """

    __slots__ = ('cls', 'fields', 'slots', 'build')

    def __init__(self, cls, fields: Sequence[str]) -> None:
        self.cls, self.fields = cls, tuple(fields)
        self.slots = tuple('_' + name for name in self.fields)
        expected = set(cls.__slots__) - {'_header', '_check_fields'}
        if '_header' not in cls.__slots__ or set(self.slots) != expected:
            raise TypeError(f'{cls.__name__}: fields {sorted(expected)} besides the header, '
                            f'the builder has {sorted(self.slots)}')
        self.build = self._checked if _CHECK_FIELDS else self._compile()

    def __call__(self, stamp_ns: int, frame_id: str, *values):
        return self.build(stamp_ns, frame_id, *values)

    def _checked(self, stamp_ns: int, frame_id: str, *values):
        return self.cls(header=fast_header(stamp_ns, frame_id), **dict(zip(self.fields, values)))

    def _compile(self):
        """Return ``build``: :func:`fast_header`'s steps, then one assignment per field."""
        names = [f'v{i}' for i in range(len(self.slots))]
        body = '\n'.join(f'    msg.{slot} = {name}' for slot, name in zip(self.slots, names))
        source = (f'def build(stamp_ns, frame_id, {", ".join(names)}):\n'
                  '    stamp = new(Time)\n'
                  '    stamp._check_fields = False\n'
                  '    stamp._sec, stamp._nanosec = divmod(int(stamp_ns), NS_PER_S)\n'
                  '    header = new(Header)\n'
                  '    header._check_fields = False\n'
                  '    header._stamp, header._frame_id = stamp, frame_id\n'
                  '    msg = new(cls)\n'
                  '    msg._check_fields = False\n'
                  '    msg._header = header\n'
                  f'{body}\n'
                  '    return msg\n')
        namespace = {'new': object.__new__, 'Time': Time, 'Header': Header, 'cls': self.cls,
                     'NS_PER_S': _NS_PER_S}
        exec(compile(source, f'<StampedBuilder {self.cls.__name__}>', 'exec'), namespace)  # noqa: S102
        return namespace['build']


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

def pitch_yaw_from_quaternion(x: float, y: float, z: float, w: float) -> tuple[float, float]:
    """(pitch θ, yaw ϕ) [rad] of an orientation read from a message; yaw in (−π, π].

    :func:`~wip_runtime.rotations.pitch_yaw_of_quaternion` of the normalised quaternion,
    after the reader's checks: InvalidMessage if a value is not finite or the norm is not 1
    within :data:`QUATERNION_NORM_TOLERANCE`.
    """
    if not (isfinite(x) and isfinite(y) and isfinite(z) and isfinite(w)):
        check_finite_values('orientation', x=x, y=y, z=z, w=w)
    norm = quaternion_norm(x, y, z, w)
    if abs(norm - 1.0) > QUATERNION_NORM_TOLERANCE:
        raise InvalidMessage(f'orientation: quaternion norm {norm!r} is not 1')
    return pitch_yaw_of_quaternion(x, y, z, w, norm)


# --------------------------------------------------------------------- sensors

#: rosbags' type store of ROS 2 Jazzy's messages, built on the first raw message.
_typestore = None
#: Hand-written little-endian decoders by type name (:func:`prepare_decoder`).
_fast_decoders: dict = {}
#: The classes of the objects those decoders return.
_decoded_classes: set = set()

_HEADER = struct.Struct('<iII')        # stamp sec, nanosec; frame_id's length (with its NUL)
_U32 = struct.Struct('<I')
#: The encapsulation header of plain CDR, little endian.
_PLAIN_CDR_LE = b'\x00\x01\x00\x00'
_IMU_DOUBLES = struct.Struct('<4d9d3d9d3d9d')


def prepare_decoder(*typenames: str) -> None:
    """Build the type store and the decoders of ``typenames`` now.

    This takes about 0.16 s of CPU here, more on a slow machine, so it is done at a node's
    start rather than in the callback of its first sensor sample.
    """
    global _typestore  # noqa: PLW0603 - one store per process
    if _typestore is None:
        from rosbags.typesys import get_typestore, Stores
        _typestore = get_typestore(Stores.ROS2_JAZZY)
        _SensorDecoders(_typestore.types)
    for typename in typenames:
        _typestore.get_msgdef(typename)


class _SensorDecoders:
    """Decoders of the two 200 Hz sensor types in little-endian CDR, with :mod:`struct`.

    They return the objects rosbags' decoder returns (its classes, float64 arrays as
    read-only numpy views of the bytes), field for field equal, unpacking the fixed part
    of a message at once where rosbags' generated code unpacks field by field. Offsets
    count from the end of the encapsulation header; a string is a uint32 length (with the
    NUL), its bytes and the NUL; a sequence a uint32 count, then its elements, aligned to
    their size when there is one (cdr.py). A count or length beyond the message's end
    fails as a truncated message does.
    """

    def __init__(self, types) -> None:
        import numpy as np   # only where sensors are decoded

        self.time, self.header = types['builtin_interfaces/msg/Time'], types['std_msgs/msg/Header']
        self.quaternion = types['geometry_msgs/msg/Quaternion']
        self.vector3 = types['geometry_msgs/msg/Vector3']
        self.imu_class = types['sensor_msgs/msg/Imu']
        self.joint_state_class = types['sensor_msgs/msg/JointState']
        self.frombuffer, self.f8 = np.frombuffer, np.dtype('<f8')
        _decoded_classes.update((self.imu_class, self.joint_state_class))
        _fast_decoders.update({'sensor_msgs/msg/Imu': self.imu,
                               'sensor_msgs/msg/JointState': self.joint_state})

    def _header(self, data: bytes) -> tuple:
        sec, nanosec, size = _HEADER.unpack_from(data, 0)
        end = 12 + size
        if size < 1 or end > len(data) or data[end - 1] != 0:
            raise ValueError(f'frame_id of {size} bytes')
        return self.header(self.time(sec, nanosec), data[12:end - 1].decode()), end

    def _doubles(self, data: bytes, offset: int) -> tuple:
        offset += -offset % 4
        (count,) = _U32.unpack_from(data, offset)
        offset += 4
        if not count:
            return self.frombuffer(b'', self.f8), offset
        offset += -offset % 8
        if offset + 8 * count > len(data):
            raise ValueError(f'{count} float64 beyond the end')
        return self.frombuffer(data, self.f8, count, offset), offset + 8 * count

    def imu(self, data: bytes):
        head, offset = self._header(data)
        offset += -offset % 8
        v = _IMU_DOUBLES.unpack_from(data, offset)
        frombuffer, f8, vector3 = self.frombuffer, self.f8, self.vector3
        return self.imu_class(head, self.quaternion(*v[0:4]),
                              frombuffer(data, f8, 9, offset + 32), vector3(*v[13:16]),
                              frombuffer(data, f8, 9, offset + 128), vector3(*v[25:28]),
                              frombuffer(data, f8, 9, offset + 224))

    def joint_state(self, data: bytes):
        head, offset = self._header(data)
        offset += -offset % 4
        (count,) = _U32.unpack_from(data, offset)
        offset += 4
        if 4 * count > len(data) - offset:
            raise ValueError(f'{count} names beyond the end')
        names = []
        for _ in range(count):
            offset += -offset % 4
            (size,) = _U32.unpack_from(data, offset)
            end = offset + 4 + size
            if size < 1 or end > len(data) or data[end - 1] != 0:
                raise ValueError(f'a name of {size} bytes')
            names.append(data[offset + 4:end - 1].decode())
            offset = end
        position, offset = self._doubles(data, offset)
        velocity, offset = self._doubles(data, offset)
        effort, _ = self._doubles(data, offset)
        return self.joint_state_class(head, names, position, velocity, effort)


def is_decoded(msg) -> bool:
    """Whether ``msg`` is a sensor message :func:`decode_serialized` made from bytes.

    Such an object is new for each message and only read, so a result computed from it
    may be kept by its identity; a message object of rclpy's classes may be one that its
    sender fills again (a test, a node publishing in its own process).
    """
    return msg.__class__ in _decoded_classes


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
        if msg[:4] == _PLAIN_CDR_LE:     # what a ROS 2 base sends: one comparison
            fast = _fast_decoders.get(typename)
            if fast is not None:
                return fast(msg[4:])
        elif len(msg) < 4 or msg[0] != 0 or msg[1] not in (0, 1) or msg[2:4] != b'\x00\x00':
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
