"""The real-time mixer's watchdog in a composed process: its deadline after a chain.

The yaw torque that ends a chain carries its sensor sample's stamp. Adopted by the spin
loop, the watchdog's next call is due ``CHAIN_GRACE`` periods after a period from that
sample, however late the chain ended, and never less than a period after the command
(``CHAIN_GRACE`` 0: a period after the command, docs/realtime.md §2).
"""

import time

import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('wip_msgs.msg')

from wip_msgs.msg import YawTorque  # noqa: E402

from wip_runtime.executors import adopt_watchdogs  # noqa: E402
from wip_runtime.stamps import make_header  # noqa: E402
from wip_control.nodes.torque_mixer_node import CHAIN_GRACE, TorqueMixerNode  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def mixer(context):
    node = TorqueMixerNode(context=context)
    adopt_watchdogs([node])
    yield node
    node.destroy_node()


@pytest.mark.parametrize('chain_latency', [0.2, 0.9])   # [control periods]
def test_the_watchdog_is_due_a_period_after_the_command_or_the_grace_after_the_sample(
        mixer, chain_latency):
    assert not mixer.lockstep
    period = mixer.control_period
    msg = YawTorque(tau_omega=0.1)
    before = time.monotonic()
    sample = before - chain_latency * period
    msg.header = make_header(time.time_ns() - round(chain_latency * period * 1e9), '')
    mixer._on_yaw(msg)
    after = time.monotonic()
    due = mixer.watchdog.due
    if chain_latency < CHAIN_GRACE:
        # The grace after a period from the sample (clocks read within the tolerance).
        assert due == pytest.approx(sample + (1.0 + CHAIN_GRACE) * period, abs=0.2e-3)
    else:
        assert before + period <= due <= after + period   # a period after the command
