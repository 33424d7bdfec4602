"""The real-time mixer's watchdog in a composed process: its deadline after a chain.

Adopted by the spin loop, the watchdog's next call is due a period after the command that
a chain's yaw torque made, however late the chain ended after its sensor sample
(docs/realtime.md §2).
"""

import time

import pytest

rclpy = pytest.importorskip('rclpy')
pytest.importorskip('wip_msgs.msg')

from wip_msgs.msg import YawTorque  # noqa: E402

from wip_runtime.executors import adopt_watchdogs  # noqa: E402
from wip_runtime.stamps import make_header  # noqa: E402
from wip_control.nodes.torque_mixer_node import TorqueMixerNode  # noqa: E402

pytestmark = pytest.mark.ros


@pytest.fixture
def mixer(context):
    node = TorqueMixerNode(context=context)
    adopt_watchdogs([node])
    yield node
    node.destroy_node()


@pytest.mark.parametrize('chain_latency', [0.2, 0.9])   # [control periods]
def test_the_watchdog_is_due_a_period_after_the_command_however_late_the_chain(
        mixer, chain_latency):
    assert not mixer.lockstep
    period = mixer.control_period
    msg = YawTorque(tau_omega=0.1)
    msg.header = make_header(time.time_ns() - round(chain_latency * period * 1e9), '')
    before = time.monotonic()
    mixer._on_yaw(msg)
    after = time.monotonic()
    assert before + period <= mixer.watchdog.due <= after + period
