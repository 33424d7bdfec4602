"""``math.fmod`` and ``math.remainder`` in numba-compiled code, exact like CPython's.

numba has neither; the kernels (``estimator_kernel``, ``safety_kernel``) compile the
interpreter's own functions that call them (the yaw unwrapping, the runaway guard's
heading); importing this module registers them.
"""

from __future__ import annotations

import math

import numpy as np
from numba.extending import overload


@overload(math.fmod)
def _fmod(x, y):
    """``math.fmod`` in compiled code (numba has none): C's fmod, exact like CPython's."""
    return lambda x, y: np.fmod(x, y)


@overload(math.remainder)
def _remainder(x, y):
    """``math.remainder`` in compiled code (numba has none): the IEEE remainder, exact.

    x − n y with n the integer nearest x / y (ties to even), from C's fmod: r = fmod(x, |y|)
    is x − trunc(x / |y|) |y| exactly, one |y| is taken from it past |y| / 2 (exactly: the
    two are within a factor of two), and at |y| / 2 when trunc(x / |y|) is odd, which is
    when fmod(x, 2 |y|) is |y| or more.
    """
    def remainder(x, y):
        size = abs(y)
        r = np.fmod(x, size)
        half = 0.5 * size
        if abs(r) > half or (abs(r) == half and abs(np.fmod(x, 2.0 * size)) >= size):
            r -= math.copysign(size, r)
        return r
    return remainder
