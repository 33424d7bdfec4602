"""ROS 2 messages written directly as serialized bytes (CDR), without rclpy.

rclpy publishes a message object by converting it field by field into its C structure and
serializing that, which was most of the viewer's cost (measured:
docs/decisions/recording-speed.md). The viewer publishes the bytes instead
(``Publisher.publish`` takes serialized messages), written here with :mod:`struct`, for the
types the viewer and the torque mixer send: the layout of
``rclpy.serialization.serialize_message`` of the message object, with zeros where rclpy
leaves its padding bytes as they were (the tests compare the lengths and the decoded
messages). A Path's poses never change once added, so
each pose is encoded once and a Path is the concatenation of its poses' bytes.

Encoding: plain CDR (XCDR1, what rmw_fastrtps writes for ROS 2), little endian: a 4-byte
encapsulation header, then the fields in declaration order, each primitive aligned to its
size counted from the end of that header; strings as uint32 length (with the NUL) + bytes +
NUL; sequences as uint32 count + elements; an empty sequence has no padding after its count.

Pure Python, no ROS import.
"""

from __future__ import annotations

import struct
from typing import Sequence

#: CDR_LE encapsulation (representation id 0x0001, options 0).
ENCAPSULATION = b'\x00\x01\x00\x00'
_NS_PER_S = 1_000_000_000
_ZEROS = bytes(8)
_I32_U32 = struct.Struct('<iI')
_U32 = struct.Struct('<I')
_POSE_DOUBLES = struct.Struct('<7d')
_COLOR = struct.Struct('<4f')
_36_DOUBLES = struct.Struct('<36d')
_3_INT32 = struct.Struct('<3i')


class CdrWriter:
    """Appends CDR fields, tracking the offset that alignment is counted from."""

    __slots__ = ('parts', 'offset')

    def __init__(self, offset: int = 0) -> None:
        self.parts: list[bytes] = []
        #: Bytes written after the encapsulation header (where alignment counts from).
        self.offset = offset

    def align(self, size: int) -> None:
        pad = -self.offset % size
        if pad:
            self.parts.append(_ZEROS[:pad])
            self.offset += pad

    def raw(self, data: bytes) -> None:
        """Bytes already encoded at the current offset's alignment."""
        self.parts.append(data)
        self.offset += len(data)

    def pack(self, alignment: int, codec: struct.Struct, *values) -> None:
        self.align(alignment)
        self.raw(codec.pack(*values))

    def u32(self, value: int) -> None:
        self.pack(4, _U32, value)

    def boolean(self, value: bool) -> None:
        self.raw(b'\x01' if value else b'\x00')

    def string(self, text: str) -> None:
        data = text.encode()
        self.u32(len(data) + 1)
        self.raw(data + b'\x00')

    def doubles(self, values: Sequence[float]) -> None:
        """Append a fixed-size array (or the elements of a sequence) of float64."""
        if values:
            self.align(8)
            self.raw(struct.pack(f'<{len(values)}d', *values))   # struct caches the format

    def header(self, stamp_ns: int, frame_id: str) -> None:
        """std_msgs/Header: builtin_interfaces/Time (int32 sec, uint32 nanosec), frame_id."""
        sec, nanosec = divmod(int(stamp_ns), _NS_PER_S)
        self.pack(4, _I32_U32, sec, nanosec)
        self.string(frame_id)

    def pose(self, position: Sequence[float], orientation: Sequence[float]) -> None:
        """geometry_msgs/Pose: Point (x, y, z), Quaternion (x, y, z, w)."""
        self.pack(8, _POSE_DOUBLES, *position, *orientation)

    def message(self) -> bytes:
        return ENCAPSULATION + b''.join(self.parts)


def odometry(stamp_ns: int, frame_id: str, child_frame_id: str,
             position: Sequence[float], orientation: Sequence[float],
             pose_covariance: Sequence[float], linear: Sequence[float],
             angular: Sequence[float], twist_covariance: Sequence[float]) -> bytes:
    """nav_msgs/Odometry."""
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.string(child_frame_id)
    w.pose(position, orientation)
    w.pack(8, _36_DOUBLES, *pose_covariance)
    w.doubles((*linear, *angular))
    w.pack(8, _36_DOUBLES, *twist_covariance)
    return w.message()


def marker(w: CdrWriter, stamp_ns: int, frame_id: str, ns: str, marker_id: int,
           marker_type: int, action: int, position: Sequence[float],
           orientation: Sequence[float], scale: Sequence[float], color: Sequence[float],
           points: Sequence[float] = ()) -> None:
    """visualization_msgs/Marker (Jazzy's fields) into ``w``; ``points`` flat (x, y, z, ...).

    Every field not named here keeps its default: no lifetime, not frame-locked, no
    per-point colours, texture, UV coordinates, text or mesh.
    """
    w.header(stamp_ns, frame_id)
    w.string(ns)
    w.pack(4, _3_INT32, marker_id, marker_type, action)
    w.pose(position, orientation)
    w.doubles(scale)
    w.pack(4, _COLOR, *color)
    w.pack(4, _I32_U32, 0, 0)            # lifetime (builtin_interfaces/Duration)
    w.boolean(False)                     # frame_locked
    if len(points) % 3:
        raise ValueError(f'points are x, y, z triples, got {len(points)} numbers')
    w.u32(len(points) // 3)
    w.doubles(points)
    w.u32(0)                             # colors
    w.string('')                         # texture_resource
    w.header(0, '')                      # texture: sensor_msgs/CompressedImage
    w.string('')                         # texture.format
    w.u32(0)                             # texture.data
    w.u32(0)                             # uv_coordinates
    w.string('')                         # text
    w.string('')                         # mesh_resource
    w.string('')                         # mesh_file.filename
    w.u32(0)                             # mesh_file.data
    w.boolean(False)                     # mesh_use_embedded_materials


def pose_stamped(stamp_ns: int, frame_id: str, position: Sequence[float],
                 orientation: Sequence[float], offset: int = 0) -> bytes:
    """geometry_msgs/PoseStamped as it is encoded starting at ``offset`` (mod 8 matters)."""
    w = CdrWriter(offset)
    w.header(stamp_ns, frame_id)
    w.pose(position, orientation)
    return b''.join(w.parts)


def path(stamp_ns: int, frame_id: str, first_pose: tuple, aligned_poses: Sequence[bytes]
         ) -> bytes:
    """nav_msgs/Path from its poses.

    ``first_pose`` is the first pose's (stamp_ns, frame_id, position, orientation), or None
    for an empty path; ``aligned_poses`` the others, each from :func:`pose_stamped` at an
    offset that is a multiple of 8. A pose ends with a float64, so every pose after the
    first starts at such an offset; only the first one's padding depends on the header.
    """
    w = CdrWriter()
    w.header(stamp_ns, frame_id)
    w.u32(len(aligned_poses) + (first_pose is not None))
    if first_pose is not None:
        w.raw(pose_stamped(*first_pose, offset=w.offset))
        w.raw(b''.join(aligned_poses))
    elif aligned_poses:
        raise ValueError('aligned poses without a first pose')
    return w.message()


def tf_message(transforms: Sequence[tuple]) -> bytes:
    """tf2_msgs/TFMessage.

    ``transforms``: (stamp_ns, frame_id, child_frame_id, translation, rotation) each, a
    geometry_msgs/TransformStamped (a Transform is laid out as a Pose: 7 float64).
    """
    w = CdrWriter()
    w.u32(len(transforms))
    for stamp_ns, frame_id, child_frame_id, translation, rotation in transforms:
        w.header(stamp_ns, frame_id)
        w.string(child_frame_id)
        w.pose(translation, rotation)
    return w.message()


def float64_multi_array(values: Sequence[float]) -> bytes:
    """std_msgs/Float64MultiArray with an empty layout (no dimensions, data_offset 0).

    One struct call: the torque mixer sends one per tick (the effort command). The same
    bytes as :class:`CdrWriter` would write: two uint32 (dim count, data_offset), the
    data's count, 4 bytes of padding to the doubles' 8-byte alignment, the doubles.
    """
    return struct.pack(f'<4sIII4x{len(values)}d', ENCAPSULATION, 0, 0, len(values), *values)
