"""The test harness itself: a child process that hangs is reported with its stacks."""

import os
import pathlib
import subprocess
import sys

import pytest

from ros_harness import communicate

PROBE = pathlib.Path(__file__).with_name('session_domain_probe.py')


def test_a_hanging_child_is_ended_with_its_python_stack_in_the_failure():
    # What the SIGINT contract test needs when an executable does not exit: where it hangs.
    child = subprocess.Popen(
        [sys.executable, '-c', 'import time\ndef wait_forever():\n    time.sleep(600)\n'
         'wait_forever()\n'], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    with pytest.raises(pytest.fail.Exception) as failure:
        communicate(child, 0.5, 'stop')
    assert child.returncode is not None
    message = str(failure.value)
    assert 'did not stop within 0.5 s' in message
    assert 'in wait_forever' in message, message   # faulthandler's dump of the main thread


def test_each_xdist_worker_has_a_dds_domain_of_its_own(tmp_path):
    # scripts/test runs the CPU-bound tests on two workers: graphs started without a domain
    # fixture use the session's domain, which must not be shared by the two workers.
    probe = tmp_path / 'domains.txt'
    env = dict(os.environ, WIP_DOMAIN_PROBE=str(probe))
    done = subprocess.run([sys.executable, '-m', 'pytest', '-p', 'no:cacheprovider', '-q',
                           '-n', '2', '--dist', 'load', str(PROBE)], env=env,
                          capture_output=True, text=True, timeout=300, cwd=PROBE.parents[1])
    assert done.returncode == 0, done.stdout + done.stderr
    domains = {}
    for line in probe.read_text().splitlines():
        worker, domain = line.split()
        domains.setdefault(worker, set()).add(domain)
    assert set(domains) == {'gw0', 'gw1'}, domains          # both workers ran tests
    assert all(len(d) == 1 for d in domains.values()), domains
    assert domains['gw0'] != domains['gw1'], domains
