"""How the launcher starts and ends node processes.

1. Real-time scheduling is applied by ``chrt``/``taskset`` in front of the program (no
   Python between fork and exec, which can deadlock in a child of a threaded process):
   the program and the threads it starts run at the requested SCHED_FIFO priority.
2. A node started by a launcher ends when the launcher dies without stopping it (SIGKILL):
   an orphaned controller would go on commanding the robot, and at real-time priority
   take the CPUs from everything else.
"""

import os
import pathlib
import signal
import struct
import subprocess
import sys
import textwrap
import time

import pytest

from wip_bringup.launcher import EXIT_USAGE, GraphError
from wip_bringup.processes import executable_path, graph_environment, NodeProcess
from wip_bringup.scheduling import CpuLatencyRequest, Scheduling
from wip_runtime.launched import end_with_launcher, LAUNCHER_PID_VARIABLE

START_UP = 60.0   # [s] generous: a loaded CI machine starts a Python process slowly


def _wait_for(predicate, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    pytest.fail(f'{what}: not within {timeout:g} s')


def _alive(pid: int) -> bool:
    try:
        with open(f'/proc/{pid}/stat', encoding='ascii') as stream:
            return stream.read().rsplit(')', 1)[1].split()[0] != 'Z'
    except OSError:
        return False


def test_scheduling_is_a_command_prefix_and_absurd_values_are_refused():
    assert Scheduling().command_prefix() == []
    assert Scheduling(20, (0,)).command_prefix() == ['chrt', '--fifo', '20',
                                                     'taskset', '--cpu-list', '0']
    assert Scheduling(20, rt_cpu_limit=1.5).command_prefix() == [
        'prlimit', '--rttime=1500000', 'chrt', '--fifo', '20']
    assert Scheduling(0, rt_cpu_limit=1.5).command_prefix() == []   # only with a priority
    with pytest.raises(GraphError, match='--rt-priority: must be in 0..99'):
        Scheduling(100).check()
    with pytest.raises(GraphError, match='--cpu-affinity: CPUs \\[4096\\]'):
        Scheduling(0, (4096,)).check()
    with pytest.raises(GraphError, match='--cpu-latency: must be in 0..1000000 us, got -1'):
        Scheduling(cpu_latency=-1).check()
    assert Scheduling(cpu_latency=0).command_prefix() == []    # held by the launcher


def test_a_cpu_latency_request_holds_while_open_and_is_refused_with_the_reason(tmp_path):
    # The kernel's PM QoS file takes a 32-bit int and keeps it while open; a file that
    # cannot be opened is a usage error naming the option and the device.
    with pytest.raises(GraphError, match='--cpu-latency 0: not possible here') as refused:
        CpuLatencyRequest(0, device=str(tmp_path / 'missing' / 'cpu_dma_latency'))
    assert refused.value.exit_code == EXIT_USAGE
    stand_in = tmp_path / 'cpu_dma_latency'
    stand_in.write_bytes(b'')
    request = CpuLatencyRequest(25, device=str(stand_in))
    assert struct.unpack('i', stand_in.read_bytes()) == (25,)
    request.close()
    request.close()    # idempotent


def _skip_unless_permitted(scheduling: Scheduling) -> None:
    try:
        scheduling.check()
    except GraphError as err:
        pytest.skip(f'SCHED_FIFO not permitted here: {err}')


#: Python lines that start a thread and print its (policy, priority).
_PRINT_NEW_THREAD_POLICY = """
policies = []
thread = threading.Thread(target=lambda: policies.append(
    (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)))
thread.start(); thread.join()
print(policies[0], flush=True)
"""


def test_a_process_and_its_threads_run_at_the_requested_fifo_priority(tmp_path):
    scheduling = Scheduling(5)
    _skip_unless_permitted(scheduling)
    program = ('import os, sys, threading, time\n' + _PRINT_NEW_THREAD_POLICY
               + 'time.sleep(60)\n')
    process = NodeProcess('probe', [sys.executable, '-c', program], tmp_path / 'probe.log',
                          dict(os.environ), scheduling)
    try:
        # A thread the program started ...
        text = _wait_for(lambda: (tmp_path / 'probe.log').read_text().strip(), START_UP,
                         'the probe program prints its thread policy')
        assert text == f'({os.SCHED_FIFO}, 5)'
        # ... and the program itself (chrt execs it: the pid the launcher knows).
        assert os.sched_getscheduler(process.pid) == os.SCHED_FIFO
        assert os.sched_getparam(process.pid).sched_priority == 5
    finally:
        assert process.stop(5.0) is not None


def test_a_runaway_at_fifo_priority_is_killed_by_its_rt_cpu_limit(tmp_path):
    """A runaway thread at SCHED_FIFO is killed by its real-time CPU limit.

    A thread that spins at SCHED_FIFO without sleeping for longer than the limit is
    killed by the kernel (RLIMIT_RTTIME) instead of starving the machine below it.
    """
    scheduling = Scheduling(5, rt_cpu_limit=0.3)
    _skip_unless_permitted(scheduling)
    process = NodeProcess('spinner', [sys.executable, '-c', 'while True: pass'],
                          tmp_path / 'spinner.log', dict(os.environ), scheduling)
    try:
        _wait_for(lambda: process.poll() is not None, START_UP, 'the spinner is killed')
        assert process.returncode in (-signal.SIGKILL, -signal.SIGXCPU)
    finally:
        process.stop(1.0)


def _task_policies(pid: int) -> list[tuple[int, int]]:
    """(policy, rt priority) of every thread of ``pid`` (proc(5) stat fields 41 and 40)."""
    policies = []
    for tid in os.listdir(f'/proc/{pid}/task'):
        with open(f'/proc/{pid}/task/{tid}/stat', encoding='ascii') as stream:
            fields = stream.read().rsplit(')', 1)[1].split()
        policies.append((int(fields[38]), int(fields[37])))
    return policies


def test_the_priority_is_raised_on_the_running_process_its_threads_and_their_children(
        tmp_path):
    """The priority is raised on the running process, its threads and their children.

    The launcher starts the controllers at the normal policy (their imports and DDS
    start-up must not starve the other processes) and raises them once every node is up:
    every thread then, and a thread started afterwards, runs at SCHED_FIFO with the
    RLIMIT_RTTIME; a process that refuses is a GraphError naming it.
    """
    scheduling = Scheduling(5, rt_cpu_limit=2.0)
    _skip_unless_permitted(scheduling)
    assert scheduling.at_start() == Scheduling()     # the CPUs only (none here)
    go = tmp_path / 'go'
    log = tmp_path / 'probe.log'
    program = (textwrap.dedent(f"""
        import os, pathlib, sys, threading, time
        threading.Thread(target=time.sleep, args=(60,), daemon=True).start()
        print('up', flush=True)
        while not pathlib.Path({str(go)!r}).exists():   # the launcher raises the priority
            time.sleep(0.01)
    """) + _PRINT_NEW_THREAD_POLICY + 'time.sleep(60)\n')
    node = NodeProcess('probe', [sys.executable, '-c', program], log, dict(os.environ),
                       scheduling.at_start())
    try:
        _wait_for(lambda: log.read_text().strip() == 'up', START_UP, 'the probe is up')
        assert {policy for policy, _ in _task_policies(node.pid)} == {os.SCHED_OTHER}
        node.raise_priority(scheduling)
        assert set(_task_policies(node.pid)) == {(os.SCHED_FIFO, 5)}
        with open(f'/proc/{node.pid}/limits', encoding='ascii') as stream:
            assert any(line.startswith('Max realtime timeout') and '2000000' in line
                       for line in stream)
        go.touch()      # one more thread, started after the raise
        text = _wait_for(lambda: log.read_text().split()[1:], START_UP,
                         "the probe prints its new thread's policy")
        assert ' '.join(text) == f'({os.SCHED_FIFO}, 5)'
    finally:
        node.stop(1.0)
    with pytest.raises(GraphError, match='probe: could not set --rt-priority 5'):
        node.raise_priority(scheduling)          # the process is gone


LAUNCHER = textwrap.dedent("""
    import pathlib, sys, time
    from wip_bringup.processes import graph_environment, NodeProcess
    out = pathlib.Path(sys.argv[1])
    node = NodeProcess('child', sys.argv[2:], out / 'child.log', graph_environment(7))
    # Written whole, then renamed: the test polls for the file and reads it at once.
    (out / 'child.pid.tmp').write_text(str(node.pid))
    (out / 'child.pid.tmp').rename(out / 'child.pid')
    time.sleep(600)
""")


def _start_launcher(tmp_path, child_command):
    return subprocess.Popen([sys.executable, '-c', LAUNCHER, str(tmp_path), *child_command],
                            stdin=subprocess.DEVNULL)


def test_a_child_ends_with_its_launcher_killed_by_sigkill(tmp_path):
    program = textwrap.dedent(f"""
        import signal, sys, time
        from wip_runtime.launched import end_with_launcher
        def stop(signum, frame):
            open({str(tmp_path / 'stopped')!r}, 'w').write(str(signum)); sys.exit(0)
        signal.signal(signal.SIGINT, stop)
        assert end_with_launcher()
        open({str(tmp_path / 'armed')!r}, 'w').write('1')
        time.sleep(600)
    """)
    launcher = _start_launcher(tmp_path, [sys.executable, '-c', program])
    try:
        _wait_for(lambda: (tmp_path / 'armed').exists(), START_UP, 'the child arms')
        child = int((tmp_path / 'child.pid').read_text())
        launcher.kill()
        launcher.wait(timeout=30)
        _wait_for(lambda: not _alive(child), 30.0, 'the child ends after its launcher')
        assert (tmp_path / 'stopped').read_text() == str(int(signal.SIGINT))
    finally:
        if launcher.poll() is None:
            launcher.kill()


@pytest.mark.ros
def test_a_controller_node_ends_with_its_launcher_killed_by_sigkill(tmp_path):
    pytest.importorskip('rclpy')
    launcher = _start_launcher(tmp_path, [str(executable_path('wip_control', 'reference'))])
    try:
        pid_file = tmp_path / 'child.pid'
        _wait_for(pid_file.exists, START_UP, 'the launcher starts the node')
        child = int(pid_file.read_text())
        _wait_for(lambda: _alive(child) and (tmp_path / 'child.log').exists(), START_UP,
                  'the node runs')
        time.sleep(2.0)   # into rclpy's spin loop, or still starting: either must end
        assert _alive(child), (tmp_path / 'child.log').read_text()
        launcher.kill()
        launcher.wait(timeout=30)
        _wait_for(lambda: not _alive(child), 60.0, 'the reference node ends after its '
                  'launcher was killed')
    finally:
        if launcher.poll() is None:
            launcher.kill()
        try:
            os.kill(int((tmp_path / 'child.pid').read_text()), signal.SIGKILL)
        except (OSError, ValueError):
            pass


def test_a_zombie_launcher_is_gone_and_stops_the_start():
    """A zombie launcher counts as gone and stops the node's start.

    A launcher killed while its node starts is a zombie until reaped: signal 0 still
    reaches it, but the node must not take it for a live launcher (it would run on,
    orphaned, believing itself a grandchild).
    """
    zombie = subprocess.Popen([sys.executable, '-c', 'pass'])
    stat = pathlib.Path(f'/proc/{zombie.pid}/stat')
    _wait_for(lambda: stat.read_text().rsplit(')', 1)[1].split()[0] == 'Z', START_UP,
              'the child becomes a zombie')
    try:
        os.kill(zombie.pid, 0)            # signal 0 reaches a zombie
        with pytest.raises(SystemExit, match=f'launcher \\(pid {zombie.pid}\\) is gone'):
            end_with_launcher({LAUNCHER_PID_VARIABLE: str(zombie.pid)})
    finally:
        zombie.wait()


def test_without_the_variable_nothing_is_arranged_and_a_dead_launcher_stops_the_start():
    assert end_with_launcher({}) is False
    assert end_with_launcher({LAUNCHER_PID_VARIABLE: 'not a pid'}) is False
    # Alive but not this process's parent: an inherited variable, nothing to do.
    assert end_with_launcher({LAUNCHER_PID_VARIABLE: str(os.getpid())}) is False
    dead = subprocess.Popen([sys.executable, '-c', 'pass'])
    dead.wait()
    with pytest.raises(SystemExit, match=f'launcher \\(pid {dead.pid}\\) is gone'):
        end_with_launcher({LAUNCHER_PID_VARIABLE: str(dead.pid)})


def test_graph_environment_names_this_process_as_the_launcher():
    assert graph_environment(3)[LAUNCHER_PID_VARIABLE] == str(os.getpid())
