"""Disturbance channels: closed forms of each kind, noise reproducibility, config errors."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from wip_runtime.config import ParamError
from wip_sim.core.disturbances import (EDGE_TOLERANCE, DisturbanceComponent,
                                           DisturbanceParams, Disturbances)

finite = dict(allow_nan=False, allow_infinity=False)
times = st.floats(0.0, 200.0, **finite)


def only(channel, *components):
    """Config with ``components`` on ``channel`` and nothing elsewhere."""
    return DisturbanceParams(**{'yaw': (), 'longitudinal': (), 'tilt': (),
                                channel: tuple(components)})


@settings(max_examples=200, deadline=None)
@given(t=times)
def test_default_is_the_papers_section_v(t):
    d1, d2, d3 = Disturbances(DisturbanceParams()).sample(t)
    assert d1 == pytest.approx(math.sin(0.5 * t), abs=1e-12)    # τd1 = sin(0.5 t)
    assert d2 == (10.0 if 30.0 <= t < 30.1 else 0.0)             # collision pulse
    assert d3 == 0.0


@settings(max_examples=200, deadline=None)
@given(t=times, amplitude=st.floats(-5, 5, **finite), w=st.floats(0, 10, **finite),
       phase=st.floats(-4, 4, **finite), start=st.floats(0, 100, **finite))
def test_sine_starts_at_its_start_time_with_its_phase(t, amplitude, w, phase, start):
    c = DisturbanceComponent(kind='sine', amplitude=amplitude, frequency=w, phase=phase,
                             start_time=start)
    d1, _, _ = Disturbances(only('yaw', c)).sample(t)
    # Active from start, less the documented 1 ns tolerance on time edges.
    active = t >= start - EDGE_TOLERANCE
    expected = amplitude * math.sin(w * (t - start) + phase) if active else 0.0
    assert d1 == pytest.approx(expected, abs=1e-12)   # same formula: rounding only


def test_pulse_is_its_amplitude_on_the_half_open_window_only():
    c = DisturbanceComponent(kind='pulse', amplitude=-3.0, start_time=2.0, width=0.25)
    sample = Disturbances(only('longitudinal', c)).sample
    assert sample(2.0)[1] == -3.0                # closed at the start
    assert sample(2.25 - 1e-6)[1] == -3.0
    assert sample(2.25)[1] == 0.0                # open at the end
    assert sample(2.0 - 1e-6)[1] == 0.0
    assert sample(10.0)[1] == 0.0


@pytest.mark.parametrize('dt', [1e-3, 5e-4, 5e-3])
def test_pulse_covers_width_over_dt_integrator_steps_whatever_the_rounding_of_k_dt(dt):
    # Step starts k·dt carry rounding errors of a few ulps around 30 s; the 1 ns edge
    # tolerance makes the pulse cover exactly width/dt steps, as it should.
    sample = Disturbances(DisturbanceParams()).sample
    active = sum(sample(k * dt)[1] == 10.0 for k in range(int(40.0 / dt)))
    assert active == round(0.1 / dt)


def test_step_holds_its_amplitude_from_the_start_time():
    c = DisturbanceComponent(kind='step', amplitude=0.7, start_time=5.0)
    sample = Disturbances(only('tilt', c)).sample
    assert [sample(t)[2] for t in (0.0, 4.999, 5.0, 1e3)] == [0.0, 0.0, 0.7, 0.7]


def test_components_of_a_channel_add_up_and_channels_are_separate():
    config = DisturbanceParams(
        yaw=(DisturbanceComponent(kind='step', amplitude=1.0),
             DisturbanceComponent(kind='sine', amplitude=2.0, frequency=1.0)),
        longitudinal=(DisturbanceComponent(kind='step', amplitude=-4.0, start_time=1.0),),
        tilt=(DisturbanceComponent(kind='step', amplitude=0.5),
              DisturbanceComponent(kind='step', amplitude=0.25),
              DisturbanceComponent(kind='pulse', amplitude=1.0, width=1.0)))
    d1, d2, d3 = Disturbances(config).sample(0.5)
    assert d1 == pytest.approx(1.0 + 2.0 * math.sin(0.5), abs=1e-15)
    assert d2 == 0.0
    assert d3 == 1.75


def _noise(seed=0, component_seed=0, std=0.2, period=0.01, start=0.0):
    c = DisturbanceComponent(kind='noise', std=std, noise_period=period, start_time=start,
                             seed=component_seed)
    return Disturbances(only('tilt', c), seed=seed)


def test_noise_is_reproducible_from_the_seed_and_independent_of_query_order():
    times_forward = np.arange(0.0, 100.0, 0.013)

    def series(noise, t):
        return [noise.sample(ti)[2] for ti in t]

    a = series(_noise(seed=7), times_forward)
    b = series(_noise(seed=7), times_forward[::-1])[::-1]   # new object, queried backwards
    assert a == b                                           # exact: the same draws
    c = series(_noise(seed=8), times_forward)
    d = series(_noise(seed=7, component_seed=1), times_forward)
    assert a != c and a != d


def test_noise_is_held_over_its_period_whatever_the_integrator_step():
    noise = _noise(period=0.01, start=1.0)
    assert noise.sample(0.999)[2] == 0.0
    # Samples taken at 1 kHz and at 4 kHz see the same held value in each period.
    fine = [noise.sample(1.0 + k * 0.00025)[2] for k in range(400)]
    coarse = [noise.sample(1.0 + k * 0.001)[2] for k in range(100)]
    assert fine[::4] == coarse
    per_period = np.array(coarse).reshape(10, 10)
    assert np.all(per_period == per_period[:, :1])      # constant within each period
    assert len(set(per_period[:, 0])) == 10              # fresh value at each period


def test_noise_has_the_configured_standard_deviation():
    std, n = 0.3, 20000
    noise = _noise(std=std, seed=3)
    values = np.array([noise.sample(k * 0.01)[2] for k in range(n)])
    # Standard errors for n = 20000 samples: mean σ/√n = 0.002, std σ/√(2n) = 0.0015;
    # four standard errors each.
    assert abs(values.mean()) < 4 * std / math.sqrt(n)
    assert values.std() == pytest.approx(std, abs=4 * std / math.sqrt(2 * n))
    # Successive held samples are independent: lag-1 correlation within ±4/√n.
    assert abs(np.corrcoef(values[:-1], values[1:])[0, 1]) < 4 / math.sqrt(n)


# ----------------------------------------------------------------------------- configuration

@pytest.mark.parametrize('mapping, message', [
    ({'longitudinal': [{'kind': 'pulse', 'amplitude': 1.0, 'widht': 0.1}]},
     r'^disturbances\.longitudinal\[0\]\.widht: unknown key'),
    ({'yaw': [{'kind': 'step'}, {'kind': 'sine', 'width': 0.1}]},
     r"^disturbances\.yaw\[1\]\.width: not used by kind 'sine'"),
    ({'tilt': [{'kind': 'pulse', 'amplitude': 1.0}]},
     r'^disturbances\.tilt\[0\]\.width: a pulse needs width > 0'),
    ({'tilt': [{'kind': 'bump'}]}, r'^disturbances\.tilt\[0\]\.kind: .bump. is not one of'),
    ({'tilt': [{'kind': 'noise', 'std': -1.0}]}, r'^disturbances\.tilt\[0\]\.std: must be >= 0'),
    ({'tilt': [{'kind': 'noise', 'noise_period': 0.0}]},
     r'^disturbances\.tilt\[0\]\.noise_period: must be > 0'),
    ({'yaw': {'kind': 'sine'}}, r'^disturbances\.yaw: expected a list'),
    ({'roll': []}, r'^disturbances\.roll: unknown key'),
])
def test_bad_disturbance_config_names_the_key(mapping, message):
    with pytest.raises(ParamError, match=message):
        DisturbanceParams.from_mapping(mapping, 'disturbances')


def test_missing_channels_keep_the_paper_default_and_empty_lists_disable():
    config = DisturbanceParams.from_mapping({'yaw': []}, 'disturbances')
    assert config.yaw == () and config.longitudinal == DisturbanceParams().longitudinal
    assert DisturbanceParams.from_mapping(None, 'disturbances') == DisturbanceParams()
    assert Disturbances(DisturbanceParams.disabled()).sample(30.05) == (0.0, 0.0, 0.0)


def test_to_mapping_round_trips():
    config = DisturbanceParams(
        tilt=(DisturbanceComponent(kind='noise', std=0.1, noise_period=0.02, seed=4),
              DisturbanceComponent(kind='step', amplitude=2.0, start_time=3.0)))
    assert DisturbanceParams.from_mapping(config.to_mapping(), 'd') == config


def test_programmatic_config_is_checked_when_used():
    bad = only('longitudinal', DisturbanceComponent(kind='step', amplitude=1.0),
               DisturbanceComponent(kind='step', frequency=2.0))
    with pytest.raises(ParamError, match=r'^longitudinal\[1\]\.frequency: not used by kind'):
        Disturbances(bad)
    with pytest.raises(ValueError, match='seed'):
        Disturbances(DisturbanceParams(), seed=-1)


def test_sample_many_equals_sample_at_every_time():
    # The runner evaluates a block of plant steps at once: same values, all channels,
    # including an empty one (tilt) and held noise.
    config = DisturbanceParams.from_mapping({
        'yaw': [{'kind': 'sine', 'amplitude': 1.0, 'frequency': 0.5}],
        'longitudinal': [{'kind': 'pulse', 'amplitude': 10.0, 'start_time': 0.3, 'width': 0.1},
                         {'kind': 'noise', 'std': 0.2, 'noise_period': 0.01}],
        'tilt': []}, 'disturbances')
    # Every kind, and a channel of three components (summed in the same order).
    config_every_kind = DisturbanceParams.from_mapping({
        'yaw': [{'kind': 'step', 'amplitude': -0.7, 'start_time': 0.5}],
        'longitudinal': [{'kind': 'sine', 'amplitude': 0.3, 'frequency': 7.0, 'phase': 0.2,
                          'start_time': 0.25},
                         {'kind': 'step', 'amplitude': 0.1, 'start_time': 0.1},
                         {'kind': 'pulse', 'amplitude': 2.0, 'start_time': 0.6, 'width': 0.2}],
        'tilt': [{'kind': 'noise', 'std': 0.5, 'noise_period': 0.002, 'start_time': 0.05}]},
        'disturbances')
    disturbances = Disturbances(config_every_kind, seed=9)
    times = [k * 0.005 + j * 0.001 for k in range(200) for j in range(5)]
    table = disturbances.sample_many(times)
    assert [tuple(row) for row in table] == [disturbances.sample(t) for t in times]
    assert np.count_nonzero(table, axis=0).min() >= 500   # every channel is exercised
    disturbances = Disturbances(config, seed=4)
    times = [k * 0.005 + j * 0.001 for k in range(200) for j in range(5)]
    table = disturbances.sample_many(times)
    assert table.shape == (1000, 3)
    assert [tuple(row) for row in table] == [disturbances.sample(t) for t in times]
