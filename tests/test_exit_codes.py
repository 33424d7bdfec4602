"""One exit-code table.

The constants of wip_runtime.cli, its docstring, the README's table and every tool's
``--help`` say the same. Every script of scripts/ and every node executable answers ``--help``
(exit 0, usage, nothing started or written), and a typo in an option is exit 2 in one line before
anything is written.
"""

import os
import pathlib
import re
import subprocess

import pytest

from processes import run_at_once
from wip_runtime import cli

REPO_ROOT = pathlib.Path(__file__).resolve().parent.parent
SCRIPTS = REPO_ROOT / 'scripts'
#: scripts/ files that are not commands.
NOT_COMMANDS = {'_env.sh'}
#: Commands that are not a tool with the table (set-up, the demo, the test runner, and
#: ros2_run, whose exit status is the executable's own).
NOT_TOOLS = {'setup', 'demo', 'test', 'ros2_run'}
HELP_TIMEOUT = 300.0  # [s] every --help at once on a slow, shared 2-core machine
#: [s] for every node refusing its arguments at once (a node that accepts them runs on).
REFUSE_TIMEOUT = 120.0


def table_codes(rows):
    """{code: meaning} of '| code | meaning |' rows ('129 / 143' is two codes)."""
    codes = {}
    for first, meaning in rows:
        for code in first.split('/'):
            codes[int(code)] = meaning.strip()
    return codes


def readme_table():
    text = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    section = text.split('## Exit codes', 1)[1].split('\n## ', 1)[0]
    return table_codes(re.findall(r'^\| ([0-9][0-9 /]*) \| (.*) \|$', section, re.M))


def epilog_table(output):
    """{code: meaning} of the exit-code epilog of a --help output."""
    assert cli.EXIT_CODES_HEADING in output, output
    table = output.split(cli.EXIT_CODES_HEADING, 1)[1]
    codes = {}
    for line in table.splitlines():
        match = re.match(r'^\s+(\d+)  (.*)$', line)
        if match:
            codes[int(match.group(1))] = match.group(2).strip()
        elif line.strip():
            break
    return codes


def test_the_constants_the_docstring_and_the_readme_agree():
    constants = {cli.EXIT_OK, cli.EXIT_FAILED, cli.EXIT_USAGE, cli.EXIT_INTERNAL,
                 cli.EXIT_DISK_FULL, cli.EXIT_NOT_ENGAGED, cli.EXIT_HANGUP,
                 cli.EXIT_INTERRUPTED, cli.EXIT_TERMINATED}
    assert set(cli.EXIT_CODES) == constants == {0, 1, 2, 3, 4, 5, 129, 130, 143}
    doc = set(int(c) for c in re.findall(r'^(\d+)\s{2,}', cli.__doc__, re.M))
    assert doc == constants
    assert set(readme_table()) == constants


def test_the_runners_use_the_table():
    from wip_bringup import launcher, run_stop
    from wip_bringup.hardware_outcome import hardware_outcome
    assert (launcher.EXIT_OK, launcher.EXIT_FELL, launcher.EXIT_USAGE, launcher.EXIT_FAILED,
            launcher.EXIT_DISK_FULL, launcher.EXIT_NOT_ENGAGED, launcher.EXIT_INTERRUPTED) == (
        cli.EXIT_OK, cli.EXIT_FAILED, cli.EXIT_USAGE, cli.EXIT_INTERNAL, cli.EXIT_DISK_FULL,
        cli.EXIT_NOT_ENGAGED, cli.EXIT_INTERRUPTED)
    assert set(run_stop.STOP_EXIT_CODES) == {cli.EXIT_INTERRUPTED, cli.EXIT_TERMINATED,
                                             cli.EXIT_HANGUP}
    # Hardware mode: 0 engaged and no fault (also at the user's stop), 1 a fault while
    # engaged, 5 never engaged; the README says the same.
    engaged = [{'t': 0.0, 'state': 'STARTING', 'reasons': ''},
               {'t': 1.0, 'state': 'ACTIVE', 'reasons': ''}]
    fault = engaged + [{'t': 2.0, 'state': 'FAULT', 'reasons': 'fallen'}]
    assert hardware_outcome(engaged, 'stopped by SIGINT')[0] == cli.EXIT_OK
    assert hardware_outcome(fault, 'stopped by SIGINT')[0] == cli.EXIT_FAILED
    assert hardware_outcome(engaged[:1], 'end')[0] == cli.EXIT_NOT_ENGAGED
    readme = ' '.join((REPO_ROOT / 'README.md').read_text(encoding='utf-8').split())
    assert ('Exit: 0 engaged and no fault, 1 a fall or safety fault while engaged (with the '
            'cause), 5 never engaged') in readme
    assert 'hardware mode: a fall or a safety FAULT after the controllers engaged' in readme


def commands():
    return sorted(p.name for p in SCRIPTS.iterdir()
                  if p.is_file() and os.access(p, os.X_OK) and p.name not in NOT_COMMANDS)


def node_executables():
    """(package, executable, path) of every node that ``ros2 run`` starts.

    Not the tools, which are scripts/ commands or have argparse.
    """
    from ament_index_python.packages import get_package_prefix
    nodes = {'wip_control': ('reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                             'torque_mixer', 'controllers'),
             'wip_sim': ('plant', 'standin_base', 'simulation'),
             'wip_bag': ('recorder', 'replay'),
             'wip_viewer': ('viewer', 'foxglove_bridge')}
    return [(package, name, pathlib.Path(get_package_prefix(package)) / 'lib' / package / name)
            for package, names in nodes.items() for name in names]


@pytest.fixture(scope='module')
def helped(tmp_path_factory, script_helps):
    """``--help`` of every scripts/ command (the session's) and node executable (all at once).

    Each in an empty folder of its own: name -> (status, output, files the folder holds after).
    """
    pytest.importorskip('rclpy')
    assert sorted(script_helps) == commands()
    runs = {f'{package}/{name}': [str(path), '--help']
            for package, name, path in node_executables()}
    found = {f'scripts/{name}': result for name, result in script_helps.items()}
    found.update({key: (status, out, files) for key, (status, out, _, files)
                  in _run_all(runs, tmp_path_factory, HELP_TIMEOUT, merge=True).items()})
    return found


def test_every_script_and_node_answers_help_without_starting_anything(helped):
    assert len([k for k in helped if k.startswith('scripts/')]) == len(commands())
    for key, (status, output, files) in helped.items():
        assert status == 0, f'{key} --help: exit {status}\n{output}'
        assert 'usage' in output.lower(), f'{key}\n{output}'
        assert 'Traceback (most recent call last)' not in output, f'{key}\n{output}'
        assert files == [], f'{key} --help wrote {files}'


def test_every_tool_help_ends_with_the_one_table(helped):
    for name in commands():
        if name in NOT_TOOLS:
            continue
        _, output, _ = helped[f'scripts/{name}']
        assert epilog_table(output) == cli.EXIT_CODES, name


#: Option names with two meanings, on purpose: replay's --clock is ros2 bag play's (publish
#: /clock), run_graph's the clock mode; each is what its users already type.
TWO_MEANINGS = {'--clock': {'replay'}}


def option_kinds(help_text: str) -> dict[str, str]:
    """Option -> 'switch' or 'value', from the options an argparse --help lists.

    argparse indents each option of its list by two spaces; prose that mentions one does not
    start so.
    """
    kinds = {}
    for match in re.finditer(r'^  (?:-\w(?: \S+)?, )?(--[\w-]+)(?:[ =]([A-Z_\[{][^\s,]*))?',
                             help_text, re.MULTILINE):
        kinds.setdefault(match.group(1), 'value' if match.group(2) else 'switch')
    return kinds


def test_one_meaning_per_option_name_across_the_tools(helped):
    # An option name is a switch in every tool or takes a value in every tool (e.g.
    # --params-file always reads a file, --json always names the file it writes).
    seen: dict[str, dict[str, str]] = {}
    for name in commands():
        if name in NOT_TOOLS:
            continue
        for option, kind in option_kinds(helped[f'scripts/{name}'][1]).items():
            if name not in TWO_MEANINGS.get(option, ()):
                seen.setdefault(option, {})[name] = kind
    mixed = {option: tools for option, tools in seen.items() if len(set(tools.values())) > 1}
    assert not mixed, mixed
    assert seen['--params-file'] and set(seen['--params-file'].values()) == {'value'}
    assert set(seen['--json'].values()) == {'value'} and len(seen['--json']) >= 3


#: reST markup that must not reach a terminal: roles, literals, citations, directives.
REST_MARKUP = re.compile(r':[a-z]+:`|``|\]_|^\s*\.\. [a-z\[]|::\s*$', re.MULTILINE)


def test_every_command_help_is_plain_text_with_examples(helped):
    for name in commands():
        if name in ('setup', 'test'):   # set-up has no use cases; test is pytest's help
            continue
        _, output, _ = helped[f'scripts/{name}']
        assert not REST_MARKUP.findall(output), (name, REST_MARKUP.findall(output))
        head, found, examples = output.partition('Examples')
        assert found, f'scripts/{name} --help has no examples'
        assert re.search(rf'^\s+scripts/{name}\b', examples, re.MULTILINE), name


def test_plain_text_renders_the_docstrings_markup():
    text = ('Runs :class:`~wip_sim.core.plant.Plant` and :func:`wip_bringup.graph.main` '
            'with ``--record`` as in [1]_::\n\n    x = 1\n\n.. math::\n\n    a = b\n\n'
            '.. [1] Yue, An, Li.')
    assert cli.plain_text(text) == ('Runs Plant and wip_bringup.graph.main with --record as '
                                    'in [1]:\n\n    x = 1\n\n\n    a = b\n\n[1] Yue, An, Li.')
    assert cli.plain_text(None) is None


@pytest.mark.parametrize('script, args', [
    ('report', ['BAG', '--out', 'out', '--no-such-option']),
    ('replay', ['BAG', '--ratee', '2']),
    ('rerun', ['BAG', '--out', 'out', '--scenaro', 'x.yaml']),
    ('bag_repair', ['BAG', '--outt', 'new']),
    ('simulate', ['--out', 'out', '--quite']),
    ('run_graph', ['--out', 'out', '--duraton', '3']),
])
def test_a_typo_in_an_option_is_exit_2_in_one_line_and_writes_nothing(tmp_path, script,
                                                                       args):
    done = subprocess.run([str(SCRIPTS / script), *args], cwd=tmp_path, text=True,
                          capture_output=True, timeout=HELP_TIMEOUT, stdin=subprocess.DEVNULL)
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if not line.startswith(
        ('wip:', 'setup:'))]   # a set-up the bootstrap may run first
    assert len(lines) == 1 and 'unrecognized arguments' in lines[0], done.stderr
    assert list(tmp_path.iterdir()) == []


def _run_all(runs, tmp_path_factory, timeout=REFUSE_TIMEOUT, merge=False):
    """Run every command of ``runs`` (key -> argv) at once, each in an empty folder.

    key -> (status, stdout, stderr, files the folder holds after); with ``merge`` stderr
    goes into stdout (and the stderr slot is '').
    """
    return run_at_once(runs, lambda key: tmp_path_factory.mktemp(key.replace('/', '_')),
                       timeout, merge)


def test_every_node_given_a_bad_ros_argument_exits_2_in_one_line(tmp_path_factory):
    pytest.importorskip('rclpy')
    runs = {f'{package}/{name}': [str(path), '--ros-args', '-r', '/imu/data:=/my imu']
            for package, name, path in node_executables()}
    for key, (status, out, err, files) in _run_all(runs, tmp_path_factory).items():
        executable = key.split('/')[1]
        assert status == cli.EXIT_USAGE, f'{key}: exit {status}\n{err}'
        assert 'Traceback' not in err + out, key
        (line,) = [line for line in err.splitlines() if 'error: ' in line
                   and not line.startswith('[ERROR]')]   # rcl logs its own line first
        assert line.startswith(f'{executable}: error: bad ROS arguments: ') and '/my imu' in line
        assert files == [], key


def test_every_node_given_a_bad_parameter_exits_2_naming_it(tmp_path_factory):
    # A value out of its declared range: the configuration error of the table (2), the
    # message naming the parameter; not 1 ("the vehicle fell").
    pytest.importorskip('rclpy')
    bad = {'wip_bag/recorder': 'discovery_period:=-1.0',
           'wip_bag/replay': 'rate:=-1.0',
           'wip_viewer/viewer': 'viewer.pose_rate:=-1.0',
           'wip_viewer/foxglove_bridge': 'port:=-5',
           'wip_sim/plant': 'clock_mode:=bogus',
           'wip_sim/simulation': 'clock_mode:=bogus',
           'wip_sim/standin_base': 'exit_after_fall:=-1.0'}
    runs = {}
    for package, name, path in node_executables():
        key = f'{package}/{name}'
        runs[key] = [str(path), '--ros-args', '-p', bad.get(key, 'clock_mode:=bogus')]
    for key, (status, out, err, files) in _run_all(runs, tmp_path_factory).items():
        name = bad.get(key, 'clock_mode:=bogus').split(':=')[0]
        assert status == cli.EXIT_USAGE, f'{key}: exit {status}\n{err}'
        assert 'Traceback' not in err + out, key
        assert name in err, f'{key}\n{err}'
        assert files == [], key
