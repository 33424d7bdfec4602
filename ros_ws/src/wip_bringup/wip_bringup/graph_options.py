"""What a run of ``scripts/run_graph`` is given and what it returns.

The options (``scripts/run_graph --help``), the result (``OUT/run.json``) and the start-up
stall (docs/run_graph.md).
"""

from __future__ import annotations

import dataclasses
from typing import Any

from wip_sim.core.scenario import Scenario

from .launcher import EXIT_TIMEOUT, GraphError
from .run_result import RunResult
from .scheduling import Scheduling


class StartupStall(GraphError):
    """The run stalled on its first ticks.

    A message published before its subscription was matched is lost (see :meth:`GraphRunner.run`).
    """

    def __init__(self, message: str) -> None:
        super().__init__(message, EXIT_TIMEOUT)


@dataclasses.dataclass
class GraphOptions:
    """Arguments of :func:`run_graph` (see ``scripts/run_graph --help``)."""

    scenario: str | None = None
    clock: str = 'lockstep'
    record: str | None = None
    duration: float | None = None
    out: str = 'out/graph'
    discovery_timeout: float = 60.0  # [s] wall: processes started -> graph complete
    stall_timeout: float = 30.0  # [s] wall without simulated-time progress
    startup_retries: int = 1  # new attempts after a stall on the first ticks
    quiet: bool = False
    layout: str = 'composed'  # see LAYOUTS
    scheduling: Scheduling = Scheduling()  # of the controller processes
    #: The viewer node (Odometry, Path, markers; recorded). None: when someone will look,
    #: i.e. with --record or --foxglove (it costs the lockstep run about a quarter of its
    #: speed on 2 cores: docs/viewing.md).
    viewer: bool | None = None
    foxglove_port: int | None = None  # serve the topics to Foxglove on this port
    foxglove_host: str = '127.0.0.1'
    #: ROS namespace of every node and topic of the run ('' none; e.g. 'robot1'): two
    #: vehicles in one domain (--namespace).
    namespace: str = ''


@dataclasses.dataclass
class GraphResult(RunResult):
    """What :func:`run_graph` returns (also written to ``OUT/run.json``).

    ``cpu_s`` of the plant from its own stats, ``timeline`` with the plant's refusals to start.
    """

    scenario: Scenario | None = None
    plant_stats: dict | None = None
    #: topic -> 'received/expected' when the recorder lacked messages at the end.
    recorder_shortfall: dict[str, str] = dataclasses.field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        stats = self.plant_stats or {}
        return {**super().summary(),
                'scenario': self.scenario.name if self.scenario else None,
                'sim_time_s': stats.get('sim_time_s'),
                'real_time_factor': stats.get('real_time_factor'),
                'recorder_shortfall': self.recorder_shortfall,
                'plant_stats': self.plant_stats}
