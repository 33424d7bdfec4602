"""ARC node: adaptive robust yaw-rate control, eqs. (12), (13) in [1]_.

Topics
------
Subscribes ``/wip/velocity_command`` (ωd, ω̇d) and ``/wip/state_estimate`` (ω̂, f̂1).
Publishes ``/wip/yaw_torque`` (wip_msgs/YawTorque: τω, α̂, eω) stamped like the estimate,
and ``/diagnostics``.

Per sample: the yaw stage of the loop, ``core.control_step.YawControllerStage`` (the ARC
``core.arc.AdaptiveRobustYawController``, as the runner's ``ControlStep``), with dt the
control period 1/``rates.control_rate`` (the same nominal dt is
used in real time: the controller runs at the sensor rate).

Synchronisation: lockstep: command(t_k) + estimate(t_k); realtime: on each estimate, with
the latest command. Malformed or non-finite input is dropped and reported; so is input
whose result overflows (never published; α̂ is kept).

Parameters: section ``arc`` (changeable at run time; α̂ is kept, projected into the new
bounds), section ``rates`` (read-only), section ``model`` and ``eso.yaw_input_gain_scale``
(read-only: α̂(0) = 1/ĝ1 computed from them, ``core.control_step.initial_alpha``, as the
runner does), ``clock_mode``, ``diagnostics_period``.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import math
import sys
import time

from wip_msgs.msg import (YawTorque, StateEstimate as StateEstimateMsg,
                          VelocityCommand as VelocityCommandMsg)

from ..core.arc import ArcOutput, ArcParams
from ..core.control_step import YawControllerStage, initial_alpha
from wip_description.params import ModelParams
from ..core.controller_settings import RatesParams
from ..core.state_estimation import PoseEstimate
from ..core.trajectory_generator import VelocityCommand
from .common import ControllerNode
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from .conversions import (arc_to_msg, checked_command, checked_estimate, command_from_msg,
                          estimate_from_msg)
from wip_runtime.diagnostics import OK
from wip_runtime.parameters import RosParams
from .settings import YawInputGainScale
from wip_runtime.sync import ExactTimeSync, LatestSync

_INPUTS = ('velocity_command', 'state_estimate')


class ArcNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('arc', 'adaptive robust yaw control (12)-(13)', _INPUTS, **kwargs)
        self.parameters = RosParams(self, 'arc', ArcParams, self._on_config)
        self.rates = RosParams(self, 'rates', RatesParams).config
        model = RosParams(self, 'model', ModelParams).config
        scale = RosParams(self, 'eso', YawInputGainScale).config.yaw_input_gain_scale
        alpha_initial = initial_alpha(model, scale)
        self.dt = 1.0 / self.rates.control_rate
        # The yaw stage of the loop (core/control_step.py).
        self.stage = YawControllerStage(self.parameters.config, alpha_initial, self.dt)
        self.controller = self.stage.controller
        if self.lockstep:
            self.sync = ExactTimeSync(_INPUTS, self._compute)
        else:
            self.sync = LatestSync(_INPUTS, self._compute, triggers=('state_estimate',),
                                   required=('velocity_command',))
        self.publisher = self.create_publisher(YawTorque, 'wip/yaw_torque', RELIABLE_QOS,
                                               direct_type=ArcOutput)
        self.subscribe_input(VelocityCommandMsg, 'wip/velocity_command', 'velocity_command',
                             command_from_msg, check=checked_command,
                             value_type=VelocityCommand)
        self.subscribe_input(StateEstimateMsg, 'wip/state_estimate', 'state_estimate',
                             estimate_from_msg, check=checked_estimate,
                             value_type=PoseEstimate)
        self._ticked: tuple[float, float] | None = None   # the last tick's (τω, its limit)
        self.diagnostics.reporters.append(self._report_values)

    def _report_values(self) -> None:
        """Report α̂ and the last τω against its limit once per status (both change per tick)."""
        if self.diagnostics.outputs:
            self.diagnostics.values['alpha_hat [kg m^2]'] = f'{self.controller.alpha_hat:.6g}'
        if self._ticked is not None:
            tau_omega, limit = self._ticked
            self.diagnostics.state(OK, f'tau_omega saturated at {math.copysign(limit, tau_omega)}'
                                   ' N m' if abs(tau_omega) >= limit else 'tracking omega_d')

    def _on_config(self, config: ArcParams) -> None:
        self.controller.config = config
        self.controller.reset(self.controller.alpha_hat)  # Project into the new bounds.

    def _compute(self, stamp: int, values) -> None:
        start = time.perf_counter()
        estimate = values['state_estimate'].estimate
        command = values['velocity_command']
        # An overflow raises (ControlOverflow, a ValueError: the input is dropped and
        # reported) with alpha_hat kept.
        out = self.stage.step(estimate.omega, estimate.f1, command)
        self.publisher.publish_value(stamp, out, arc_to_msg)
        self.diagnostics.output(stamp, time.perf_counter() - start)
        # The status text is made once per status (_report_values), from this tick's torque
        # and the limit it was computed with (arc.max_yaw_torque may change at run time).
        self._ticked = (out.tau_omega, self.controller.config.max_yaw_torque)


def main(args=None) -> int:
    """Entry point ``arc``."""
    return run_node(ArcNode, 'arc', args)


if __name__ == '__main__':
    sys.exit(main())
