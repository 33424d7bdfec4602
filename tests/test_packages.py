"""The packages of ros_ws/src by role, and what they may import.

The import graph of every Python module under ``ros_ws/src/<package>/<package>/`` is built
from the source (ast, every ``import`` statement, also those inside functions: a lazy import
is still a dependency) and checked:

(a) no import cycle between modules;
(b) every package imports only what its package.xml declares (``<depend>`` or
    ``<exec_depend>``): ROS packages by name, Python libraries by their rosdep key
    (python3-<name>), and libraries without a rosdep key from requirements.txt;
(c) the dependency graph of the packages (from their package.xml) has no cycle;
(d) the packages are layered (:data:`LAYERS`, docs/packages.md): none imports a package of its
    own layer or above, and each package.xml declares the wip_* packages its code imports, no
    more; its setup.py installs the package it names;
(e) wip_control, the controllers a robot installs, imports of the other wip_* packages only
    the messages, the runtime and the robot's description; wip_bag and wip_viewer import
    nothing of wip_control.
"""

import ast
import pathlib
import re
import sys
import xml.etree.ElementTree as ElementTree

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
SRC = ROOT / 'ros_ws' / 'src'

#: The packages and their job (the README's layout table says the same).
PACKAGES = ('wip_msgs', 'wip_runtime', 'wip_description', 'wip_control', 'wip_sim', 'wip_bag',
            'wip_bringup', 'wip_tools', 'wip_viewer')
#: The packages from the bottom up (docs/packages.md, "Layers"): a package imports only
#: packages of the layers below its own.
LAYERS = (('wip_msgs',), ('wip_runtime',), ('wip_description',), ('wip_bag', 'wip_control'),
          ('wip_viewer',), ('wip_sim',), ('wip_bringup',), ('wip_tools',))
#: Dependencies that no import statement shows: (package, dependency) -> how it is used.
IMPORTED_BY_NAME = {('wip_tools', 'wip_viewer'): 'wip_tools.parameters imports '
                                                 'wip_viewer.settings by its name'}
#: Standard ROS interface packages that ros_ws carries for a ROS installation without them
#: (scripts/setup builds them only there; tests/test_setup_contract.py).
STANDARD_INTERFACES = ('tf2_msgs',)
#: Python libraries with a rosdep key: import name -> key.
ROSDEP_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
               'matplotlib': 'python3-matplotlib', 'numba': 'python3-numba'}
#: Python libraries without a rosdep key: import name -> its name in requirements.txt.
PIP_ONLY = {'mcap': 'mcap', 'mcap_ros2': 'mcap-ros2-support', 'proxsuite': 'proxsuite',
            'mujoco': 'mujoco',
            'daqp': 'daqp', 'dask': 'dask', 'tqdm': 'tqdm', 'foxglove': 'foxglove-sdk',
            'rosbags': 'rosbags',
            # Optional (runs.parquet when installed): imported under try/except ImportError.
            'pyarrow': None}
#: Imports of the ROS client library and message packages: the name is the package.
ROS_IMPORTS = {'rclpy', 'rcl_interfaces', 'builtin_interfaces', 'ament_index_python',
               'std_msgs', 'std_srvs', 'sensor_msgs', 'nav_msgs', 'geometry_msgs',
               'visualization_msgs', 'diagnostic_msgs', 'rosgraph_msgs', 'wip_msgs',
               'tf2_msgs'}


def python_packages():
    """Names of the ament_python packages (those with Python modules)."""
    return sorted(p.name for p in SRC.iterdir() if (p / p.name / '__init__.py').is_file())


def modules():
    """Dotted module name -> source path, for every module of every package."""
    found = {}
    for package in python_packages():
        for path in sorted((SRC / package / package).rglob('*.py')):
            parts = list(path.relative_to(SRC / package).with_suffix('').parts)
            if parts[-1] == '__init__':
                parts.pop()
            found['.'.join(parts)] = path
    return found


def imports_of(name, path, known):
    """Every module ``name`` imports.

    Dotted names, relative imports resolved; ``from x import y`` counts as an import of x.y when
    x.y is a module of ours.
    """
    is_package = path.name == '__init__.py'
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split('.') if is_package else name.split('.')[:-1]
                base = base[:len(base) - (node.level - 1)]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module
            found.add(target)
            found.update(f'{target}.{alias.name}' for alias in node.names
                         if f'{target}.{alias.name}' in known)
    return found


@pytest.fixture(scope='module')
def graph():
    """Return module -> set of imported modules (ours and others)."""
    known = modules()
    return {name: imports_of(name, path, known) for name, path in known.items()}


def declared(package):
    """Names a package.xml declares as run-time dependencies."""
    tree = ElementTree.parse(SRC / package / 'package.xml')
    return {e.text.strip() for tag in ('depend', 'exec_depend') for e in tree.iter(tag)}


def find_cycle(edges):
    """One cycle of the directed graph ``edges`` (node -> successors) as a list, or None."""
    state = {}  # node -> 1 on the current path, 2 done

    def visit(node, path):
        state[node] = 1
        path.append(node)
        for succ in sorted(edges.get(node, ())):
            if state.get(succ) == 1:
                return path[path.index(succ):] + [succ]
            if succ not in state:
                cycle = visit(succ, path)
                if cycle:
                    return cycle
        state[node] = 2
        path.pop()
        return None

    for node in sorted(edges):
        if node not in state:
            cycle = visit(node, [])
            if cycle:
                return cycle
    return None


def requirement_names():
    text = (ROOT / 'requirements.txt').read_text(encoding='utf-8')
    return {re.split(r'[=<>\[ ;]', line.strip(), maxsplit=1)[0].lower()
            for line in text.splitlines() if line.strip() and not line.startswith('#')}


def test_the_source_tree_holds_the_packages_of_the_layout():
    on_disk = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())
    assert on_disk == sorted(PACKAGES + STANDARD_INTERFACES)
    for package in python_packages():
        for name in ('setup.py', 'setup.cfg', f'resource/{package}'):
            assert (SRC / package / name).is_file(), f'{package}/{name}'
        # ros2 run looks for the console scripts in lib/<package>.
        assert f'$base/lib/{package}' in (SRC / package / 'setup.cfg').read_text()


def test_the_graph_sees_every_module_and_its_imports(graph):
    # The checks below are only as good as the graph: it must hold every package's modules
    # and the imports known to exist.
    assert {name.split('.')[0] for name in graph} == set(python_packages())
    assert 'wip_bringup.launcher' in graph['wip_bringup.hardware']
    assert 'wip_bag.bag_writer' in graph['wip_bag.bag_repair']
    assert 'wip_control.core.mpc_config' in graph['wip_control.nodes.mpc_node']  # relative import


def test_no_import_cycle_between_modules(graph):
    ours = {name: {t for t in targets if t in graph} for name, targets in graph.items()}
    cycle = find_cycle(ours)
    assert cycle is None, ' -> '.join(cycle)
    # The checker finds a cycle when there is one.
    assert find_cycle({'a': {'b'}, 'b': {'c'}, 'c': {'a'}}) == ['a', 'b', 'c', 'a']


def test_every_package_declares_what_it_imports(graph):
    pip = requirement_names()
    problems = []
    for package in python_packages():
        deps = declared(package)
        roots = {target.split('.')[0] for name, targets in graph.items()
                 if name.split('.')[0] == package for target in targets}
        for root in sorted(roots - {package}):
            if root in sys.stdlib_module_names or root == '__future__':
                continue
            if root in ROS_IMPORTS or root in PACKAGES:
                if root not in deps:
                    problems.append(f'{package} imports {root}: not in its package.xml')
            elif root in ROSDEP_KEYS:
                if ROSDEP_KEYS[root] not in deps:
                    problems.append(f'{package} imports {root}: declare '
                                    f'{ROSDEP_KEYS[root]} in its package.xml')
            elif root in PIP_ONLY:
                if PIP_ONLY[root] is not None and PIP_ONLY[root] not in pip:
                    problems.append(f'{package} imports {root}: {PIP_ONLY[root]} is not in '
                                    'requirements.txt')
            else:
                problems.append(f'{package} imports {root}: unknown to this test (add it to '
                                'ROS_IMPORTS, ROSDEP_KEYS or PIP_ONLY)')
    assert not problems, '\n'.join(problems)


def test_the_package_dependency_graph_has_no_cycle():
    edges = {package: declared(package) & set(PACKAGES) for package in PACKAGES}
    cycle = find_cycle(edges)
    assert cycle is None, ' -> '.join(cycle)


def package_imports(graph, package):
    """Return the wip_* packages ``package`` imports, each with one import that shows it."""
    found = {}
    for name, targets in sorted(graph.items()):
        if name.split('.')[0] != package:
            continue
        for target in sorted(targets):
            root = target.split('.')[0]
            if root != package and root in PACKAGES:
                found.setdefault(root, f'{name} imports {target}')
    return found


def layer_of(package):
    return next(i for i, layer in enumerate(LAYERS) if package in layer)


def test_the_layers_hold_every_package_once():
    layered = [package for layer in LAYERS for package in layer]
    assert sorted(layered) == sorted(PACKAGES)


def test_docs_list_the_layers_checked_here():
    text = (ROOT / 'docs' / 'packages.md').read_text(encoding='utf-8')
    section = text.split('\n## Layers\n', 1)[1].split('\n## ', 1)[0]
    listed = [tuple(line.split('. ', 1)[1].split(', ')) for line in section.splitlines()
              if re.match(r'^\d+\. ', line)]
    assert listed == [tuple(sorted(layer)) for layer in LAYERS]


@pytest.mark.parametrize('package', PACKAGES)
def test_no_package_imports_its_own_layer_or_one_above(graph, package):
    # Imports in functions count (the graph has them): a lazy import is still a dependency.
    upward = sorted(line for root, line in package_imports(graph, package).items()
                    if layer_of(root) >= layer_of(package))
    assert not upward, '\n'.join(upward)
    upward = sorted(d for d in declared(package) & set(PACKAGES)
                    if layer_of(d) >= layer_of(package))
    assert not upward, f'{package}/package.xml declares {upward}'


@pytest.mark.parametrize('package', python_packages())
def test_package_xml_declares_the_wip_packages_the_code_imports_and_no_more(graph, package):
    imported = set(package_imports(graph, package))
    imported |= {dependency for (user, dependency) in IMPORTED_BY_NAME if user == package}
    assert declared(package) & set(PACKAGES) == imported


@pytest.mark.parametrize('package', python_packages())
def test_setup_py_installs_the_package_its_package_xml_names(package):
    tree = ElementTree.parse(SRC / package / 'package.xml')
    setup_py = (SRC / package / 'setup.py').read_text(encoding='utf-8')
    assert tree.findtext('name') == package
    assert f"package_name = '{package}'" in setup_py
    assert f"version='{tree.findtext('version')}'" in setup_py
    # Data files besides the modules: the XML of the package's own folder, nothing else.
    xml = sorted((SRC / package / package).glob('*.xml'))
    assert ("package_data={package_name: ['*.xml']}" in setup_py) == bool(xml)
    assert 'glob(' not in setup_py and 'config' not in setup_py


def test_the_controllers_import_only_the_messages_runtime_and_description(graph):
    # wip_control is the drop-in for a robot: it must install without the simulator, the
    # bag tooling, the bring-up or the offline tools.
    allowed = {'wip_msgs', 'wip_runtime', 'wip_description'}
    foreign = sorted(line for root, line in package_imports(graph, 'wip_control').items()
                     if root not in allowed)
    assert not foreign, '\n'.join(foreign)
    assert declared('wip_control') & set(PACKAGES) == allowed


@pytest.mark.parametrize('package', ['wip_bag', 'wip_viewer'])
def test_the_bag_tools_and_the_viewer_need_no_controller(graph, package):
    # A bag tool or a viewer runs where no controller is installed (a laptop, a log server).
    assert 'wip_control' not in package_imports(graph, package)
    assert 'wip_control' not in declared(package)


def test_the_robot_description_needs_no_ros_client_library(graph):
    # The description is read by every package, also by the offline tools and scripts that
    # start no node: nothing it imports, directly or not, loads rclpy.
    reached = set()
    for name in graph:
        if name.startswith('wip_description'):
            reached |= reached_from(graph, name)
    ros = sorted(f'{name} imports {target}' for name in reached for target in graph[name]
                 if target.split('.')[0] in ROS_IMPORTS)
    assert not ros, '\n'.join(ros)


def test_the_viewer_shows_the_controllers_default_limits():
    # foxglove_layout writes the controllers' defaults (the viewer imports no controller).
    from wip_control.core.controller_settings import ControllerParams
    from wip_viewer.foxglove_layout import PlotLimits

    settings, limits = ControllerParams(), PlotLimits()
    assert (limits.max_tilt, limits.max_speed, limits.max_yaw_rate,
            limits.max_wheel_torque) == (
        settings.mpc.max_tilt, settings.trajectory_generator.max_speed,
        settings.trajectory_generator.max_yaw_rate, settings.mixer.max_wheel_torque)


def reached_from(graph, start):
    """Every module of ours that ``start`` imports, directly or not."""
    reached, todo = set(), [start]
    while todo:
        name = todo.pop()
        if name in reached:
            continue
        reached.add(name)
        todo.extend(t for t in graph.get(name, ()) if t in graph)
    return reached


@pytest.mark.parametrize('tool', ['wip_bringup.check_base', 'wip_bringup.hardware'])
def test_the_real_base_tools_need_no_simulator(graph, tool):
    # check_base and hardware mode run on a robot: nothing they import, directly or not, is
    # in wip_sim (run_graph's simulation mode, wip_bringup.graph, is the one that is).
    sim = sorted(name for name in reached_from(graph, tool) if name.startswith('wip_sim'))
    assert not sim, f'{tool} reaches {sim}'
    assert any(name.startswith('wip_sim') for name in reached_from(graph, 'wip_bringup.graph'))


def test_the_controllers_hold_no_plant(graph):
    # What runs on a robot: estimation, generator, ARC, MPC, LQR, safety and the control
    # step. The plant, its compiled integrator, the forward sensor models, the disturbances
    # and the in-process runner are the simulator's (wip_sim); analysis is wip_tools'. Of
    # the controllers only the MPC's QP assembly and polish, the time-scaled reference's
    # real-time sample, the gyro estimator's steady sample, the safety layer's steady tick
    # and the body's attitude from an IMU sample are compiled with numba (and numba_math,
    # what they call), declared.
    control = {name: targets for name, targets in graph.items()
               if name.startswith('wip_control')}
    simulator = {'plant', 'plant_rk4', 'sensor_models', 'disturbances', 'ground', 'runner',
                 'simulation', 'scenario', 'record', 'metrics', 'criteria'}
    assert not sorted(name for name in control if name.rsplit('.', 1)[-1] in simulator)
    assert sorted(name for name, targets in control.items()
                  if any(t.split('.')[0] in ('numba', 'llvmlite') for t in targets)) == [
                      'wip_control.core.attitude_kernel', 'wip_control.core.estimator_kernel',
                      'wip_control.core.mpc_kernel', 'wip_control.core.numba_math',
                      'wip_control.core.qp_polish',
                      'wip_control.core.retiming_kernel', 'wip_control.core.safety_kernel']
    assert 'python3-numba' in declared('wip_control')
    # The checks see the modules they look for where they are.
    assert {'wip_sim.core.plant', 'wip_sim.core.plant_rk4', 'wip_sim.core.runner',
            'wip_tools.analysis.metrics'} <= set(graph)
    assert 'numba' in graph['wip_sim.core.plant_rk4']
