"""The test harness itself: a child process that hangs is reported with its stacks."""

import subprocess
import sys

import pytest

from ros_harness import communicate


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
