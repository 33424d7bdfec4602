"""Trajectory generator node: desired velocities (υd, ωd, ω̇d) of eq. (9) in [1]_.

Topics
------
Subscribes ``/wip/reference`` (wip_msgs/ReferenceState) and ``/wip/state_estimate``
(wip_msgs/StateEstimate: x̂, ŷ, ϕ̂). Publishes ``/wip/velocity_command``
(wip_msgs/VelocityCommand) stamped like the estimate, and ``/diagnostics``.

Per sample: the guidance stage of the loop, ``core.control_step.TrajectoryGeneratorStage`` (the
generator ``core.trajectory_generator.TrajectoryGenerator``: body-frame errors, saturated
(9), filtered ω̇d), as the runner's ``ControlStep``.

Obstacles: while the estimate says ``obstacle_blocked``, the stage refuses to push on
(``core.obstacle_refusal``, parameter ``trajectory_generator.obstacle_back_off``): it backs
off and holds until the reference no longer leads past the obstacle; /diagnostics is then
a WARN that says where, why and what resumes it.

Synchronisation: lockstep: estimate(t_k) + reference(t_k); realtime: on each estimate,
with the latest reference. Malformed or non-finite input is dropped and reported; so is
input whose command overflows (a non-finite command is never published, and the
generator's filter state is restored).

Parameters: section ``trajectory_generator`` (changeable at run time: the gains and
limits apply from the next sample), ``clock_mode``, ``diagnostics_period``.

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016.
"""

from __future__ import annotations

import sys
import time

from wip_msgs.msg import (ReferenceState as ReferenceStateMsg,
                          StateEstimate as StateEstimateMsg,
                          VelocityCommand as VelocityCommandMsg)

from ..core.control_step import TrajectoryGeneratorStage
from ..core.obstacle_refusal import make_refusal
from ..core.position import TRACKING
from ..core.reference_state import ReferenceState
from ..core.state_estimation import PoseEstimate
from ..core.trajectory_generator import TrajectoryGeneratorParams, VelocityCommand
from .common import ControllerNode
from wip_runtime.node_main import run_node
from wip_runtime.qos import RELIABLE_QOS
from .conversions import (checked_estimate, checked_reference, command_to_msg,
                          estimate_from_msg, reference_from_msg)
from wip_runtime.diagnostics import OK, WARN
from wip_runtime.parameters import RosParams
from wip_runtime.sync import ExactTimeSync, LatestSync

_INPUTS = ('reference', 'state_estimate')


class TrajectoryGeneratorNode(ControllerNode):
    """See the module docstring."""

    def __init__(self, **kwargs) -> None:
        super().__init__('trajectory_generator', 'saturated trajectory generator (9)',
                         _INPUTS, **kwargs)
        self.parameters = RosParams(self, 'trajectory_generator',
                                           TrajectoryGeneratorParams, self._on_config)
        # The guidance stage of the loop (core/control_step.py).
        self.stage = TrajectoryGeneratorStage(self.parameters.config)
        self.generator = self.stage.generator
        if self.lockstep:
            self.sync = ExactTimeSync(_INPUTS, self._compute)
        else:
            self.sync = LatestSync(_INPUTS, self._compute, triggers=('state_estimate',),
                                   required=('reference',))
        self.publisher = self.create_publisher(VelocityCommandMsg, 'wip/velocity_command',
                                               RELIABLE_QOS, direct_type=VelocityCommand)
        self.subscribe_input(ReferenceStateMsg, 'wip/reference', 'reference',
                             reference_from_msg, check=checked_reference,
                             value_type=ReferenceState)
        self.subscribe_input(StateEstimateMsg, 'wip/state_estimate', 'state_estimate',
                             estimate_from_msg, check=checked_estimate,
                             value_type=PoseEstimate)
        self._ticked: tuple | None = None   # the last tick's refusal and saturation flags
        self._counted = None                # the refusal of the last tick that had one
        self.diagnostics.reporters.append(self._report_state)

    def _on_config(self, config: TrajectoryGeneratorParams) -> None:
        old = self.generator.config
        self.generator.config = config
        if (config.obstacle_back_off, config.obstacle_refuse_delay) != (
                old.obstacle_back_off, old.obstacle_refuse_delay):
            # New refusal settings take effect at the next blocking.
            self.stage.refusal = make_refusal(config)

    def _compute(self, stamp: int, values) -> None:
        start = time.perf_counter()
        pose = values['state_estimate']
        # An overflow raises (ControlOverflow, a ValueError: the input is dropped and
        # reported) with the generator's state kept.
        command = self.stage.step(self.time_base.seconds(stamp), values['reference'],
                                  pose.x, pose.y, pose.estimate.phi, pose.obstacle_blocked,
                                  pose.position_status == TRACKING)
        self.publisher.publish_value(stamp, command, command_to_msg)
        self.diagnostics.output(stamp, time.perf_counter() - start)
        # What the status says is made once per status (_report_state), from what this
        # tick leaves: the refusal in force and the saturation flags (a later failed step
        # may change the flags, a new setting the refusal).
        generator, refusal = self.generator, self.stage.refusal
        self._ticked = (refusal, generator.saturated_speed, generator.saturated_yaw_rate)
        if refusal is not None:
            self._counted = refusal

    def _report_state(self) -> None:
        """Why the generator commands what it commands, as of its last tick."""
        if self._counted is not None:
            # Only a tick changes a refusal's count; one replaced by new settings keeps it.
            self.diagnostics.values['obstacle refusals'] = str(self._counted.refusals)
        if self._ticked is None:
            return
        refusal, speed, yaw_rate = self._ticked
        if refusal is not None and refusal.refusing:
            self.diagnostics.state(WARN, refusal.reason())
            return
        limits = [name for name, on in (('v_d', speed), ('omega_d', yaw_rate)) if on]
        self.diagnostics.state(OK, f'{" and ".join(limits)} saturated' if limits
                               else 'tracking, commands within limits')


def main(args=None) -> int:
    """Entry point ``trajectory_generator``."""
    return run_node(TrajectoryGeneratorNode, 'trajectory_generator', args)


if __name__ == '__main__':
    sys.exit(main())
