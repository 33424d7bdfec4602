"""The live view of a run: the viewer node, the Foxglove bridge and their options."""

from __future__ import annotations

import argparse
import re

from .processes import NodeProcess


def viewer_wanted(options) -> bool:
    """Whether the viewer runs.

    ``options.viewer`` if set, else whether anyone will see its topics (a bag is
    recorded or the live view is served).
    """
    if options.viewer is not None:
        return bool(options.viewer)
    return options.record is not None or options.foxglove_port is not None


def live_view_line(bridge: NodeProcess, host: str, port: int | None) -> str:
    """Where the live view is: the URL the bridge printed (with port 0, the port it got)."""
    match = re.search(r'foxglove_bridge: serving (ws://\S+)', bridge.log_tail(200))
    url = match.group(1) if match else f'ws://{host}:{port}'
    return (f'live view: open {url} in Foxglove (Open connection, Foxglove WebSocket; '
            'layout foxglove/wip_live.json)')


FOXGLOVE_PORT = 8765  # Foxglove's default WebSocket port


def foxglove_port(text: str) -> int:
    """Parse --foxglove (an argparse type): a TCP port, 0..65535."""
    try:
        port = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a port number') from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f'{port} is not in 0..65535')
    return port


def add_view_arguments(parser: argparse.ArgumentParser) -> None:
    """--foxglove [PORT], --foxglove-host, --viewer/--no-viewer (simulation and hardware mode)."""
    parser.add_argument('--foxglove', nargs='?', type=foxglove_port, const=FOXGLOVE_PORT,
                        default=None, metavar='PORT',
                        help="serve the graph's topics live over the Foxglove WebSocket "
                        f'protocol on PORT (default {FOXGLOVE_PORT}; 0 = any free port), '
                        'with the e-stop services /wip/estop/{engage,release,reset}')
    parser.add_argument('--foxglove-host', default='127.0.0.1', metavar='ADDRESS',
                        help='address of the Foxglove server (default 127.0.0.1: this '
                        'machine only; 0.0.0.0 serves the network)')
    parser.add_argument('--viewer', action=argparse.BooleanOptionalAction, default=None,
                        help='the viewer node (Odometry, Path, markers for 3-D viewers); '
                        'default: on with --record or --foxglove, else off')
