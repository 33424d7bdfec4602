"""A stop signal that native code turned into another error is still a stop.

A signal handler's exception raised while pybind11 converts a value (rclpy's take of a
message in ``spin_once``) comes out as ``RuntimeError: Unable to convert call argument``;
the run's stop must still be a stop (exit 128 + the signal, the bag finished), not an
internal error. The native call is stood in for by a function that turns the handler's
exception into that RuntimeError, as pybind11 does.
"""

import os
import signal
import time

import pytest

from wip_bringup.run_stop import StopRequested, stop_raised_in_native_code, stop_signals


def native_take(signum):
    """Receive ``signum`` inside a call that converts its exception, as pybind11 does."""
    try:
        os.kill(os.getpid(), signum)
        time.sleep(1.0)   # the handler raises at the next instruction
    except KeyboardInterrupt:
        raise RuntimeError("Unable to convert call argument '0' to Python object") from None
    raise AssertionError('the signal was not delivered within 1 s')


@pytest.mark.parametrize('signum', [signal.SIGTERM, signal.SIGHUP])
def test_a_stop_signal_turned_into_a_runtime_error_is_raised_as_the_stop(signum):
    with stop_signals():
        with pytest.raises(StopRequested) as caught:
            with stop_raised_in_native_code():
                native_take(signum)
    assert caught.value.signum == signum


def test_an_interrupt_turned_into_a_runtime_error_is_raised_as_keyboard_interrupt():
    with stop_signals():
        with pytest.raises(KeyboardInterrupt) as caught:
            with stop_raised_in_native_code():
                native_take(signal.SIGINT)
    assert not isinstance(caught.value, StopRequested)


def test_an_error_without_a_signal_is_left_as_it_is():
    with stop_signals():
        with pytest.raises(RuntimeError, match='Unable to convert'):
            with stop_raised_in_native_code():
                raise RuntimeError("Unable to convert call argument '0' to Python object")


def test_a_signal_received_before_the_block_does_not_turn_a_later_error_into_a_stop():
    with stop_signals():
        with pytest.raises(StopRequested):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)
        with pytest.raises(ValueError):
            with stop_raised_in_native_code():
                raise ValueError('a real failure')
