"""Input synchronisation of the controller nodes (``wip_runtime.sync``, pure Python).

The lockstep graph is deterministic only if a node computes t_k from exactly the inputs
stamped t_k whatever order DDS delivers them in; these tests check that property over
permutations, the bounded buffer, the gate, the latest-value mode and the tick grid.
"""

import itertools

from hypothesis import given, settings, strategies as st
import pytest

from wip_runtime.sync import (decimation, ExactTimeSync, is_decimated_tick, LatestSync, on_grid,
                              tick_index)

NAMES = ('a', 'b', 'c')


def _recorder():
    out = []
    return out, lambda stamp, values: out.append((stamp, dict(values)))


@given(st.permutations([(name, stamp) for stamp in (10, 20, 30) for name in NAMES]))
@settings(max_examples=200, deadline=None)
def test_exact_sync_emits_complete_sets_with_their_own_values_in_stamp_order(order):
    out, callback = _recorder()
    sync = ExactTimeSync(NAMES, callback)
    for name, stamp in order:
        sync.add(name, stamp, (name, stamp))
    # The emitted stamps strictly increase and each set holds the values of its stamp.
    stamps = [s for s, _ in out]
    assert stamps == sorted(set(stamps))
    for stamp, values in out:
        assert values == {n: (n, stamp) for n in NAMES}
    # A stamp is emitted iff its set completed before any later stamp's set did.
    completion = {s: max(i for i, (_, t) in enumerate(order) if t == s) for s in (10, 20, 30)}
    expected = [s for s in sorted(completion)
                if all(completion[s] < completion[later] for later in completion if later > s)]
    assert stamps == expected
    assert sync.emitted == len(expected)
    assert not sync.pending


@given(st.permutations(NAMES))
@settings(max_examples=20, deadline=None)
def test_exact_sync_one_stamp_is_emitted_once_in_any_arrival_order(order):
    out, callback = _recorder()
    sync = ExactTimeSync(NAMES, callback)
    emitted = [sync.add(name, 5_000_000, name.upper()) for name in order]
    assert emitted == [False, False, True]  # only the last arrival completes the set
    assert out == [(5_000_000, {'A'.lower(): 'A', 'b': 'B', 'c': 'C'})]


def test_exact_sync_drops_inputs_at_or_before_the_last_emitted_stamp():
    out, callback = _recorder()
    sync = ExactTimeSync(('a', 'b'), callback)
    sync.add('a', 2, 1)
    sync.add('b', 2, 1)
    assert not sync.add('a', 2, 9) and not sync.add('b', 1, 9)
    assert sync.dropped['stale'] == 2 and len(out) == 1


def test_exact_sync_superseded_incomplete_sets_are_dropped():
    out, callback = _recorder()
    sync = ExactTimeSync(('a', 'b'), callback)
    sync.add('a', 1, 'old')          # its 'b' never comes
    sync.add('a', 2, 'x')
    sync.add('b', 2, 'y')
    assert out == [(2, {'a': 'x', 'b': 'y'})]
    assert sync.dropped['superseded'] == 1 and not sync.pending


def test_exact_sync_discard_forgets_one_stamp_only():
    out, callback = _recorder()
    sync = ExactTimeSync(('a', 'b'), callback)
    sync.add('a', 1, 'answered elsewhere')
    sync.add('a', 2, 'x')
    sync.discard(1)
    sync.discard(7)                  # nothing buffered: no effect
    assert sync.pending == {2: ('a',)}
    sync.add('b', 2, 'y')
    assert out == [(2, {'a': 'x', 'b': 'y'})] and not sync.dropped['superseded']


def test_exact_sync_buffer_is_bounded_and_evicts_the_oldest_stamp():
    out, callback = _recorder()
    sync = ExactTimeSync(('a', 'b'), callback, max_pending=4)
    for stamp in range(10):
        sync.add('a', stamp, stamp)
    assert list(sync.pending) == [6, 7, 8, 9]
    assert sync.dropped['evicted'] == 6
    sync.add('b', 7, 'b7')           # completing 7 supersedes 6 and emits 7
    assert out == [(7, {'a': 7, 'b': 'b7'})]
    assert list(sync.pending) == [8, 9]


def test_exact_sync_required_inputs_may_depend_on_the_stamp():
    out, callback = _recorder()
    # 'gps' only at multiples of 10, like the ESO's GPS ticks.
    sync = ExactTimeSync(('imu', 'gps'), callback,
                         required=lambda s: ('imu', 'gps') if s % 10 == 0 else ('imu',))
    sync.add('imu', 10, 'i10')
    assert out == []                 # waits for the fix
    sync.add('gps', 10, 'g10')
    sync.add('imu', 11, 'i11')
    assert out == [(10, {'imu': 'i10', 'gps': 'g10'}), (11, {'imu': 'i11'})]
    assert sync.missing(20) == ('imu', 'gps')


def test_exact_sync_gate_holds_a_complete_set_until_drained():
    out, callback = _recorder()
    ready = {'torques': False}
    sync = ExactTimeSync(('a',), callback, gate=lambda s: ready['torques'])
    assert not sync.add('a', 1, 'x')
    assert not sync.drain()
    ready['torques'] = True
    assert sync.drain()
    assert out == [(1, {'a': 'x'})]


def test_exact_sync_duplicate_input_keeps_the_newer_value():
    out, callback = _recorder()
    sync = ExactTimeSync(('a', 'b'), callback)
    sync.add('a', 1, 'first')
    sync.add('a', 1, 'second')
    sync.add('b', 1, 'b')
    assert out == [(1, {'a': 'second', 'b': 'b'})] and sync.dropped['duplicate'] == 1


def test_exact_sync_rejects_unknown_inputs_and_bad_sizes():
    with pytest.raises(KeyError, match='unknown input'):
        ExactTimeSync(('a',), lambda s, v: None).add('z', 1, 0)
    with pytest.raises(ValueError, match='max_pending'):
        ExactTimeSync(('a',), lambda s, v: None, max_pending=0)


def test_latest_sync_calls_back_on_each_trigger_with_the_latest_values():
    out, callback = _recorder()
    sync = LatestSync(('estimate', 'reference'), callback, triggers=('estimate',),
                      required=('reference',))
    assert not sync.add('estimate', 1, 'e1')     # no reference yet
    sync.add('reference', 1, 'r1')
    sync.add('reference', 2, 'r2')
    assert sync.add('estimate', 3, 'e3')
    assert out == [(3, {'estimate': 'e3', 'reference': 'r2'})]
    assert not sync.add('estimate', 2, 'old')    # older than the latest: ignored
    assert sync.dropped['stale'] == 1 and sync.latest('estimate') == 'e3'


def test_latest_sync_with_two_triggers_fires_once_per_pair_whatever_the_order():
    out, callback = _recorder()
    sync = LatestSync(('imu', 'joints'), callback, triggers=('imu', 'joints'))
    for stamp, order in zip((1, 2, 3), (('imu', 'joints'), ('joints', 'imu'),
                                        ('imu', 'imu', 'joints'))):
        for name in order:
            sync.add(name, stamp, (name, stamp))
    assert [s for s, _ in out] == [1, 2, 3]
    assert out[-1][1] == {'imu': ('imu', 3), 'joints': ('joints', 3)}


def test_tick_grid_matches_the_runner_decimation():
    # Runner: t = k * 0.005, MPC every round(0.1 * 200) = 20 samples, GPS every 20.
    h, every = 0.005, decimation(0.1, 0.005)
    assert every == 20
    for k in range(0, 200):
        stamp = round(k * h * 1e9)
        assert tick_index(stamp, h) == k
        assert is_decimated_tick(stamp, h, every) == (k % 20 == 0)
    # A nanosecond of rounding in a stamp does not move it off its tick.
    assert is_decimated_tick(99_999_999, h, every) and on_grid(100_000_001, 0.1)
    assert not on_grid(5_000_000, 0.1)
    assert decimation(0.001, 0.005) == 1


def test_exact_sync_handles_every_order_of_two_interleaved_stamps():
    # Exhaustive over all 720 orders of 2 stamps x 3 inputs (complements hypothesis).
    items = [(n, s) for s in (1, 2) for n in NAMES]
    for order in itertools.permutations(items):
        out, callback = _recorder()
        sync = ExactTimeSync(NAMES, callback)
        for name, stamp in order:
            sync.add(name, stamp, stamp)
        stamps = [s for s, _ in out]
        assert 2 in stamps and stamps == sorted(stamps)
        assert all(set(v.values()) == {s} for s, v in out)


def test_latest_sync_never_pairs_an_old_encoder_sample_with_a_new_imu_sample():
    """LatestSync never pairs an old encoder sample with a new IMU sample.

    After a stall the queued messages come one stream first: the oldest queued encoder
    sample must wait for its newer ones instead of pairing with the newest IMU sample.
    """
    sets = []
    sync = LatestSync(('joint_states', 'imu'), lambda s, v: sets.append((s, dict(v))),
                      triggers=('joint_states', 'imu'), required=('joint_states', 'imu'),
                      max_skew_ns=5_000_000)
    ms = 1_000_000
    sync.add('joint_states', 0, 'j0')
    sync.add('imu', 0, 'i0')
    assert sets == [(0, {'joint_states': 'j0', 'imu': 'i0'})]
    # A 100 ms stall; then the IMU's queue is taken first, then the encoders'.
    for k in range(80, 101, 5):
        sync.add('imu', k * ms, f'i{k}')
    for k in range(80, 101, 5):
        sync.add('joint_states', k * ms, f'j{k}')
    # Every emitted set has stamps at most one period apart: (95, 100) then (100, 100)
    # are allowed; (80 encoder, 100 IMU) never.
    for stamp, values in sets[1:]:
        j, i = int(values['joint_states'][1:]), int(values['imu'][1:])
        assert abs(j - i) <= 5 and stamp == max(j, i) * ms
    assert sets[1:] == [(100 * ms, {'joint_states': 'j95', 'imu': 'i100'})]
    assert sync.dropped['skewed'] == 3    # j80, j85, j90 waited for a newer sample
    sync.add('imu', 105 * ms, 'i105')     # the streams interleave again
    assert sets[-1] == (105 * ms, {'joint_states': 'j100', 'imu': 'i105'})
    # Without the bound (the old behaviour) the first set after the stall paired the
    # oldest encoder sample with the newest IMU sample.
    old = []
    plain = LatestSync(('joint_states', 'imu'), lambda s, v: old.append(dict(v)),
                       triggers=('joint_states', 'imu'), required=('joint_states', 'imu'))
    plain.add('joint_states', 0, 'j0')
    plain.add('imu', 0, 'i0')
    for k in range(80, 101, 5):
        plain.add('imu', k * ms, f'i{k}')
    plain.add('joint_states', 80 * ms, 'j80')
    assert old[-1] == {'joint_states': 'j80', 'imu': 'i100'}
