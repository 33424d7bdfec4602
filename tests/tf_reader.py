"""A minimal tf consumer for the tests: frames from /tf and /tf_static, composed.

Independent of the code under test: it reads only the transforms' fields (parent, child,
translation, rotation, stamp) and composes them with its own quaternion algebra, the way
tf2's ``lookup_transform`` chains parent links from a frame up to the target.
"""

from __future__ import annotations

import math

import numpy as np


def quaternion_multiply(a, b):
    """Hamilton product of (x, y, z, w) quaternions."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def rotate(q, v):
    x, y, z, w = q
    u = np.array([x, y, z])
    v = np.asarray(v, dtype=float)
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


def yaw(q) -> float:
    x, y, z, w = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


class TfBuffer:
    """Transforms by child frame: static ones, and dynamic ones by stamp [ns]."""

    def __init__(self) -> None:
        self.static: dict[str, tuple] = {}
        self.dynamic: dict[str, dict[int, tuple]] = {}

    def add(self, transforms, static: bool = False) -> None:
        """Add a TFMessage's transforms (message objects of any decoder with ROS's fields)."""
        for t in transforms:
            stamp = t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec
            tr, rot = t.transform.translation, t.transform.rotation
            entry = (t.header.frame_id, (tr.x, tr.y, tr.z), (rot.x, rot.y, rot.z, rot.w))
            if static:
                self.static[t.child_frame_id] = entry
            else:
                self.dynamic.setdefault(t.child_frame_id, {})[stamp] = entry

    def lookup(self, target: str, source: str, stamp_ns: int):
        """Return (translation, rotation) of ``source`` in ``target`` at exactly ``stamp_ns``.

        KeyError when a link of the chain is missing (or has no transform at that stamp).
        """
        translation, rotation = np.zeros(3), (0.0, 0.0, 0.0, 1.0)
        frame = source
        while frame != target:
            if frame in self.static:
                parent, t, q = self.static[frame]
            else:
                parent, t, q = self.dynamic[frame][stamp_ns]
            # parent <- frame, then frame <- source (accumulated so far).
            translation = np.asarray(t) + rotate(q, translation)
            rotation = quaternion_multiply(q, rotation)
            frame = parent
        return translation, rotation
