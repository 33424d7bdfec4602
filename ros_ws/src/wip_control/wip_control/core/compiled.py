"""The numba-compiled kernels of the core, imported and warmed up once per process.

Each kernel module (``mpc_kernel``, ``qp_polish``, ``retiming_kernel``,
``estimator_kernel``, ``safety_kernel``, ``attitude_kernel``) has a ``warm_up()`` that
loads its code from numba's cache or compiles it. It is called where a controller is made
(an MPC, a loop's reference, a gyro estimator, the mixer's safety monitor, a node that reads
an IMU), not in its first tick; a process that makes none of them does not import numba.
``python3 -m wip_control.core.compiled`` fills numba's cache of all of them (scripts/setup
and the Docker image do, after building).
"""

from __future__ import annotations

import hashlib
import importlib
import math
import operator
import pathlib
import sys
from types import ModuleType
from typing import Callable, Iterable

#: The kernel modules of the controllers: the MPC's QP assembly, the QP's polish, the
#: time-scaled reference's real-time sample, the gyro estimator's sample, the safety
#: layer's steady tick, the body's attitude from an IMU sample.
MPC_KERNEL = f'{__package__}.mpc_kernel'
QP_POLISH = f'{__package__}.qp_polish'
RETIMING_KERNEL = f'{__package__}.retiming_kernel'
ESTIMATOR_KERNEL = f'{__package__}.estimator_kernel'
SAFETY_KERNEL = f'{__package__}.safety_kernel'
ATTITUDE_KERNEL = f'{__package__}.attitude_kernel'
KERNELS = (MPC_KERNEL, QP_POLISH, RETIMING_KERNEL, ESTIMATOR_KERNEL, SAFETY_KERNEL,
           ATTITUDE_KERNEL)

_loaded: dict[str, ModuleType] = {}


def load_compiled(module_name: str) -> ModuleType:
    """Return the kernel module ``module_name``, imported and warmed up on the first call."""
    module = _loaded.get(module_name)
    if module is None:
        module = importlib.import_module(module_name)
        module.warm_up()
        _loaded[module_name] = module
    return module


def load_checked(module_name: str,
                 difference: Callable[[ModuleType], str]) -> tuple[ModuleType | None, str]:
    """Return the kernel module ``module_name`` and '' if ``difference(module)`` finds none.

    ``difference`` compares the kernel with the interpreter ('' when they agree). Where they
    differ, numba's cache may be stale (a formula changed since it was filled): compiled
    afresh once and compared again; (None, the difference) if they still differ.
    """
    module = load_compiled(module_name)
    found = difference(module)
    if found:
        module.refresh()
        found = difference(module)
    return (None, found) if found else (module, '')


def array_slot(array: str, index: int, doc: str) -> property:
    """Return a float attribute kept at ``index`` of the object's state array ``array``.

    The objects whose state a kernel advances in place (the channels, the slip monitor, the
    position) keep it in a float64 array; their attributes read and write its slots.
    """
    get = operator.attrgetter(array)
    return property(lambda self: float(get(self)[index]),
                    lambda self, value: get(self).__setitem__(index, value), doc=doc)


def typed_slot(array: str, index: int, kind: type, doc: str) -> property:
    """Return an attribute of type ``kind`` (bool, int, float) kept at ``index`` of ``array``."""
    get = operator.attrgetter(array)
    return property(lambda self: kind(get(self)[index]),
                    lambda self, value: get(self).__setitem__(index, kind(value)), doc=doc)


def optional_slot(array: str, index: int, doc: str) -> property:
    """Return a float attribute kept at ``index`` of ``array`` that may be None (NaN there)."""
    get = operator.attrgetter(array)

    def read(self) -> float | None:
        value = float(get(self)[index])
        return None if math.isnan(value) else value

    def write(self, value: float | None) -> None:
        get(self)[index] = math.nan if value is None else value
    return property(read, write, doc=doc)


def sources_digest(functions: Iterable[Callable], kernel_module: str,
                   also: Iterable[ModuleType] = ()) -> str:
    """SHA-256 of the files of ``functions`` (those a kernel compiles) and of the kernel's own.

    Derived from the functions themselves, so that a file whose function a kernel starts to
    compile is in its digest. ``also``: modules whose constants the compiled functions read
    (numba keeps a global's value in the compiled code) or whose overloads they call.
    """
    digest = hashlib.sha256()
    names = ({function.__module__ for function in functions} | {kernel_module}
             | {module.__name__ for module in also})
    for name in sorted(names):
        digest.update(pathlib.Path(sys.modules[name].__file__).read_bytes())
    return digest.hexdigest()


def refresh_if_sources_changed(cache_path: str, stamp_name: str, digest: str,
                               refresh: Callable[[], None]) -> None:
    """Compile a kernel afresh (``refresh``) when its sources' ``digest`` is not the one kept.

    numba's cache knows only the kernel file's date, not that of the files whose functions
    it compiles (``register_jitable``): the digest of all of them is kept in ``stamp_name``
    beside the cache (``cache_path``), and written after compiling afresh.
    """
    stamp = pathlib.Path(cache_path) / stamp_name
    try:
        known = stamp.read_text(encoding='utf-8')
    except OSError:
        known = ''
    if known != digest:
        refresh()
        try:
            stamp.write_text(digest, encoding='utf-8')
        except OSError:
            pass    # a read-only cache: compiled afresh in every process, still correct


if __name__ == '__main__':
    for kernel in KERNELS:
        load_compiled(kernel)
