"""The gyro estimator's compiled sample (core/estimator_kernel.py), the interpreter's.

The kernel compiles the module functions of the channels, the slip monitor and the dead
reckoning and composes them as ``StateEstimator.update`` does, on the objects' own state
arrays: the estimates must be the same floats, sample after sample, through what a robot
sees (sensor noise, wheels that spin, a dropped or repeated sample, GPS fixes, one far off,
the yaw wrapping), whichever of the two takes each sample.
"""

import dataclasses
import math

import numpy as np
import pytest

from compiled_harness import assert_records_the_same_bits, stale_kernel_module

from wip_control.core import estimator_kernel
from wip_control.core.eso import EsoParams
from wip_control.core.position import PositionParams
from wip_control.core.state_estimation import EstimatorOverflow, StateEstimator
from wip_description.params import ModelParams

MODEL = ModelParams()
H = 0.005
#: Absurd input gets its one error: no numpy warning on the way (the interpreted methods
#: compute on Python floats).
pytestmark = pytest.mark.filterwarnings('error::RuntimeWarning')


def twins(config=EsoParams(), **kwargs):
    """Two estimators of ``config``; the second takes its steady samples compiled."""
    interpreted = StateEstimator(MODEL, config, PositionParams(), **kwargs)
    compiled = StateEstimator(MODEL, config, PositionParams(), **kwargs)
    assert compiled.use_compiled() == ''
    return interpreted, compiled


def counting(estimator):
    """Count what the kernel did with each sample (estimator_kernel.TAKEN, ...)."""
    kernel, counts = estimator._kernel, {}

    def counted(*args):
        out = kernel(*args)
        counts[out[0]] = counts.get(out[0], 0) + 1
        return out

    estimator._kernel = counted
    return counts


def drive(seed=4, samples=1600):
    """Return samples (t, φl, φr, θ, ϕ, τl, τr, rates, fix) of a noisy drive with incidents."""
    rng = np.random.default_rng(seed)
    t, out = 0.0, []
    for k in range(samples):
        t += 2 * H if k == 700 else (0.0 if k == 900 else H)    # one dropped, one repeated
        spin_left = 60.0 * (t - 2.0) ** 2 if 2.0 <= t < 2.15 else 0.0
        spin_both = 50.0 * (t - 5.0) ** 2 if 5.0 <= t < 5.2 else 0.0
        fix = None
        if k % 20 == 3:
            fix = (0.4 * t + rng.normal(0.0, 0.02), 0.1 + rng.normal(0.0, 0.02))
            if k == 1203:
                fix = (40.0, -30.0)                              # far off: rejected
        out.append((t, 1.6 * t + 0.05 * math.sin(3 * t) + spin_left + spin_both
                    + rng.normal(0.0, 1e-3),
                    1.7 * t + spin_both + rng.normal(0.0, 1e-3),
                    0.04 * math.sin(2 * t) + rng.normal(0.0, 2e-3),
                    math.remainder(2.9 + 0.7 * t + rng.normal(0.0, 1e-3), 2 * math.pi),
                    3.0 * math.cos(4 * t) + (12.0 if spin_left or spin_both else 0.0),
                    2.0 * math.sin(5 * t) + (12.0 if spin_both else 0.0),
                    (0.08 * math.cos(2 * t) + rng.normal(0.0, 0.01),
                     0.7 + rng.normal(0.0, 0.01)), fix))
    return out


def run(estimator, samples):
    poses = []
    for t, left, right, pitch, yaw, tau_left, tau_right, rates, fix in samples:
        poses.append(estimator.update(t, left, right, pitch, yaw, tau_left, tau_right,
                                      rates, fix))
    return poses


def assert_same_bits(a, b):
    assert len(a) == len(b)
    for k, (x, y) in enumerate(zip(a, b)):
        assert np.array([*x.estimate, *x[1:]], dtype=float).tobytes() == \
            np.array([*y.estimate, *y[1:]], dtype=float).tobytes(), k


@pytest.mark.parametrize('settings', [
    {},
    {'config': EsoParams(obstacle_release_hold=0.5, obstacle_stall_time=0.1)},
    {'config': EsoParams(slip_max_acceleration=0.0)},
    {'encoders_relative_to_body': False},
    {'dead_reckoning': True},
])
def test_the_compiled_estimate_is_the_interpreted_one_to_the_bit(settings):
    interpreted, compiled = twins(**settings)
    counts = counting(compiled)
    samples = drive()
    if settings.get('dead_reckoning'):
        samples = [(*sample[:-1], None) for sample in samples]
    assert_same_bits(run(compiled, samples), run(interpreted, samples))
    # The kernel took nearly every sample; the interpreter the first two, those with a
    # fix, the one after the dropped sample and the repeated one.
    taken = counts[estimator_kernel.TAKEN]
    assert taken >= 0.9 * len(samples) and counts[estimator_kernel.NOT_TAKEN] >= 3
    if interpreted.slip is not None:
        assert interpreted.slip.events >= 2    # the slips happened, to both alike
        assert compiled.slip.state.tobytes() == interpreted.slip.state.tobytes()
    assert compiled.position.state.tobytes() == interpreted.position.state.tobytes()
    assert (compiled.position.accepted_fixes, compiled.position.rejected_fixes) == \
        (interpreted.position.accepted_fixes, interpreted.position.rejected_fixes)


def outcome(estimator, sample):
    """(error type or None, its text or the pose's bytes, the estimator's state after)."""
    try:
        pose = estimator.update(*sample[:-2], sample[-2], sample[-1])
        result = (None, np.array([*pose.estimate, *pose[1:]], dtype=float).tobytes())
    except ValueError as error:
        result = (type(error), str(error))
    return (*result, state_bytes(estimator))


def state_bytes(estimator):
    observer, slip = estimator.observer, estimator.slip
    arrays = [estimator.position.state] + ([] if slip is None else [slip.state])
    if observer is not None:
        arrays += [observer.yaw._s, observer.tilt._s, observer.longitudinal._s]
    return b''.join(a.tobytes() for a in arrays), estimator.started, estimator.yaw_unwrapped


@pytest.mark.parametrize('config', [EsoParams(), EsoParams(slip_max_acceleration=0.0)])
def test_bad_input_is_refused_as_by_the_interpreter(config):
    # Non-finite, and finite but absurd (an encoder or a torque near the largest float): the
    # same error and the same state after it, then both go on alike.
    samples = drive(samples=300)
    errors = set()
    # (φl, φr, τl = τr, the gyro's (θ̇, ω))
    for bad in [(math.nan, 0.0, 0.0, (0.0, 0.0)), (0.0, 0.0, math.inf, (0.0, 0.0)),
                (5e307, 5e307, 0.0, (0.0, 0.0)), (1e307, 1e307, 0.0, (0.0, 0.0)),
                (0.0, 0.0, 1e307, (0.0, 0.0)), (1e150, 0.0, 0.0, (0.0, 0.0)),
                (1e90, 0.0, 1e90, (1e90, 0.0)),
                (0.0, 0.0, 0.0, (0.0, 1.7e308)), (0.0, 0.0, 0.0, (1.7e308, 0.0))]:
        interpreted, compiled = twins(config)
        run(interpreted, samples)
        run(compiled, samples)
        t = samples[-1][0] + H
        outcomes = [outcome(estimator, (t, bad[0], bad[1], 0.0, 0.0, bad[2], bad[2], bad[3],
                                        None))
                    for estimator in (interpreted, compiled)]
        assert outcomes[0] == outcomes[1], bad
        errors.add(outcomes[0][0])
        for sample in samples[:30]:
            t += H
            later = (t, *sample[1:])
            assert outcome(interpreted, later) == outcome(compiled, later)
    assert ValueError in errors and EstimatorOverflow in errors


def test_an_int_time_is_converted_not_compiled_anew():
    interpreted, compiled = twins()
    samples = [(k, *sample[1:]) if k == 0 else sample
               for k, sample in enumerate(drive(samples=50))]
    assert_same_bits(run(compiled, samples), run(interpreted, samples))
    assert len(estimator_kernel.step.signatures) == 1
    with pytest.raises(TypeError):
        compiled._kernel(*[None] * 19)


def test_the_paper_estimator_stays_interpreted():
    estimator = StateEstimator(MODEL, EsoParams(estimator='paper'))
    assert "no compiled form of the 'paper' estimator" == estimator.use_compiled()
    assert estimator._kernel is None


def test_a_kernel_that_disagrees_is_not_used(monkeypatch):
    # A stale numba cache (a formula changed in slip.py, the kernel's file not) gives other
    # floats: the estimator says why and stays interpreted.
    from wip_control.core import compiled as compiled_module

    real = compiled_module.load_compiled(compiled_module.ESTIMATOR_KERNEL)

    # One ulp off in ŷ until compiled afresh twice.
    Stale = stale_kernel_module('step', real.step, lambda out: (
        *out[:5], math.nextafter(out[5], math.inf), *out[6:]))

    monkeypatch.setattr(compiled_module, 'load_compiled', lambda name: Stale)
    estimator = StateEstimator(MODEL)
    why_not = estimator.use_compiled()
    assert Stale.refreshed == 1 and 'differs from the interpreted one at t = ' in why_not
    assert estimator._kernel is None
    Stale.refreshed, Stale.fixed_by = 0, 1
    estimator = StateEstimator(MODEL)
    assert estimator.use_compiled() == '' and Stale.refreshed == 1
    assert estimator._kernel == Stale.step


def test_the_in_process_run_records_the_same_bits_compiled_or_not(monkeypatch):
    # The runner takes the estimator's steady samples compiled: every recorded channel is
    # the interpreted run's to the bit (but the QP's wall-clock solve time), on the MuJoCo
    # plant over a bump (wheels that slip and stall).
    from wip_sim.core.scenario import load_scenario

    scenario = dataclasses.replace(load_scenario('scenarios/mujoco_bump.yaml'), duration=8.0)
    assert_records_the_same_bits(scenario, lambda: monkeypatch.setattr(
        StateEstimator, 'use_compiled', lambda self: 'off'))


def test_the_compiled_remainder_and_fmod_are_the_c_librarys():
    import numba

    @numba.njit
    def both(x, y):
        return math.remainder(x, y), math.fmod(x, y)

    rng = np.random.default_rng(5)
    xs = rng.standard_normal(20000) * 10.0 ** rng.uniform(-3, 8, 20000)
    ys = np.where(np.arange(20000) % 2, 2 * math.pi,
                  np.abs(rng.standard_normal(20000)) * 10.0 ** rng.uniform(-2, 3, 20000))
    ties = [(k * 0.5 * y, y) for k in range(-41, 42) for y in (2 * math.pi, 1.0, 0.1)]
    for x, y in [*zip(xs.tolist(), ys.tolist()), *ties]:
        got, want = both(x, y), (math.remainder(x, y), math.fmod(x, y))
        assert np.array(got).tobytes() == np.array(want).tobytes(), (x, y)
