"""Parameters of the recorder and replayer nodes, and the registry of both.

Declared like every node parameter (:func:`wip_runtime.config.param`); no rclpy import,
so the parameter reference is generated from :data:`NODES`.
"""

from __future__ import annotations

import dataclasses

from wip_runtime.config import param, TEXT

from .bag_writer import COMPRESSION, DEFAULT_CHUNK_SIZE

#: Largest bag file size a split may ask for [bytes] (an exabyte: no real limit).
_LARGEST_BYTES = 2 ** 60


@dataclasses.dataclass(frozen=True)
class RecorderParams:
    """Parameters of the ``recorder`` node (``ros2 bag record`` replacement)."""

    output: str = param('', TEXT, 'bag directory to create (must not exist or be empty); '
                        'empty: rosbag2_YYYY_MM_DD-HH_MM_SS in the working directory')
    topics: tuple[str, ...] = param((), TEXT, 'topics to record; empty: all topics of the '
                                    'graph, also later ones')
    exclude: tuple[str, ...] = param((), TEXT, 'topics never recorded')
    compression: str = param('zstd', TEXT, 'MCAP chunk compression',
                             choices=tuple(COMPRESSION))
    discovery_period: float = param(1.0, 's', 'period of the graph polling for new topics '
                                    '(wall time)', minimum=0.0, exclusive_minimum=True,
                                    maximum=3600.0)
    flush_period: float = param(1.0, 's', 'maximum time between two flushes of the bag file '
                                '(wall time); 0: flush only at close', minimum=0.0,
                                maximum=3600.0)
    chunk_size: int = param(DEFAULT_CHUNK_SIZE, 'bytes', 'uncompressed MCAP chunk size',
                            minimum=1, maximum=2 ** 31)
    max_bag_size: int = param(0, 'bytes', 'split into files of at most this many bytes; 0: '
                              'no limit', minimum=0, maximum=_LARGEST_BYTES)
    max_bag_duration: float = param(0.0, 's', 'split into files of at most this long; 0: no '
                                    'limit', minimum=0.0, maximum=1e9)
    close_timeout: float = param(30.0, 's', 'longest wait at shutdown for the writer to '
                                 'close the bag', minimum=0.0, maximum=3600.0)
    scenario_file: str = param('', TEXT, 'scenario YAML stored in the bag metadata '
                               '(custom_data wip.scenario) for rerun; empty: none')


@dataclasses.dataclass(frozen=True)
class ReplayerParams:
    """Parameters of the ``replayer`` node (``ros2 bag play`` replacement)."""

    bag: str = param('', TEXT, 'bag directory or .mcap file to play (required)')
    rate: float = param(1.0, '1', 'playback speed factor', minimum=0.0,
                        exclusive_minimum=True, maximum=1e6)
    start_offset: float = param(0.0, 's', 'start this long after the first message',
                                minimum=0.0, maximum=1e9)
    duration: float = param(0.0, 's', 'play this long from the start point; 0: all',
                            minimum=0.0, maximum=1e9)
    loop: bool = param(False, '1', 'play again from the start point at the end')
    topics: tuple[str, ...] = param((), TEXT, 'topics to play; empty: all')
    exclude: tuple[str, ...] = param((), TEXT, 'topics never played')
    remap: tuple[str, ...] = param((), TEXT, "'from:=to' topic renames")
    clock: bool = param(False, '1', 'publish /clock with the recorded time')
    clock_rate: float = param(100.0, 'Hz', 'rate of /clock between messages; 0: only with '
                              'the messages', minimum=0.0, maximum=1e5)
    start_paused: bool = param(False, '1', 'start paused (see ~/pause)')
    wait_for_subscribers: int = param(0, '1', 'matched subscriptions each topic of '
                                      'wait_topics needs before playing', minimum=0,
                                      maximum=1000)
    wait_topics: tuple[str, ...] = param((), TEXT, 'topics whose subscriptions are awaited; '
                                         'empty: all played topics')
    wait_timeout: float = param(10.0, 's', 'longest wait for the subscribers', minimum=0.0,
                                maximum=1e5)
    delay: float = param(0.0, 's', 'wall-clock delay before playing', minimum=0.0,
                         maximum=1e5)
    qos_depth: int = param(1000, '1', 'keep-last depth of the publishers', minimum=1,
                           maximum=1000000)
    exit_when_done: bool = param(True, '1', 'exit at the end of the bag')
    partial: bool = param(False, '1', 'play the intact part of a damaged bag')


#: executable -> the (prefix, dataclass) groups it declares.
NODES: dict[str, tuple[tuple[str, type], ...]] = {
    'recorder': (('', RecorderParams),),
    'replay': (('', ReplayerParams),),
}
