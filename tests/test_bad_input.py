"""Generated bad input.

A clear error or a correct result, never a traceback, never a changed original.

Property-based (hypothesis): scenario files (valid, absurd values, broken YAML, duplicate
keys, bytes that are not UTF-8) and bags (valid, truncated, bit-flipped, garbage
metadata.yaml, odd paths). The properties:

- a scenario file loads into a :class:`Scenario` whose every number is within its declared
  range, or raises :class:`ParamError` (a one-line message); nothing else;
- reading a bag gives exactly the messages written, or raises :class:`BagReadError`
  (a damaged bag is never decoded into other values);
- a partial read gives a subsequence of the messages written (nothing invented);
- ``bag_info`` exits 0 only for a bag that reads back exactly, else 1 or 2;
- ``bag_repair`` never changes the original; its new bag holds a subsequence of the
  original messages (all of them when it exits 0);
- no tool prints a traceback.
"""

import contextlib
import dataclasses
import io
import pathlib
import shutil
import tempfile
import typing

from hypothesis import given, HealthCheck, settings, strategies as st
import pytest
import yaml

from wip_runtime.config import ParamError, load_yaml_text
from wip_sim.core.scenario import load_scenario, Scenario, scenario_to_mapping
from wip_tools import simulate

pytestmark = pytest.mark.filterwarnings('ignore::DeprecationWarning')

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow,
                                           HealthCheck.function_scoped_fixture])


def _snapshot(path):
    path = pathlib.Path(path)
    if path.is_file():
        return {'': path.read_bytes()}
    if not path.exists():
        return None
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob('*'))
            if p.is_file()}


def _numbers(scenario):
    """(dotted path, value, field metadata) of every numeric leaf of a scenario."""
    out = []

    def walk(obj, path):
        hints = typing.get_type_hints(type(obj))
        for f in dataclasses.fields(obj):
            value = getattr(obj, f.name)
            if dataclasses.is_dataclass(value):
                walk(value, f'{path}.{f.name}')
            elif isinstance(value, tuple) and value and dataclasses.is_dataclass(value[0]):
                for i, item in enumerate(value):
                    walk(item, f'{path}.{f.name}[{i}]')
            elif hints[f.name] in (int, float) or isinstance(value, tuple):
                for v in (value if isinstance(value, tuple) else (value,)):
                    if isinstance(v, (int, float)) and not isinstance(v, bool):
                        out.append((f'{path}.{f.name}', v, f.metadata))
    walk(scenario, '')
    return out


# ------------------------------------------------------------------- scenario files

_KEYS = {
    'duration': st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                          st.integers(min_value=-10 ** 30, max_value=10 ** 30),
                          st.sampled_from(['1e12', '90', '', 'inf'])),
    'seed': st.one_of(st.integers(min_value=-10 ** 40, max_value=10 ** 40),
                      st.floats(), st.text(max_size=5)),
    'fall_threshold': st.floats(min_value=-2, max_value=3),
    'initial_state': st.fixed_dictionaries({}, optional={
        'theta': st.floats(min_value=-2, max_value=2),
        'v': st.floats(),
        'pose': st.lists(st.floats(min_value=-1e5, max_value=1e5), max_size=4)}),
    'plant': st.fixed_dictionaries({}, optional={
        'model': st.sampled_from(['paper', 'full', 'Paper', 3]),
        'parameters': st.fixed_dictionaries({}, optional={
            'body_mass': st.floats(), 'wheel_radius': st.floats(),
            'gravity': st.floats(min_value=-1e300, max_value=1e300)})}),
    'eso': st.fixed_dictionaries({}, optional={
        'epsilon': st.floats(min_value=0, max_value=1e6),
        'yaw_gains': st.lists(st.floats(), max_size=4)}),
    'mpc': st.fixed_dictionaries({}, optional={
        'prediction_horizon': st.integers(min_value=-5, max_value=10 ** 6),
        'control_horizon': st.integers(min_value=-5, max_value=100),
        'max_tilt': st.floats()}),
    'reference': st.fixed_dictionaries({}, optional={
        'kind': st.sampled_from(['line', 'circle', 'waypoints', 'spiral']),
        'line_speed': st.floats(min_value=-1, max_value=1e4),
        'waypoints_x': st.lists(st.floats(min_value=-1e5, max_value=1e5), max_size=6)}),
    'disturbances': st.fixed_dictionaries({}, optional={
        'longitudinal': st.lists(st.fixed_dictionaries({
            'kind': st.sampled_from(['pulse', 'sine', 'noise', 'step', 'other']),
            'amplitude': st.floats(), 'width': st.floats(min_value=-1, max_value=10)}),
            max_size=3)}),
    'sensors': st.fixed_dictionaries({}, optional={
        'gps_noise_std': st.floats(), 'encoder_counts_per_rev': st.integers()}),
    'rates': st.fixed_dictionaries({}, optional={
        'control_rate': st.sampled_from([100.0, 200.0, 7.0, 0.0, 1e9]),
        'plant_rate': st.sampled_from([1000.0, 333.0, 1e12])}),
}

scenario_mappings = st.fixed_dictionaries({}, optional=_KEYS)


def _yaml_text(mapping):
    return yaml.safe_dump(mapping, sort_keys=False, allow_unicode=True)


scenario_texts = st.one_of(
    scenario_mappings.map(lambda m: _yaml_text(m).encode('utf-8')),
    # Damaged files: a valid file with bytes replaced, cut, or doubled keys.
    st.tuples(scenario_mappings, st.binary(min_size=1, max_size=4),
              st.integers(min_value=0, max_value=400)).map(
        lambda t: (lambda b: b[:t[2]] + t[1] + b[t[2]:])(_yaml_text(t[0]).encode())),
    scenario_mappings.map(lambda m: (_yaml_text(m) * 2).encode('utf-8')),
    st.binary(max_size=200),
    st.sampled_from([b'\xff\xfe\x00d', b'- 1\n- 2\n', b'duration: [', b'{a: 1, a: 2}',
                     b'seed: ' + b'9' * 5000, b'duration: 1e12\n', b'&a [*a]',
                     b'duration: .nan\n', b'mpc: {prediction_horizon: 100000}\n']),
)


@SETTINGS
@given(scenario_texts)
def test_a_scenario_file_loads_within_its_ranges_or_is_refused_in_one_line(tmp_path, text):
    path = tmp_path / 'scenario.yaml'
    path.write_bytes(text)
    try:
        scenario = load_scenario(path)
    except ParamError as err:
        message = str(err)
        assert message and '\n' not in message.strip() or 'YAML' in message
        assert 'Traceback' not in message
    else:
        assert isinstance(scenario, Scenario)
        for name, value, meta in _numbers(scenario):
            lo, hi = meta.get('minimum'), meta.get('maximum')
            assert lo is None or value >= lo, name
            assert hi is None or value <= hi, name
        assert 0 < scenario.duration <= 36000 and 0 <= scenario.seed < 2 ** 63
        assert abs(scenario.initial_state.theta) < scenario.fall_threshold
        # What was loaded is what --dump-scenario writes, and it loads back the same.
        again = tmp_path / 'again.yaml'
        again.write_text(yaml.safe_dump(scenario_to_mapping(scenario)))
        assert load_scenario(again) == scenario
    assert path.read_bytes() == text  # never changed


@SETTINGS
@given(scenario_texts)
def test_simulate_dump_scenario_answers_0_or_2_without_a_traceback(tmp_path, text):
    path = tmp_path / 'scenario.yaml'
    path.write_bytes(text)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = simulate.main(['--scenario', str(path), '--dump-scenario'])
    assert code in (0, 2)
    if code == 2:
        assert err.getvalue().startswith('ERROR: ') and 'Traceback' not in err.getvalue()
        assert len(err.getvalue().strip().splitlines()) <= 3
    assert path.read_bytes() == text


@given(st.text(max_size=40), st.integers(min_value=1, max_value=3))
@SETTINGS
def test_duplicate_keys_are_refused_at_any_depth(key, depth):
    key = 'k' + ''.join(c for c in key if c.isalnum())
    inner = f'{key}: 1\n{key}: 2\n'
    text = ''.join(f'{"  " * i}s{i}:\n' for i in range(depth - 1)) + ''.join(
        '  ' * (depth - 1) + line + '\n' for line in inner.splitlines())
    with pytest.raises(ParamError, match='duplicate key'):
        load_yaml_text(text, 'test')


@given(st.floats(allow_nan=False, allow_infinity=False, width=64))
@SETTINGS
def test_exponent_notation_is_a_number(value):
    text = f'{value:e}'  # 1.234560e+12 and also '1e12' forms below
    assert load_yaml_text(f'x: {text}', 'test')['x'] == float(text)
    mantissa, exponent = f'{value:.0e}'.split('e')
    short = f'{mantissa}e{int(exponent)}'  # e.g. 1e12, -3e-7: no dot
    assert load_yaml_text(f'x: {short}', 'test')['x'] == float(short)


# ----------------------------------------------------------------------------- bags

bag_reader = pytest.importorskip('wip_bag.bag_reader')
from wip_bag.bag_info import main as bag_info_main  # noqa: E402
from wip_bag.bag_reader import BagReadError, iter_raw_messages  # noqa: E402
from wip_bag.bag_repair import main as bag_repair_main  # noqa: E402
from wip_bag.bag_writer import Rosbag2McapWriter  # noqa: E402

START_NS = 1_700_000_000_000_000_000


def _cdr_string(text):
    # std_msgs/String in CDR (little endian): encapsulation, length with NUL, bytes, NUL.
    data = text.encode('utf-8') + b'\x00'
    return b'\x00\x01\x00\x00' + len(data).to_bytes(4, 'little') + data


@pytest.fixture(scope='module')
def pristine(tmp_path_factory):
    """Return a finished bag of 2 topics, 600 messages in about 20 zstd chunks, and its content."""
    directory = tmp_path_factory.mktemp('pristine') / 'bag'
    with Rosbag2McapWriter(directory, chunk_size=2048,
                           custom_data={'wip.note': 'pristine'}) as bag:
        bag.add_topic('/a', 'std_msgs/msg/String')
        bag.add_topic('/b', 'std_msgs/msg/String')
        for k in range(600):
            bag.write('/a' if k % 3 else '/b', _cdr_string(f'{k}:' + 'xyzw' * (k % 17)),
                      START_NS + k * 1_000_000)
    messages = _Messages((m.topic, m.log_time_ns, m.data) for m in iter_raw_messages(directory))
    assert len(messages) == 600
    return directory, messages


class _Messages(list):
    def __repr__(self):  # hypothesis prints the arguments of a failing example
        return f'<{len(self)} messages>'


def _copy(directory, tmp):
    target = pathlib.Path(tmp) / 'bag'
    shutil.copytree(directory, target)
    return target


def _mcap(bag):
    return next(bag.glob('*.mcap'))


def _is_subsequence(part, whole):
    it = iter(whole)
    return all(any(item == other for other in it) for item in part)


def _quiet(function, *args):
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = function(*args)
    return code, out.getvalue(), err.getvalue()


damage = st.one_of(
    st.tuples(st.just('flip'), st.lists(st.tuples(st.floats(0, 1), st.integers(0, 7)),
                                        min_size=1, max_size=3)),
    st.tuples(st.just('cut'), st.floats(0, 1)),
    st.tuples(st.just('garbage'), st.binary(min_size=1, max_size=16), st.floats(0, 1)),
)


def _damage(path, how):
    data = bytearray(path.read_bytes())
    if how[0] == 'flip':
        for where, bit in how[1]:
            data[min(int(where * len(data)), len(data) - 1)] ^= 1 << bit
    elif how[0] == 'cut':
        data = data[:int(how[1] * len(data))]
    else:
        at = int(how[2] * len(data))
        data[at:at + len(how[1])] = how[1]
    path.write_bytes(bytes(data))


@SETTINGS
@given(damage)
def test_a_damaged_bag_reads_back_exactly_or_is_refused_and_repair_keeps_the_original(
        pristine, how):
    directory, messages = pristine
    with tempfile.TemporaryDirectory() as tmp:
        bag = _copy(directory, tmp)
        _damage(_mcap(bag), how)
        before = _snapshot(bag)
        try:
            got = [(m.topic, m.log_time_ns, m.data) for m in iter_raw_messages(bag)]
        except BagReadError as err:
            assert 'Traceback' not in str(err)
            exact = False
        else:
            assert got == messages  # never a silently different content
            exact = True
        partial = [(m.topic, m.log_time_ns, m.data)
                   for m in iter_raw_messages(bag, allow_partial=True)]
        assert _is_subsequence(partial, messages)
        code, out, err = _quiet(bag_info_main, [str(bag)])
        assert code in (0, 1) and 'Traceback' not in out + err
        if code == 0:
            assert exact
        repaired = pathlib.Path(tmp) / 'repaired'
        code, out, err = _quiet(bag_repair_main, [str(bag), '--out', str(repaired)])
        assert code in (0, 1, 2) and 'Traceback' not in out + err
        assert repaired.exists() == (code in (0, 1) and 'nothing to recover' not in err)
        if repaired.exists():
            recovered = [(m.topic, m.log_time_ns, m.data)
                         for m in iter_raw_messages(repaired)]
            assert _is_subsequence(recovered, messages)
            assert recovered == partial  # every intact chunk, whatever came before
            if code == 0:
                assert recovered == messages
        assert _snapshot(bag) == before  # the original is never touched


metadata_texts = st.one_of(
    st.binary(max_size=64),
    st.sampled_from([b'- a\n- b\n', b'rosbag2_bagfile_information: [', b'\xff\xfe',
                     b'rosbag2_bagfile_information: 3\n', b'{}',
                     b'rosbag2_bagfile_information:\n  relative_file_paths: ../../etc\n',
                     b'rosbag2_bagfile_information:\n  relative_file_paths: [x.mcap]\n',
                     b'rosbag2_bagfile_information:\n  message_count: many\n'
                     b'  custom_data: {a: b}\n  ros_distro: jazzy\n']),
    st.recursive(st.none() | st.booleans() | st.integers() | st.text(max_size=8),
                 lambda c: st.lists(c, max_size=3) | st.dictionaries(
                     st.text(max_size=6), c, max_size=3), max_leaves=8).map(
        lambda v: yaml.safe_dump({'rosbag2_bagfile_information': v}).encode()),
)


@settings(SETTINGS, max_examples=40)
@given(metadata_texts)
def test_garbage_metadata_is_reported_and_repair_rebuilds_it(pristine, text):
    directory, messages = pristine
    with tempfile.TemporaryDirectory() as tmp:
        bag = _copy(directory, tmp)
        (bag / 'metadata.yaml').write_bytes(text)
        before = _snapshot(bag)
        try:
            got = [(m.topic, m.log_time_ns, m.data) for m in iter_raw_messages(bag)]
        except BagReadError as err:
            assert 'metadata.yaml' in str(err) or 'bag' in str(err)
        else:
            assert got == messages
        code, out, err = _quiet(bag_info_main, [str(bag)])
        assert code in (0, 1) and 'Traceback' not in out + err
        repaired = pathlib.Path(tmp) / 'repaired'
        code, out, err = _quiet(bag_repair_main, [str(bag), '--out', str(repaired)])
        assert code == 0, err  # the messages are all intact: only metadata.yaml is rebuilt
        assert [(m.topic, m.log_time_ns, m.data)
                for m in iter_raw_messages(repaired)] == messages
        assert _quiet(bag_info_main, [str(repaired)])[0] == 0
        assert _snapshot(bag) == before


odd_paths = st.sampled_from(['missing', 'file.txt', 'empty_dir', 'dir with space',
                             'unicodé', 'not_mcap', 'metadata_dir', 'dangling'])


@settings(SETTINGS, max_examples=20)
@given(odd_paths)
def test_odd_paths_are_usage_errors(tmp_path, kind):
    base = tmp_path / kind
    target = base
    if kind == 'file.txt':
        base.write_text('not a bag')
    elif kind in ('empty_dir', 'dir with space', 'unicodé'):
        base.mkdir(exist_ok=True)
    elif kind == 'not_mcap':
        base.mkdir(exist_ok=True)
        (base / 'x.mcap').write_bytes(b'hello')
    elif kind == 'metadata_dir':
        base.mkdir(exist_ok=True)
        (base / 'metadata.yaml').mkdir(exist_ok=True)
    elif kind == 'dangling' and not base.is_symlink():
        base.symlink_to(tmp_path / 'nowhere')
    code, out, err = _quiet(bag_info_main, [str(target)])
    assert code in (1, 2) and 'Traceback' not in out + err
    code, out, err = _quiet(bag_repair_main, [str(target), '--out',
                                              str(tmp_path / f'{kind}_out')])
    assert code in (1, 2) and 'Traceback' not in out + err
    with pytest.raises(BagReadError):
        list(iter_raw_messages(target))


# ------------------------------------------------- every declared parameter has a range

def _config_classes():
    """Every config dataclass of the core (fields made with param()), found by import."""
    import importlib
    import pkgutil
    import wip_control.core as core
    found = {}
    for info in pkgutil.iter_modules(core.__path__):
        module = importlib.import_module(f'wip_control.core.{info.name}')
        for value in vars(module).values():
            if isinstance(value, type) and dataclasses.is_dataclass(value) and any(
                    'unit' in f.metadata for f in dataclasses.fields(value)):
                found[f'{value.__module__}.{value.__qualname__}'] = value
    return found


def test_every_numeric_parameter_has_both_bounds_and_a_default_within_them():
    classes = _config_classes()
    assert len(classes) >= 10  # the sections of a scenario, at least
    checked = 0
    for name, cls in classes.items():
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if 'unit' not in f.metadata or f.default is dataclasses.MISSING:
                continue
            values = f.default if isinstance(f.default, tuple) else (f.default,)
            numbers = [v for v in values if isinstance(v, (int, float))
                       and not isinstance(v, bool)]
            if not numbers and hints[f.name] not in (int, float):
                continue
            lo, hi = f.metadata['minimum'], f.metadata['maximum']
            assert lo is not None and hi is not None, f'{name}.{f.name} has no range'
            for v in numbers:
                assert lo <= v <= hi, f'{name}.{f.name}: default {v} outside [{lo}, {hi}]'
                floor = f.metadata.get('floor')
                assert floor is None or v >= floor, f'{name}.{f.name}: default below floor'
            checked += 1
    assert checked >= 80
