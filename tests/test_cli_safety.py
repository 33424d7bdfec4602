"""Every reproduction of a data-safety bug, each with its new behaviour.

No data lost, no silent wrong result, no traceback, one exit-code table.

Exit codes (every tool): 0 ok, 1 the vehicle fell or a check failed, 2 usage or input
error (nothing written), 3 internal error (one line, the trace in a file).
"""

import json
import os
import pathlib
import signal
import subprocess
import sys
import time

import pytest
import yaml

from wip_runtime.config import ParamError
from wip_sim.core.scenario import load_scenario
from wip_runtime import cli
from wip_tools import simulate

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]


def _snapshot(path):
    path = pathlib.Path(path)
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob('*'))
            if p.is_file()}


def _scenario(tmp_path, text, name='s.yaml'):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode('utf-8'))
    return path


# ---------------------------------------------------------------- the exit-code table

def test_an_internal_error_is_one_line_exit_3_and_the_trace_is_in_a_file(
        tmp_path, monkeypatch, capsys):
    monkeypatch.setenv(cli.TRACE_DIR_ENV, str(tmp_path / 'traces'))

    def broken(argv):
        return {}['no such key']

    assert cli.run_main(broken, 'tool', []) == cli.EXIT_INTERNAL == 3
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and 'Traceback' not in err
    assert err.startswith("tool: internal error: KeyError: 'no such key' (full trace in ")
    (trace,) = (tmp_path / 'traces').iterdir()
    assert str(trace) in err and 'Traceback' in trace.read_text()
    assert cli.run_main(lambda argv: 1, 'tool') == 1  # a tool's own code passes through
    assert cli.run_main(lambda argv: sys.exit(2), 'tool') == 2  # argparse's usage errors


# ------------------------------------------------------------ scenario values and files

@pytest.mark.parametrize('text, message', [
    (b'name: \xff\xfe\n', 'not a UTF-8 text file'),
    ('seed: ' + '9' * 5000 + '\n', 'more than 4300 digits'),
    ('seed: 18446744073709551616\n', 'seed: must be in [0, 2**63 - 1]'),
    ('initial_state: {theta: 0.6}\n', 'beyond fall_threshold'),
    ('plant: {parameters: {body_mass: 1e300}}\n', 'plant.parameters.body_mass: must be <='),
    ('eso: {epsilon: 1e-300}\n', 'eso.epsilon: must be >='),
    ('sensors: {gps_noise_std: 1e300}\n', 'sensors.gps_noise_std: must be <='),
    ('disturbances: {longitudinal: [{kind: pulse, amplitude: 1e308, width: 0.1}]}\n',
     'disturbances.longitudinal[0].amplitude: must be <='),
    ('mpc: {prediction_horizon: 100000}\n', 'mpc.prediction_horizon: must be <= 60'),
    ('mpc: {prediction_horizon: 150}\n', 'mpc.prediction_horizon: must be <= 60'),
    ('reference: {kind: line, line_speed: 0}\n', 'reference.line_speed: must be > 0'),
    ('duration: 36000\n', 'more than the 1e+06 one run may have'),
    ('duration: 1e12\n', 'duration: must be in (0, 36000] s'),  # a number, out of range
    ('duration: 10\nduration: 20\n', "duplicate key 'duration' on line 2"),
    ('reference: {waypoints_x: [' + ', '.join(['1.0'] * 10001) + ']}\n', 'at most 10000'),
])
def test_a_bad_scenario_is_refused_before_anything_runs_in_one_line(tmp_path, monkeypatch,
                                                                    capsys, text, message):
    path = _scenario(tmp_path, text)
    with pytest.raises(ParamError, match='.*' + message.replace('[', r'\[').replace(
            '(', r'\(').replace('*', r'\*').replace('+', r'\+')):
        load_scenario(path)
    monkeypatch.setattr(simulate, 'run_scenario', lambda *a, **k: pytest.fail('ran'))
    out = tmp_path / 'out'
    assert simulate.main(['--scenario', str(path), '--out', str(out), '--quiet']) == 2
    assert simulate.main(['--scenario', str(path), '--dump-scenario']) == 2
    err = capsys.readouterr().err
    assert message in err and 'Traceback' not in err
    assert len(err.strip().splitlines()) == 2  # one line per call
    assert not out.exists()


def test_exponent_notation_and_short_runs(tmp_path):
    assert load_scenario(_scenario(tmp_path, 'duration: 1e2\n')).duration == 100.0
    # Less than half a control period is no control tick at all: refused in one line.
    for text in ('duration: 0.001\n', 'duration: 1e-9\n'):
        with pytest.raises(ParamError, match='the run would have no control tick'):
            load_scenario(_scenario(tmp_path, text))
    # One control period, or a fall on the first tick: metrics, no IndexError.
    for text in ('duration: 0.005\n', 'initial_state: {theta: 0.49, theta_dot: 10}\n'
                 'duration: 1\n'):
        out = tmp_path / f'out{len(text)}'
        code = simulate.main(['--scenario', str(_scenario(tmp_path, text)), '--out',
                              str(out), '--quiet', '--no-figures'])
        metrics = json.loads((out / 'metrics.json').read_text())
        assert code == (1 if metrics['fell'] else 0)
        assert metrics['duration_s'] <= 1.0 + 1e-9


def test_simulate_checks_out_before_the_run(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(simulate, 'run_scenario', lambda *a, **k: pytest.fail('ran'))
    a_file = tmp_path / 'a_file'
    a_file.write_text('mine')
    for out in (a_file, a_file / 'sub'):
        assert simulate.main(['--out', str(out), '--quiet']) == 2
        assert 'is a file, not a directory' in capsys.readouterr().err
    assert a_file.read_text() == 'mine'
    # An unwritable directory (as root every directory is writable: simulated).
    monkeypatch.setattr(cli.os, 'access', lambda path, mode: False)
    assert simulate.main(['--out', str(tmp_path / 'locked' / 'out'), '--quiet']) == 2
    assert 'is not writable' in capsys.readouterr().err
    assert not (tmp_path / 'locked').exists()


# ----------------------------------------------------------------- run_graph outputs

graph = pytest.importorskip('wip_bringup.graph')


def test_run_graph_never_deletes_logs_it_did_not_write(tmp_path, capsys):
    out = tmp_path / 'u'
    (out / 'logs').mkdir(parents=True)
    (out / 'logs' / 'thesis.tex').write_text('years of work')
    (out / 'logs_attempt_1').mkdir()
    (out / 'logs_attempt_1' / 'notes.txt').write_text('mine too')
    before = _snapshot(out)
    assert graph.main(['--duration', '0.5', '--out', str(out), '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'run_graph did not write' in err and 'Traceback' not in err
    assert _snapshot(out) == before  # nothing deleted, nothing added (no run.json)


def test_run_graph_record_into_an_existing_bag_touches_nothing(tmp_path, capsys):
    bag = tmp_path / 'demo_bag'
    bag.mkdir()
    (bag / 'scenario.yaml').write_text('duration: 90.0\n')
    (bag / 'demo_bag_0.mcap').write_bytes(b'recorded data')
    before = _snapshot(bag)
    for out in (tmp_path / 'fresh', tmp_path / 'fresh2'):
        assert graph.main(['--duration', '0.5', '--record', str(bag), '--out', str(out),
                           '--quiet']) == 2
        err = capsys.readouterr().err
        assert 'refusing to overwrite a bag' in err and 'Traceback' not in err
        assert not out.exists()
    assert _snapshot(bag) == before


def test_run_graph_refuses_an_out_that_is_a_file_and_a_non_utf8_scenario(tmp_path, capsys):
    a_file = tmp_path / 'a_file'
    a_file.write_text('mine')
    assert graph.main(['--out', str(a_file), '--quiet']) == 2
    scenario = _scenario(tmp_path, b'name: \xff\n')
    assert graph.main(['--scenario', str(scenario), '--out', str(tmp_path / 'o'),
                       '--quiet']) == 2
    err = capsys.readouterr().err
    assert 'is a file' in err and 'not a UTF-8 text file' in err and 'Traceback' not in err
    assert a_file.read_text() == 'mine' and not (tmp_path / 'o').exists()


def test_a_dead_recorder_points_to_scripts_bag_repair(tmp_path):
    from wip_bringup.graph_runner import GraphRunner
    runner = GraphRunner(graph.GraphOptions(out=str(tmp_path / 'o'), record=str(tmp_path / 'bag'),
                                            quiet=True))
    said = []
    runner.say = said.append

    class DeadRecorder:
        name, pid, killed, log_path = 'recorder', 1, False, tmp_path / 'recorder.log'

        def stop(self, grace):
            return 1

    runner.processes = {'recorder': DeadRecorder()}
    runner.stop_all()
    assert any(f'scripts/bag_repair {tmp_path / "bag"}' in line for line in said), said
    assert not any('recover_bag' in line for line in said)


# --------------------------------------------------------------------------------- bags

pytest.importorskip('wip_msgs.msg', reason='wip_msgs not built (scripts/setup builds it)')
from wip_sim.core.runner import run_scenario  # noqa: E402
from wip_sim.core.scenario import scenario_from_mapping  # noqa: E402
from wip_bag import bag_info, bag_repair  # noqa: E402
from record_bag import write_record_as_bag  # noqa: E402
from wip_tools import report, rerun  # noqa: E402
from wip_bag.bag_integrity import scan_file  # noqa: E402
from wip_bag.bag_reader import BagIntegrityError, iter_raw_messages, read_bag  # noqa: E402
from wip_bringup.private_domain import take_private_domain  # noqa: E402


@pytest.fixture(scope='module')
def run_bag(tmp_path_factory):
    """Return a 4 s in-process run written as the graph records it (small chunks: many)."""
    scenario = scenario_from_mapping({'duration': 4.0})
    result = run_scenario(scenario)
    directory = tmp_path_factory.mktemp('run') / 'bag'
    write_record_as_bag(result, scenario, directory, chunk_size=32 * 1024)
    return directory


def _copy(bag, tmp_path, name='bag'):
    import shutil
    target = tmp_path / name
    shutil.copytree(bag, target)
    return target


def _flip_in_chunk(bag, index):
    """Flip one bit in the middle of the data of the index-th chunk; its time range."""
    path = next(bag.glob('*.mcap'))
    chunk = scan_file(path).chunks[index]
    data = bytearray(path.read_bytes())
    data[chunk.offset + 200] ^= 0x10
    path.write_bytes(bytes(data))
    return chunk


def _chunk_messages(bag, index):
    """Return the messages of the index-th chunk of an intact bag (as (topic, log time, data))."""
    from mcap.records import Message
    from wip_bag.bag_integrity import iter_chunk_records
    path = next(bag.glob('*.mcap'))
    file_scan = scan_file(path)
    _, records = list(iter_chunk_records(path, file_scan))[index]
    return [(file_scan.channels[r.channel_id].topic, r.log_time, r.data) for r in records
            if isinstance(r, Message)]


def _without(whole, lost):
    """``whole`` less the messages of ``lost`` (each removed once, in order)."""
    remaining = list(lost)
    out = []
    for message in whole:
        if remaining and message in remaining:
            remaining.remove(message)
            continue
        out.append(message)
    assert not remaining
    return out


def _messages(bag, **options):
    return [(m.topic, m.log_time_ns, m.data) for m in iter_raw_messages(bag, **options)]


def test_one_flipped_bit_is_an_error_with_its_time_range_and_topics(run_bag, tmp_path,
                                                                    capsys):
    bag = _copy(run_bag, tmp_path)
    chunks = scan_file(next(bag.glob('*.mcap'))).chunks
    assert len(chunks) >= 6
    chunk = _flip_in_chunk(bag, 2)
    with pytest.raises(BagIntegrityError, match='chunk CRC mismatch') as caught:
        list(read_bag(bag))
    message = str(caught.value)
    assert 'between t = ' in message and '/wip/ground_truth' in message
    out = tmp_path / 'report'
    assert report.main([str(bag), '--out', str(out), '--no-figures', '--quiet']) == 2
    assert not out.exists()
    assert bag_info.main([str(bag)]) == 1  # the verdict is the exit code
    assert 'NOT OK' in capsys.readouterr().out
    # On request, the intact part, marked partial; every reported value is finite.
    assert report.main([str(bag), '--out', str(out), '--no-figures', '--quiet',
                        '--partial']) == 0
    metrics = json.loads((out / 'metrics.json').read_text())
    assert metrics['partial'] is True and 'chunk CRC mismatch' in metrics['lost'][0]
    assert metrics['max_abs_v_mps'] < 10.0
    partial = _messages(bag, allow_partial=True)
    lost = _chunk_messages(run_bag, 2)
    assert lost and sorted(partial) == sorted(_without(_messages(run_bag), lost))
    assert all(chunk.start_ns <= m[1] <= chunk.end_ns for m in lost)


def test_a_truncated_bag_is_refused_by_every_reader(run_bag, tmp_path, capsys):
    bag = _copy(run_bag, tmp_path)
    path = next(bag.glob('*.mcap'))
    path.write_bytes(path.read_bytes()[:path.stat().st_size // 2])
    assert bag_info.main([str(bag)]) == 1
    assert report.main([str(bag), '--out', str(tmp_path / 'r'), '--quiet',
                        '--no-figures']) == 2
    assert rerun.main([str(bag), '--out', str(tmp_path / 'rr'), '--quiet',
                       '--no-figures']) == 2
    err = capsys.readouterr().err
    assert err.count('unfinished file') >= 2 and 'Traceback' not in err
    assert not (tmp_path / 'r').exists() and not (tmp_path / 'rr' / 'bag').exists()
    replay = subprocess.run([sys.executable, '-m', 'wip_bag.replayer_node', str(bag)],
                            capture_output=True, text=True, timeout=60)
    assert replay.returncode == 2, replay.stderr
    assert 'unfinished file' in replay.stderr and 'Traceback' not in replay.stderr


def test_repair_recovers_every_intact_chunk_after_a_damaged_one(run_bag, tmp_path, capsys):
    bag = _copy(run_bag, tmp_path)
    _flip_in_chunk(bag, 1)
    before = _snapshot(bag)
    assert bag_repair.main([str(bag), '--dry-run']) == 1
    out = capsys.readouterr().out
    assert 'would rewrite' in out and 'rewritten' not in out
    assert not (tmp_path / 'bag_repaired').exists()
    assert bag_repair.main([str(bag)]) == 1  # written, but a chunk was lost: says so
    repaired = tmp_path / 'bag_repaired'
    whole = _messages(run_bag)
    expected = _without(whole, _chunk_messages(run_bag, 1))
    assert sorted(_messages(repaired)) == sorted(expected)
    assert [m[1] for m in _messages(repaired)] == sorted(m[1] for m in expected)
    assert len(expected) > 0.8 * len(whole)  # the chunks after the damaged one, too
    assert bag_info.main([str(repaired)]) == 0
    assert _snapshot(bag) == before  # never touches the original
    assert bag_repair.main([str(bag)]) == 2  # the output exists: refused, not overwritten
    assert 'exists' in capsys.readouterr().err


@pytest.mark.parametrize('metadata', [
    b'- a list\n- not a mapping\n',
    b'rosbag2_bagfile_information: {version: 9, [broken\n',
    'rosbag2_bagfile_information:\n  custom_data: {owner: "lab"}\n  ros_distro: jazzy\n'
    '  description: "caf\xe9"\n'.encode('latin-1'),  # not UTF-8
])
def test_a_broken_metadata_yaml_is_reported_and_rebuilt(run_bag, tmp_path, capsys, metadata):
    bag = _copy(run_bag, tmp_path)
    (bag / 'metadata.yaml').write_bytes(metadata)
    assert bag_info.main([str(bag)]) == 1
    assert 'NOT OK' in capsys.readouterr().out
    assert report.main([str(bag), '--out', str(tmp_path / 'r'), '--quiet',
                        '--no-figures']) == 2
    assert rerun.main([str(bag), '--out', str(tmp_path / 'rr'), '--quiet',
                       '--no-figures']) == 2
    err = capsys.readouterr().err
    assert 'metadata.yaml' in err and 'Traceback' not in err
    assert bag_repair.main([str(bag), '--out', str(tmp_path / 'fixed')]) == 0
    info = yaml.safe_load((tmp_path / 'fixed' / 'metadata.yaml').read_text())[
        'rosbag2_bagfile_information']
    assert info['message_count'] == len(_messages(run_bag))
    if b'owner' in metadata:
        assert info['custom_data'] == {'owner': 'lab'}
    assert (bag / 'metadata.yaml').read_bytes() == metadata


# -------------------------------------------------------------------------------- nodes

def test_mixer_refuses_inf_warns_about_unknown_overrides_and_stops_quietly(tmp_path):
    env = dict(os.environ, ROS_DOMAIN_ID=str(take_private_domain()),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    module = [sys.executable, '-m', 'wip_control.nodes.torque_mixer_node', '--ros-args']
    bad = subprocess.run(module + ['-p', 'mpc.sampling_period:=inf'], capture_output=True,
                         text=True, timeout=60, env=env)
    assert bad.returncode == 2     # the table's usage or input error
    assert bad.stderr.strip() == \
        'torque_mixer: error: mpc.sampling_period: must be finite, got inf'
    log = tmp_path / 'mixer.log'
    with open(log, 'w') as stream:
        mixer = subprocess.Popen(module + ['-p', 'max_wheel_torque:=3.0',
                                           '-p', 'mpc_period:=0.1'], stdout=stream,
                                 stderr=subprocess.STDOUT, env=env)
        deadline = time.monotonic() + 30
        while 'safety state' not in log.read_text() and time.monotonic() < deadline:
            time.sleep(0.1)
        mixer.send_signal(signal.SIGINT)
        assert mixer.wait(timeout=30) == 0
    text = log.read_text()
    assert "parameter 'max_wheel_torque' is not a parameter of this node" in text
    assert "did you mean 'mixer.max_wheel_torque'" in text
    # A parameter of an older version names what replaced it.
    assert ("parameter 'mpc_period' is not a parameter of this node and is ignored (the "
            "mixer reads the MPC's period from 'mpc.sampling_period')") in text
    assert 'stopping: zero effort command sent' in text
    assert 'FATAL' not in text and 'Traceback' not in text and 'Error occurred' not in text


def test_a_command_line_splits_at_the_first_ros_args():
    from wip_runtime.cli import split_ros_args
    assert split_ros_args(['--with-viewer', '--ros-args', '-p', 'a:=1', '--ros-args']) == (
        ['--with-viewer'], ['--ros-args', '-p', 'a:=1', '--ros-args'])
    assert split_ros_args(('--help',)) == (['--help'], [])
    assert split_ros_args([]) == ([], [])
