"""Torque mixer node: wheel torques from (τυ, τω), eq. (24) in [1]_, REP 103 signs.

Topics
------
Subscribes ``/wip/yaw_torque`` (wip_msgs/ArcState: τω) and ``/wip/drive_torque``
(wip_msgs/MpcOutput: τυ, held between MPC ticks). Publishes ``/wip/wheel_torques``
(wip_msgs/WheelTorques) stamped like the yaw torque, the same command as
``/effort_controller/commands`` (std_msgs/Float64MultiArray, one effort per joint in the
order of the ``joints`` parameter, for a ros2_control JointGroupEffortController), and
``/diagnostics``.

Per sample: ``core.mixer.mix(τυ, τω, mixer.max_wheel_torque)`` (the runner's step 7): yaw
first, then the drive torque within 2 τmax − |τω|, each wheel within ±τmax.

Safety (a first part of the safety layer; stale inputs, e-stop, tilt limit and the torque
rate limit are a later issue): a non-finite τω or τυ gives zero torque on both wheels with
``zeroed = true`` and the reason; a message is published for the sample all the same, so
a lockstep plant never waits forever. Before the first drive torque τυ = 0.

Synchronisation: lockstep: yaw_torque(t_k), plus drive_torque(t_k) when t_k is an MPC
tick (k = round(t_k / h) a multiple of round(``mpc_period`` / h), h = 1/``rates.control_rate``,
from t = 0, as in the runner), else the drive torque of the last tick; realtime: on each
yaw torque, with the latest drive torque.

Parameters: section ``mixer`` (changeable at run time), section ``rates`` (read-only),
``mpc_period`` [s], ``joints``, ``left_joint``, ``right_joint``, ``clock_mode``,
``diagnostics_period``.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import sys
import time

from std_msgs.msg import Float64MultiArray
from wip_msgs.msg import ArcState, MpcOutput, WheelTorques

from ..core.config import ConfigError
from ..core.mixer import MixerConfig, mix
from ..core.mpc import MpcConfig
from ..core.scenario import RatesConfig
from .common import ControllerNode, finite, RELIABLE_QOS, run_node, stamp_to_ns
from .conversions import effort_command, wheel_torques_to_msg
from .diagnostics import OK, WARN
from .parameters import ConfigParameters, declare_plain
from .sync import decimation, ExactTimeSync, is_decimated_tick, LatestSync

_INPUTS = ('yaw_torque', 'drive_torque')


class TorqueMixerNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('torque_mixer', 'torque mixer (24) and safety', _INPUTS, **kwargs)
        self.parameters = ConfigParameters(self, 'mixer', MixerConfig, self._on_config)
        self.mixer = self.parameters.config
        self.rates = ConfigParameters(self, 'rates', RatesConfig).config
        self.mpc_period = declare_plain(self, 'mpc_period', MpcConfig().sampling_period, 's',
                                        'MPC sampling period: in lockstep a drive torque '
                                        'is awaited at every MPC tick')
        if not (isinstance(self.mpc_period, float) and self.mpc_period > 0.0):
            raise ConfigError(f'mpc_period: must be > 0, got {self.mpc_period!r}')
        self.left_joint = declare_plain(self, 'left_joint', 'left_wheel_joint', '',
                                        'name of the left wheel joint')
        self.right_joint = declare_plain(self, 'right_joint', 'right_wheel_joint', '',
                                         'name of the right wheel joint')
        self.joints = list(declare_plain(
            self, 'joints', [self.left_joint, self.right_joint], '',
            'joints of /effort_controller/commands, in the order of its data'))
        if sorted(self.joints) != sorted([self.left_joint, self.right_joint]):
            raise ConfigError(f'joints: must list left_joint {self.left_joint!r} and '
                              f'right_joint {self.right_joint!r} once each, got {self.joints}')
        self.control_period = 1.0 / self.rates.control_rate
        self.every = decimation(self.mpc_period, self.control_period)
        self.held_drive = 0.0
        self.torques_publisher = self.create_publisher(WheelTorques, '/wip/wheel_torques',
                                                       RELIABLE_QOS)
        self.effort_publisher = self.create_publisher(
            Float64MultiArray, '/effort_controller/commands', RELIABLE_QOS)
        if self.lockstep:
            self.sync = ExactTimeSync(_INPUTS, self._mix, required=self._required)
        else:
            self.sync = LatestSync(_INPUTS, self._mix, triggers=('yaw_torque',))
        self.subscribe(ArcState, '/wip/yaw_torque', 'yaw_torque', self._on_yaw)
        self.subscribe(MpcOutput, '/wip/drive_torque', 'drive_torque', self._on_drive)
        self.diagnostics.state(OK, 'waiting for the first yaw torque')

    def _on_config(self, config: MixerConfig) -> None:
        self.mixer = config

    def is_tick(self, stamp_ns: int) -> bool:
        """Whether ``stamp_ns`` is an MPC tick of the lockstep grid (from t = 0)."""
        return is_decimated_tick(stamp_ns, self.control_period, self.every)

    def _required(self, stamp_ns: int) -> tuple[str, ...]:
        return _INPUTS if self.is_tick(stamp_ns) else ('yaw_torque',)

    def _on_yaw(self, msg: ArcState) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('yaw_torque', stamp)
        self.feed('yaw_torque', stamp, float(msg.tau_omega))

    def _on_drive(self, msg: MpcOutput) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        self.diagnostics.input('drive_torque', stamp)
        tau_v = float(msg.tau_v)
        if self.lockstep and not self.is_tick(stamp):
            # Not awaited at this stamp: hold it from now on (the MPC's period differs
            # from mpc_period, which /diagnostics reports).
            self.diagnostics.drop('drive_torque', 'off the MPC ticks',
                                  f'stamp {stamp} ns; held without synchronisation')
            self.held_drive = tau_v
            return
        self.feed('drive_torque', stamp, tau_v)

    def _mix(self, stamp: int, values) -> None:
        start = time.perf_counter()
        tau_omega = values['yaw_torque']
        if 'drive_torque' in values:
            self.held_drive = values['drive_torque']
        tau_v = self.held_drive
        reason = ''
        if not finite(tau_omega):
            reason = f'non-finite yaw torque {tau_omega!r}'
        elif not finite(tau_v):
            reason = f'non-finite drive torque {tau_v!r}'
        if reason:
            left = right = 0.0
        else:
            left, right = mix(tau_v, tau_omega, self.mixer.max_wheel_torque)
        self.torques_publisher.publish(wheel_torques_to_msg(left, right, stamp, bool(reason),
                                                            reason))
        self.effort_publisher.publish(effort_command(left, right, self.joints,
                                                     self.left_joint, self.right_joint))
        self.diagnostics.output(stamp, time.perf_counter() - start)
        if reason:
            self.diagnostics.state(WARN, f'zeroed: {reason}')
        else:
            limit = self.mixer.max_wheel_torque
            clipped = max(abs(left), abs(right)) >= limit
            self.diagnostics.state(OK, f'mixing; wheel torque at the {limit:g} N m limit'
                                   if clipped else 'mixing within the limits')


def main(args=None) -> int:
    """Entry point ``torque_mixer``."""
    return run_node(TorqueMixerNode, 'torque_mixer', args)


if __name__ == '__main__':
    sys.exit(main())
