"""Test configuration: make the workspace's Python packages importable from source.

The pure-numpy core is tested straight from ``ros_ws/src`` so that editing it needs no
rebuild; tests of nodes and of the graph use the colcon-built install tree, which
``scripts/test`` builds first.
"""

import contextlib
import os
import pathlib
import sys

import pytest
from hypothesis import settings

REPO_ROOT = pathlib.Path(__file__).resolve().parents[1]
#: [s] for every scripts/ --help at once on a slow, shared 2-core machine.
SCRIPT_HELP_TIMEOUT = 300.0

# Property-based tests: in CI (CI set, as .ci/run's environment has it) the same examples
# on every run, so that a submission is judged on its code, not on what a random search
# happened to draw that day, and no deadline (an example's time is the machine's load, not
# the code's); on a developer's machine each run draws new examples and keeps
# what fails in .hypothesis/ to replay it.
settings.register_profile('ci', derandomize=True, database=None, deadline=None)
if os.environ.get('CI'):
    settings.load_profile('ci')
# A child process that hangs is ended with SIGABRT first (ros_harness.stop_with_stacks):
# with faulthandler on, its output then holds every thread's Python stack.
os.environ.setdefault('PYTHONFAULTHANDLER', '1')
# The tests choose their DDS domains and discovery themselves (private_dds_domain, explicit
# environments): hardware mode and check_base must take those as the user's settings, not
# drop them as scripts/_env.sh's defaults (wip_bringup.launcher.use_user_ros_environment).
_ENV_DEFAULTS = os.environ.pop('WIP_ROS_DEFAULTS', '').split()
for package in ('wip_control', 'wip_sim', 'wip_bag', 'wip_bringup', 'wip_tools', 'wip_viewer'):
    path = str(REPO_ROOT / 'ros_ws' / 'src' / package)
    if path not in sys.path:
        sys.path.insert(0, path)

from wip_bringup.private_domain import (release_private_domain, release_taken_domains,  # noqa: E402
                                        reserve_private_domain)
from wip_runtime.dds_profile import use_launcher_profile  # noqa: E402

# The test processes' own participants (harness nodes, run_graph's probe) announce themselves
# as often as the graphs' nodes do, where the user has no Fast DDS profile: set before any
# participant of this process is made (wip_runtime/fastdds_launcher_profile.xml says why).
use_launcher_profile()

# The session's own domain, for the tests that start graphs without a domain fixture: not
# scripts/_env.sh's pid-derived default, which is not reserved (a test session beside another
# put its stand-in base and controllers into the other session's lockstep graph), but one
# reserved on this host for the session's life (the kernel frees it when pytest exits). A
# domain the user set themselves is kept. A pytest-xdist worker inherits its controller's
# session domain: it reserves one of its own, or two workers' graphs would meet in it.
if ('ROS_DOMAIN_ID' not in os.environ
        or f"ROS_DOMAIN_ID={os.environ['ROS_DOMAIN_ID']}" in _ENV_DEFAULTS
        or os.environ['ROS_DOMAIN_ID'] == os.environ.get('WIP_TEST_SESSION_DOMAIN')):
    _SESSION_DOMAIN = reserve_private_domain()
    os.environ['ROS_DOMAIN_ID'] = os.environ['WIP_TEST_SESSION_DOMAIN'] = str(
        _SESSION_DOMAIN[0])


# ----------------------------------------------------------------- ROS test isolation

@contextlib.contextmanager
def private_dds_domain():
    """Give this process and its children a random DDS domain, localhost only.

    A random DDS domain with localhost-only discovery for this process and the
    processes it starts (ROS_DOMAIN_ID, ROS_AUTOMATIC_DISCOVERY_RANGE), restored after.

    1..101: Fast DDS ports of higher domain ids fall into Linux's ephemeral port range.
    """
    keys = ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')
    saved = {key: os.environ.get(key) for key in keys}
    # Reserved on this host: two test sessions (or a session and a simulation) never meet.
    domain_id, reservation = reserve_private_domain()
    os.environ['ROS_DOMAIN_ID'] = str(domain_id)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    try:
        yield domain_id
    finally:
        release_private_domain(reservation)
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


@pytest.fixture(autouse=True)
def _release_taken_domains():
    """Free the domains a test took with take_private_domain once it has ended.

    The domains a test took with wip_bringup.private_domain.take_private_domain are
    free again once it has ended.
    """
    yield
    release_taken_domains()


@pytest.fixture
def domain():
    """Yield a DDS domain of the test's own (see :func:`private_dds_domain`)."""
    with private_dds_domain() as domain_id:
        yield domain_id


@pytest.fixture
def test_node(domain):
    """A node in a private rclpy context in the test's domain, with its own executor.

    ``node.executor_for_test``.
    """
    rclpy = pytest.importorskip('rclpy')
    from rclpy.executors import SingleThreadedExecutor
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    node = rclpy.create_node('test_probe', context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    node.executor_for_test = executor
    yield node
    executor.shutdown()
    node.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope='module')
def module_domain():
    """Yield a DDS domain for a whole test module (see :func:`private_dds_domain`)."""
    with private_dds_domain() as domain_id:
        yield domain_id


@pytest.fixture(scope='module')
def context(module_domain):
    """One rclpy context for a whole test module, in its own DDS domain."""
    rclpy = pytest.importorskip('rclpy')
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=module_domain)
    yield ctx
    rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope='session')
def script_helps(tmp_path_factory):
    """``scripts/NAME --help`` of every command of scripts/, all at once, for the session.

    Each in an empty folder of its own (stderr into stdout): name -> (status, output, files
    the folder holds after). One start of each front door for the tests that read their
    help (tests/test_exit_codes.py, tests/test_doc_commands.py).
    """
    from processes import run_at_once
    scripts = REPO_ROOT / 'scripts'
    names = sorted(p.name for p in scripts.iterdir()
                   if p.is_file() and os.access(p, os.X_OK) and p.name != '_env.sh')
    results = run_at_once({name: [str(scripts / name), '--help'] for name in names},
                          lambda name: tmp_path_factory.mktemp(f'scripts_{name}'),
                          SCRIPT_HELP_TIMEOUT, merge=True)
    return {name: (status, out, files) for name, (status, out, _, files) in results.items()}


@pytest.fixture
def harnesses():
    """Close what a test made that must be closed, at its end, failed or not.

    What a test made that must be closed (``close()``: node harnesses, see
    ``tests/ros_harness.py``), closed at its end, failed or not.
    """
    made = []
    yield made
    for harness in made:
        harness.close()


# ----------------------------------------------------------------- a slow day on purpose

def pytest_addoption(parser):
    parser.addoption(
        '--busy-cores', type=int, default=0, metavar='N',
        help='run N busy processes (one spinning Python loop each, at the normal '
             'scheduling policy) for the whole session: the shared, slow machine CI may '
             'get, made on purpose (e.g. scripts/test --busy-cores 2 -m realtime)')


@pytest.fixture(scope='session', autouse=True)
def busy_cores(request):
    """Run the ``--busy-cores N`` processes for the whole session.

    The ``--busy-cores N`` processes, started before the first test and ended after the
    last (killed with their process group, so an interrupted session leaves none).
    """
    import signal
    import subprocess
    count = request.config.getoption('--busy-cores')
    if count < 0:
        raise pytest.UsageError(f'--busy-cores: must be >= 0, got {count}')
    loops = [subprocess.Popen([sys.executable, '-c', 'while True: pass'],
                              start_new_session=True) for _ in range(count)]
    yield len(loops)
    for loop in loops:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(loop.pid, signal.SIGKILL)
        loop.wait()
