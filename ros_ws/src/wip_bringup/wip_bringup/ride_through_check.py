"""One ride-through rule for the MPC node and the torque mixer, checked before a run starts.

Both nodes judge an input's lateness by ``wip_control.core.safety_config.lateness`` with the
values ``safety.max_estimate_age`` and ``safety.bridge_time``: the mixer to bridge or zero its
torque, the MPC to hold its tick or report INPUT_INVALID. Each node reads them from its own
params-file sections (its name's, ``/**``), so a file that sets them in one node's section
only gives the graph two rules: the MPC would call an input stale that the mixer still
bridges, or hold its ticks while the mixer has already cut the torque
(docs/decisions/safety-layer.md). Each node run alone (``ros2 run``) is not checked: it has
no peer.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from wip_control.nodes.settings import SafetyRideThrough

#: The two nodes that share the rule.
SHARING_NODES = ('mpc', 'torque_mixer')
#: The shared values, as the nodes name them.
RIDE_THROUGH = tuple(f'safety.{field.name}' for field in dataclasses.fields(SafetyRideThrough))


@dataclasses.dataclass(frozen=True)
class Setting:
    """The value one node would run with, and where it comes from (for the message)."""

    value: Any
    source: str   # 'default', or the params file and section that set it last


def ride_through_mismatch(settings: Mapping[str, Mapping[str, Setting]]) -> str | None:
    """Return one line naming the first ride-through value the two nodes would hold apart.

    ``settings``: node -> {parameter name -> :class:`Setting`} for the nodes of the run
    (the rule is checked only when both :data:`SHARING_NODES` run). None when they agree.
    """
    if not all(node in settings for node in SHARING_NODES):
        return None
    first, second = SHARING_NODES
    for name in RIDE_THROUGH:
        a, b = settings[first][name], settings[second][name]
        if float(a.value) != float(b.value):
            return (f'{name}: {first} {a.value:g} s ({a.source}) but {second} {b.value:g} s '
                    f'({b.source}): the two nodes share one lateness rule; set '
                    f'{" and ".join(RIDE_THROUGH)} in a /** section or in both sections')
    return None
