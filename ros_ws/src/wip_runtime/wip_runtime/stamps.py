"""Time stamps: builtin_interfaces/Time and std_msgs/Header from integer nanoseconds."""

from __future__ import annotations

from builtin_interfaces.msg import Time
from std_msgs.msg import Header

_NS_PER_S = 1_000_000_000


def stamp_to_ns(stamp: Time) -> int:
    """builtin_interfaces/Time -> integer nanoseconds (exact)."""
    return stamp.sec * _NS_PER_S + stamp.nanosec


def ns_to_stamp(stamp_ns: int) -> Time:
    """Integer nanoseconds -> builtin_interfaces/Time (exact, nanosec in [0, 1e9))."""
    sec, nanosec = divmod(int(stamp_ns), _NS_PER_S)
    return Time(sec=sec, nanosec=nanosec)


def make_header(stamp_ns: int, frame_id: str = '') -> Header:
    """std_msgs/Header with the stamp [ns] and frame."""
    return Header(stamp=ns_to_stamp(stamp_ns), frame_id=frame_id)
