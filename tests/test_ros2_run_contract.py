"""``ros2 run <package> <executable>`` works for every executable of the project.

ros2cli is not on PyPI, so the contract is tested directly: ``ros2 run pkg exe`` runs
``<prefix>/lib/<pkg>/<exe>`` with the prefix from the ament index. Each node executable of
every package is resolved that way and started as its own process in a DDS domain of its
own; a probe node in that domain must see the node's name and its topics (publishers and
subscriptions of the design); then SIGINT must end it cleanly. Each command-line tool
(every ``scripts/`` command of the README but set-up, demo and test) is an executable too:
its ``--help`` works, and its ``scripts/`` front door runs the same module.

Clean exit = exit code 0 and no traceback. Every entry point catches KeyboardInterrupt
and ExternalShutdownException (Jazzy raises either on SIGINT) and returns 0 after
destroying its node, as the Jazzy demos do; -2 or 130 would mean the interrupt escaped as
an uncaught exception (a traceback, possibly a half-written output), which is what this
test must catch.

All executables start at once (each in its own domain), so the whole module costs one
start-up (imports and discovery, a few seconds on two cores), not one per executable.
"""

import os
import pathlib
import re
import signal
import subprocess
import time

import pytest

rclpy = pytest.importorskip('rclpy')
from ament_index_python.packages import get_package_prefix  # noqa: E402
from processes import run_at_once  # noqa: E402
from ros_harness import communicate  # noqa: E402
from wip_bringup.private_domain import (release_private_domain,  # noqa: E402
                                        reserve_private_domain)

pytestmark = pytest.mark.ros

PACKAGES = ('wip_control', 'wip_sim', 'wip_bag', 'wip_bringup', 'wip_tools', 'wip_viewer')
REPO_ROOT = pathlib.Path(__file__).resolve().parent.parent
START_TIMEOUT = 60.0  # [s] all processes start together on 2 cores; discovery up to ~3 s
STOP_TIMEOUT = 10.0  # [s] from SIGINT to exit: the recorder closes its bag first

#: executable -> (node name, published topics, subscribed topics) of the design
#: (README / architecture: node graph and topics). /diagnostics: every node publishes it.
CONTRACT = {
    'reference': ('reference', {'/wip/reference', '/diagnostics'}, set()),
    'eso': ('eso', {'/wip/state_estimate', '/diagnostics'},
            {'/joint_states', '/imu/data', '/gps/fix', '/wip/wheel_torques'}),
    'trajectory_generator': ('trajectory_generator',
                             {'/wip/velocity_command', '/diagnostics'},
                             {'/wip/reference', '/wip/state_estimate'}),
    'arc': ('arc', {'/wip/yaw_torque', '/diagnostics'},
            {'/wip/velocity_command', '/wip/state_estimate'}),
    'mpc': ('mpc', {'/wip/drive_torque', '/diagnostics'},
            {'/wip/state_estimate', '/wip/velocity_command', '/wip/yaw_torque'}),
    'torque_mixer': ('torque_mixer',
                     {'/wip/wheel_torques', '/effort_controller/commands', '/diagnostics'},
                     {'/wip/yaw_torque', '/wip/drive_torque'}),
    'plant': ('plant', {'/clock', '/joint_states', '/imu/data', '/gps/fix',
                        '/wip/ground_truth', '/diagnostics'}, {'/wip/wheel_torques'}),
    'recorder': ('recorder', {'/diagnostics'}, set()),
    'replay': ('replayer', {'/contract/chatter', '/diagnostics'}, set()),
    # Hardware mode's stand-in for a real base: ros2_control-style topics only.
    'standin_base': ('standin_base', {'/joint_states', '/imu/data', '/gps/fix',
                                      '/diagnostics'}, {'/effort_controller/commands'}),
    # The guided sign/mounting check listens only; '-r' remaps as ros2 run passes them.
    'check_base': ('check_base', set(), {'/contract/joints', '/imu/data'}),
    # Standard messages for 3-D viewers, from the graph's custom ones.
    'viewer': ('viewer', {'/wip/odom/estimate', '/wip/odom/truth',
                          '/wip/markers/vehicle', '/wip/markers/prediction',
                          '/wip/path/reference', '/wip/path/travelled', '/diagnostics'},
               {'/wip/state_estimate', '/wip/ground_truth', '/wip/reference',
                '/wip/drive_torque'}),
    # The Foxglove WebSocket bridge: forwards the e-stop from a client; subscribes to the
    # graph's topics only while a client does.
    'foxglove_bridge': ('foxglove_bridge', {'/wip/estop', '/wip/estop_reset', '/diagnostics'},
                        set()),
}

#: Executables that hold several nodes (composition): executable -> its nodes, each with
#: the contract of its own executable.
COMPOSED = {'controllers': ('reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                            'torque_mixer'),
            'simulation': ('plant', 'reference', 'eso', 'trajectory_generator', 'arc', 'mpc',
                           'torque_mixer')}

#: Command-line tools: executable -> (package, its scripts/ front door). Those that are
#: also nodes (check_base, replay) are in CONTRACT too; each is named as its front door.
TOOLS = {
    'simulate': ('wip_tools', 'simulate'),
    'report': ('wip_tools', 'report'),
    'rerun': ('wip_tools', 'rerun'),
    'bench': ('wip_tools', 'bench'),
    'campaign': ('wip_tools', 'campaign'),
    'soak': ('wip_tools', 'soak'),
    'identify': ('wip_tools', 'identify'),
    'bag_info': ('wip_bag', 'bag_info'),
    'bag_repair': ('wip_bag', 'bag_repair'),
    'replay': ('wip_bag', 'replay'),
    'run_graph': ('wip_bringup', 'run_graph'),
    'estop': ('wip_bringup', 'estop'),
    'check_base': ('wip_bringup', 'check_base'),
    # Writes the Foxglove layout files (foxglove/); no scripts/ front door.
    'foxglove_layout': ('wip_viewer', None),
    # The parameter reference; its front door is scripts/simulate --list-parameters.
    'parameters': ('wip_tools', None),
    # docs/paper.md's results table from a run; scripts/ros2_run is its front door.
    'results_table': ('wip_tools', None),
}
#: scripts/ commands that are not a tool of a package: set-up, the demo (run_graph then
#: report), the test runner, and ros2_run (``ros2 run`` for any executable, in the venv).
NOT_TOOLS = {'setup', 'demo', 'test', 'ros2_run'}
HELP_TIMEOUT = 120.0  # [s] all --help processes start together on a slow, busy machine

#: Exit status on SIGINT where it is not 0: check_base is an interactive check, and an
#: interrupted check has not passed (130 = 128 + SIGINT, the shell's convention).
SIGINT_STATUS = {'check_base': 130}


def executables():
    """(package, executable, path) of everything ``ros2 run`` could start."""
    found = []
    for package in PACKAGES:
        directory = pathlib.Path(get_package_prefix(package)) / 'lib' / package
        for path in sorted(directory.iterdir()):
            if path.is_file() and os.access(path, os.X_OK):
                found.append((package, path.name, path))
    return found


def make_bag(directory):
    """Return a tiny bag for the replayer: 5 std_msgs/String on /contract/chatter."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    from wip_bag.bag_writer import Rosbag2McapWriter
    with Rosbag2McapWriter(directory) as bag:
        bag.add_topic('/contract/chatter', 'std_msgs/msg/String')
        for i in range(5):
            bag.write('/contract/chatter', serialize_message(String(data=f'{i}')),
                      1_000_000_000 + i * 10_000_000)
    return directory


class Started:
    """One executable's process and a probe node in its own domain."""

    def __init__(self, executable, path, domain, extra_args, cwd):
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain),
                   ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
        self.executable = executable
        self.process = subprocess.Popen(
            [str(path), '--ros-args', *extra_args], env=env, cwd=cwd,
            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=domain)
        self.probe = rclpy.create_node('contract_probe', context=self.context)

    def topics_of(self, node_name):
        get_pubs = self.probe.get_publisher_names_and_types_by_node
        get_subs = self.probe.get_subscriber_names_and_types_by_node
        try:
            return ({name for name, _ in get_pubs(node_name, '/')},
                    {name for name, _ in get_subs(node_name, '/')})
        except Exception:  # noqa: BLE001 - the node is not known yet (NodeNameNonExistentError)
            return set(), set()

    def close(self):
        if self.process.poll() is None:
            self.process.kill()
            self.process.communicate()
        self.probe.destroy_node()
        rclpy.try_shutdown(context=self.context)


@pytest.fixture(scope='module')
def started(tmp_path_factory):
    """Every executable started at once, each in its own domain."""
    work = tmp_path_factory.mktemp('contract')
    bag = make_bag(work / 'replay_bag')
    extra = {
        'recorder': ['-p', f'output:={work / "recorded"}'],
        'replay': ['-p', f'bag:={bag}', '-p', 'exit_when_done:=false', '-p', 'loop:=true'],
        'plant': ['-p', 'autostart:=false'],
        'simulation': ['-p', 'autostart:=false'],
        'check_base': ['-r', '/joint_states:=/contract/joints'],
        'foxglove_bridge': ['-p', 'port:=0'],
    }
    nodes = set(CONTRACT) | set(COMPOSED)
    found = [entry for entry in executables() if entry[1] in nodes]
    # Domains reserved on the host for the module's life (a test session side by side
    # with another must not share one), released after the processes stopped.
    reserved = [reserve_private_domain() for _ in found]
    processes = {}
    try:
        for (package, executable, path), (domain, _) in zip(found, reserved):
            processes[executable] = Started(executable, path, domain,
                                            extra.get(executable, []), work)
        yield processes
    finally:
        for process in processes.values():
            process.close()
        for _, descriptor in reserved:
            release_private_domain(descriptor)


def test_every_executable_has_a_contract_entry():
    names = {executable for _, executable, _ in executables()}
    assert names == set(CONTRACT) | set(COMPOSED) | set(TOOLS), \
        'update CONTRACT, COMPOSED or TOOLS (and the README) for new executables'
    packages = {package for package, _, _ in executables()}
    assert packages == set(PACKAGES)
    found = {executable: package for package, executable, _ in executables()}
    assert {name: found[name] for name in TOOLS} == {
        name: package for name, (package, _) in TOOLS.items()}
    # One name: a tool's executable is called as its scripts/ front door.
    assert all(script in (None, executable) for executable, (_, script) in TOOLS.items())


def entry_point_module(package, executable):
    """Return the module whose ``main`` a console script runs.

    Read from the package's setup.py (and its console.py for the tools, see
    wip_runtime.cli.console_script).
    """
    source = REPO_ROOT / 'ros_ws' / 'src' / package
    text = (source / 'setup.py').read_text(encoding='utf-8')
    match = re.search(rf"'{executable} = ([\w.]+):(\w+)'", text)
    assert match, f'{package}/setup.py has no console script {executable}'
    if match.group(2) == 'main':
        return match.group(1)
    assert match.group(1) == f'{package}.console', match.group(0)
    console = (source / package / 'console.py').read_text(encoding='utf-8')
    found = re.search(rf"^{match.group(2)} = console_script\('([\w.]+)', '{executable}'\)$",
                      console, re.MULTILINE)
    assert found, f'{package}/console.py: no console_script for {executable}'
    return found.group(1)


def test_every_readme_command_is_an_executable_run_by_its_script():
    readme = (REPO_ROOT / 'README.md').read_text(encoding='utf-8')
    commands = set(re.findall(r'^\| `scripts/(\w+)', readme, re.MULTILINE)) - NOT_TOOLS
    fronts = {script: (package, executable)
              for executable, (package, script) in TOOLS.items() if script}
    assert commands == set(fronts), 'the README lists a command that is no executable'
    for script, (package, executable) in sorted(fronts.items()):
        text = (REPO_ROOT / 'scripts' / script).read_text(encoding='utf-8')
        # A thin front door: the set-up, then the executable's own module.
        assert re.findall(r'exec python -m ([\w.]+) "\$@"', text) == [
            entry_point_module(package, executable)], script


def test_scripts_ros2_run_lists_and_starts_every_executable_as_ros2_run():
    # The venv's stand-in for ros2 run: the same executables, started from the same files.
    script = REPO_ROOT / 'scripts' / 'ros2_run'
    listed = subprocess.run([str(script), '--list'], capture_output=True, text=True,
                            timeout=HELP_TIMEOUT, check=True).stdout.split('\n')
    assert sorted(line for line in listed if line) == sorted(
        f'{package} {name}' for package, name, _ in executables())
    helped = subprocess.run([str(script), 'wip_viewer', 'foxglove_layout', '--help'],
                            capture_output=True, text=True, timeout=HELP_TIMEOUT)
    assert helped.returncode == 0 and 'usage: python -m wip_viewer.foxglove_layout' in \
        helped.stdout
    unknown = subprocess.run([str(script), 'wip_sim', 'no_such_node'], capture_output=True,
                             text=True, timeout=HELP_TIMEOUT)
    assert unknown.returncode == 2 and unknown.stderr.count('\n') == 1, unknown.stderr
    assert "no executable 'no_such_node' in package 'wip_sim'" in unknown.stderr


@pytest.fixture(scope='module')
def helped(tmp_path_factory):
    """``<exe> --help`` of every tool, all started at once: executable -> (status, output)."""
    work = tmp_path_factory.mktemp('help')
    paths = {executable: path for package, executable, path in executables()}
    results = run_at_once({executable: [str(paths[executable]), '--help']
                           for executable in TOOLS}, lambda executable: work, HELP_TIMEOUT,
                          merge=True)
    return {executable: (status, output) for executable, (status, output, _, _)
            in results.items()}


@pytest.mark.slow  # 13 processes importing numpy and rclpy at once: about 20 s on 2 cores
@pytest.mark.parametrize('executable', sorted(TOOLS))
def test_every_tool_answers_help(executable, helped):
    status, output = helped[executable]
    assert status == 0, f'{executable} --help: exit {status}\n{output}'
    assert 'usage:' in output and 'Traceback' not in output, output


@pytest.mark.slow
@pytest.mark.parametrize('executable', sorted(set(CONTRACT) | set(COMPOSED)))
def test_executable_runs_as_ros2_run_would_and_stops_cleanly_on_sigint(executable, started):
    one = started[executable]
    contracts = [CONTRACT[n] for n in COMPOSED.get(executable, (executable,))]
    deadline = time.monotonic() + START_TIMEOUT
    while True:
        if one.process.poll() is not None:
            output, _ = one.process.communicate()
            pytest.fail(f'{executable} exited ({one.process.returncode}) during start-up:\n'
                        f'{output}')
        names = {name for name, namespace in one.probe.get_node_names_and_namespaces()
                 if namespace == '/'}
        missing = []
        for node_name, publishes, subscribes in contracts:
            pubs, subs = one.topics_of(node_name) if node_name in names else (set(), set())
            if not (node_name in names and publishes <= pubs and subscribes <= subs):
                missing.append(f'node {node_name!r} present: {node_name in names}; missing '
                               f'publishers {publishes - pubs}, missing subscriptions '
                               f'{subscribes - subs}')
        if not missing:
            break
        if time.monotonic() > deadline:
            pytest.fail(f'{executable}: after {START_TIMEOUT} s: {"; ".join(missing)}')
        time.sleep(0.1)  # graph polling (discovery is asynchronous, no event to wait on)

    one.process.send_signal(signal.SIGINT)
    output, _ = communicate(one.process, STOP_TIMEOUT, 'stop on SIGINT')
    expected = SIGINT_STATUS.get(executable, 0)
    assert one.process.returncode == expected, f'{executable} exit code ' \
                                               f'{one.process.returncode}:\n{output}'
    assert 'Traceback' not in output, output


def test_a_console_script_maps_failures_onto_the_exit_code_table(tmp_path, monkeypatch,
                                                                 capsys):
    # What `ros2 run <package> <tool>` runs: the tool's main through run_main. A module
    # that fails at import or in main gives one line on stderr and exit 3, no traceback.
    from wip_runtime.cli import console_script
    monkeypatch.setenv('WIP_TRACE_DIR', str(tmp_path / 'traces'))
    (tmp_path / 'contract_tool_ok.py').write_text(
        'def main(argv):\n    return 0 if argv is None else 9\n', encoding='utf-8')
    (tmp_path / 'contract_tool_broken.py').write_text(
        'def main(argv):\n    raise RuntimeError("broken on purpose")\n', encoding='utf-8')
    monkeypatch.syspath_prepend(str(tmp_path))
    assert console_script('contract_tool_ok', 'ok')() == 0
    assert console_script('contract_tool_broken', 'broken')() == 3
    assert console_script('contract_tool_missing', 'missing')() == 3
    err = capsys.readouterr().err.splitlines()
    assert [line.split(':', 2)[:2] for line in err] == [['broken', ' internal error'],
                                                        ['missing', ' internal error']]
    assert 'broken on purpose' in err[0] and 'Traceback' not in '\n'.join(err)
