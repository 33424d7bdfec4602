"""The time-scaled reference's compiled sample (core/retiming_kernel.py), the interpreted one's.

The kernel compiles the module functions of retiming and reference_curves and composes
them as ``TimeScaled._interpreted_sample`` does: the samples must be the same floats, for
every closed-form curve, at times off any grid, before t = 0 and far along the path (the
tables' arrays grown many times), with either lead.
"""

import dataclasses
import math

import numpy as np
import pytest

from compiled_harness import assert_records_the_same_bits, stale_kernel_module

from wip_control.core import time_scaling
from wip_control.core.references import make_reference, ReferenceParams
from wip_control.core.time_scaling import TimeScaled

CLOSED_FORMS = {
    'trifolium': {},
    'circle': {'circle_radius': 1.0, 'circle_speed': 0.6},     # ω 0.6 > ωmax: re-timed
    'line': {'line_speed': 1.4},                               # υ 1.4 > υmax: re-timed
    'figure_eight': {'figure_eight_period': 20.0},
    'hold': {},
}


def twins(config):
    """Two references of ``config`` with tables of their own; the second compiled."""
    made = make_reference(config)
    interpreted, compiled = (
        TimeScaled(made.base, made.max_speed, made.max_yaw_rate, made.rate_limit, made.step,
                   made.speed_lead_time, made.speed_lead_time_accelerating)
        for _ in range(2))
    assert compiled.use_compiled() == ''
    assert compiled._kernel is not None and compiled._memo is None
    return interpreted, compiled


@pytest.mark.parametrize('kind', sorted(CLOSED_FORMS))
@pytest.mark.parametrize('leads', [(0.75, 0.75), (0.75, 0.3), (0.0, 0.0), (0.0, 0.3)])
def test_the_compiled_sample_is_the_interpreted_one_to_the_bit(kind, leads):
    config = ReferenceParams(kind=kind, time_scaling=True, path_max_speed=0.8,
                             path_max_yaw_rate=0.3, path_speed_lead_time=leads[0],
                             path_speed_lead_time_accelerating=leads[1],
                             **CLOSED_FORMS[kind])
    interpreted, compiled = twins(config)
    rng = np.random.default_rng(3)
    # Sensor stamps: 200 Hz with jitter from before the start to 300 s (30 000 nodes: the
    # arrays' buffers double five times), and a few far-apart times.
    times = np.concatenate([np.cumsum(0.005 + rng.uniform(-2e-4, 2e-4, 60000)) - 0.4,
                            [0.0, -3.0, 1e-9, 299.9876543]])
    kernel, calls = compiled._kernel, []

    def counted(*args):
        calls.append(args[0])
        return kernel(*args)

    compiled._kernel = counted
    # (Without a lead, the re-timed state itself, whatever the accelerating lead.)
    expected = (interpreted._interpreted_sample if leads[0] > 0.0 else interpreted._timed)
    for t in times:
        t = float(t)
        assert tuple(compiled.sample(t)) == tuple(expected(t)), t
    assert len(calls) == len(times)   # every sample compiled


def test_a_curve_without_a_compiled_form_stays_interpreted():
    config = ReferenceParams(kind='waypoints', time_scaling=True,
                             waypoints_speed=1.0, waypoints_max_yaw_rate=0.5)
    reference = make_reference(config)
    assert 'no compiled form' in reference.use_compiled()
    assert reference._kernel is None
    assert reference.sample(1.234) == make_reference(config).sample(1.234)


def test_a_kernel_that_disagrees_is_not_used(monkeypatch):
    # A stale numba cache (a formula changed in time_scaling.py, the kernel's file not)
    # gives other floats: the reference says why and samples interpreted.
    from wip_control.core import compiled as compiled_module

    real = compiled_module.load_compiled(compiled_module.RETIMING_KERNEL)

    # One ulp off in υ until compiled afresh twice.
    Stale = stale_kernel_module('sample', real.sample, lambda out: (
        *out[:3], math.nextafter(out[3], math.inf), *out[4:]))

    monkeypatch.setattr(compiled_module, 'load_compiled', lambda name: Stale)
    reference = make_reference(ReferenceParams())
    why_not = reference.use_compiled()
    assert Stale.refreshed == 1 and 'differs from the interpreted one at t = ' in why_not
    assert reference._kernel is None and reference._memo is not None
    assert reference.sample(2.5) == make_reference(ReferenceParams()).sample(2.5)
    # A stale cache that compiling afresh mends: the kernel is used.
    Stale.refreshed, Stale.fixed_by = 0, 1
    reference = make_reference(ReferenceParams())
    assert reference.use_compiled() == '' and Stale.refreshed == 1
    assert reference._kernel == Stale.sample


def test_bad_times_are_refused_as_by_the_interpreted_sample():
    reference = make_reference(ReferenceParams())
    assert reference.use_compiled() == ''
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(ValueError, match='finite'):
            reference.sample(bad)
    far = reference.MAX_EXTENSION + 100.0
    with pytest.raises(ValueError, match='beyond the times sampled so far'):
        reference.sample(far)
    # And it goes on sampling afterwards, the same floats.
    assert reference.sample(3.21) == make_reference(ReferenceParams()).sample(3.21)


def test_references_sharing_tables_share_the_arrays_too():
    config = dataclasses.replace(ReferenceParams(), kind='figure_eight')
    first, second = make_reference(config), make_reference(config)
    assert first._tables is second._tables
    assert first.use_compiled() == '' and second.use_compiled() == ''
    far = [first.sample(t) for t in np.arange(0.0, 50.0, 0.0137)]
    assert [second.sample(t) for t in np.arange(0.0, 50.0, 0.0137)] == far
    fresh = TimeScaled(first.base, first.max_speed, first.max_yaw_rate, first.rate_limit,
                       first.step, first.speed_lead_time, first.speed_lead_time_accelerating,
                       tables=time_scaling.RetimingTables())
    assert [fresh._interpreted_sample(t) for t in np.arange(0.0, 50.0, 0.0137)] == far


def test_a_loop_samples_a_closed_form_curve_compiled_and_a_waypoint_path_interpreted():
    from wip_control.core.references import make_loop_reference

    compiled, warning = make_loop_reference(ReferenceParams())
    assert warning == '' and compiled.compiled
    waypoints, warning = make_loop_reference(ReferenceParams(
        kind='waypoints', time_scaling=True, waypoints_speed=1.0, waypoints_max_yaw_rate=0.5))
    assert warning == '' and not waypoints.compiled
    commanded, warning = make_loop_reference(ReferenceParams(kind='cmd_vel'))
    assert warning == '' and not isinstance(commanded, TimeScaled)


def test_the_in_process_run_records_the_same_bits_compiled_or_not(monkeypatch):
    # The runner samples the reference compiled: every recorded channel is the interpreted
    # run's to the bit (but the QP's wall-clock solve time).
    import wip_sim.core.runner as runner
    from wip_sim.core.scenario import scenario_from_mapping

    assert_records_the_same_bits(scenario_from_mapping({'duration': 12.0}), lambda: (
        monkeypatch.setattr(runner, 'make_loop_reference',
                            lambda config: (make_reference(config), ''))))
