"""What the tests of the compiled kernels share: a run recorded both ways; a stale kernel."""

from typing import Callable

import numpy as np


def assert_records_the_same_bits(scenario, interpret: Callable[[], None]) -> None:
    """Run ``scenario`` in process compiled, then after ``interpret()``: the same bits.

    Every recorded channel but the QP's wall-clock solve time must be equal to the bit.
    ``interpret`` switches the kernel under test off (a monkeypatch).
    """
    import wip_sim.core.runner as runner

    compiled = runner.run_scenario(scenario).record.groups
    interpret()
    interpreted = runner.run_scenario(scenario).record.groups
    assert compiled.keys() == interpreted.keys()
    for group, channels in compiled.items():
        assert channels.keys() == interpreted[group].keys(), group
        for name, values in channels.items():
            if (group, name) != ('mpc', 'solve_time'):
                assert np.asarray(values).tobytes() == \
                    np.asarray(interpreted[group][name]).tobytes(), (group, name)


def stale_kernel_module(function: str, real: Callable, perturb: Callable, fixed_by: int = 2):
    """Return a stand-in kernel module whose ``function`` disagrees until compiled afresh.

    ``function`` is ``real`` with ``perturb`` applied to its output (a last bit off, as a
    stale numba cache gives) until ``refresh`` has been called ``fixed_by`` times.
    """
    class Stale:
        refreshed = 0

        @classmethod
        def refresh(cls):
            cls.refreshed += 1

    Stale.fixed_by = fixed_by

    def call(*args):
        out = real(*args)
        return perturb(out) if Stale.refreshed < Stale.fixed_by else out
    setattr(Stale, function, staticmethod(call))
    return Stale
