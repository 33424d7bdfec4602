"""The ROS network of a tool, its errors and namespaces: light enough for a fast start.

No rclpy, numpy or node code: ``scripts/estop`` imports this and must reach a robot within a
second of the command (docs/real-base.md, "E-stop"); :mod:`wip_bringup.launcher` re-exports
every name.
"""

from __future__ import annotations

import dataclasses
import os
import re
from typing import Mapping, MutableMapping

from wip_runtime.cli import EXIT_INTERNAL as EXIT_FAILED, EXIT_USAGE


class GraphError(Exception):
    """The graph could not be started or did not run to its end; ``exit_code`` says how."""

    def __init__(self, message: str, exit_code: int = EXIT_FAILED) -> None:
        super().__init__(message)
        self.exit_code = exit_code


#: A ROS namespace: tokens of letters, digits and underscores, none starting with a digit
#: (rcl's rules; '~' and substitutions have no meaning for a namespace given here).
_NAMESPACE = re.compile(r'/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*')


def parse_namespace(text: str | None) -> str:
    """Parse ``--namespace``.

    ``--namespace``: '' (none) or an absolute namespace ('robot1' -> '/robot1');
    GraphError (usage) if it is not a valid ROS namespace.
    """
    if text is None or text in ('', '/'):
        return ''
    if not _NAMESPACE.fullmatch(text):
        raise GraphError(f'--namespace: {text!r} is not a valid ROS namespace (letters, '
                         'digits and _ separated by /, no token starting with a digit)',
                         EXIT_USAGE)
    return '/' + text.lstrip('/')


#: Set by scripts/_env.sh: the ROS variables it gave a private default ("NAME=VALUE ..."), so
#: that the tools that talk to a real robot can tell them from the user's own settings.
ROS_DEFAULTS_VARIABLE = 'WIP_ROS_DEFAULTS'
_PRIVATE_DEFAULTS = ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE')


@dataclasses.dataclass(frozen=True)
class RosNetwork:
    """The DDS domain and discovery settings a process uses (ROS's defaults where unset)."""

    domain_id: int
    discovery_range: str
    static_peers: str

    def describe(self) -> str:
        peers = f', ROS_STATIC_PEERS={self.static_peers}' if self.static_peers else ''
        return (f'ROS_DOMAIN_ID={self.domain_id}, ROS_AUTOMATIC_DISCOVERY_RANGE='
                f'{self.discovery_range}{peers}')


def ros_network(environ: Mapping[str, str] | None = None) -> RosNetwork:
    """Return the ROS network settings of ``environ`` (default ``os.environ``).

    Where a setting is unset, ROS's own default: domain 0, discovery range SUBNET.
    """
    environ = os.environ if environ is None else environ
    value = environ.get('ROS_DOMAIN_ID', '').strip()
    try:
        domain_id = int(value) if value else 0
    except ValueError as err:
        raise GraphError(f'ROS_DOMAIN_ID={value!r} is not an integer', EXIT_USAGE) from err
    return RosNetwork(domain_id,
                      environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').strip() or 'SUBNET',
                      environ.get('ROS_STATIC_PEERS', '').strip())


def use_user_ros_environment(environ: MutableMapping[str, str] | None = None) -> RosNetwork:
    """Drop the private domain and localhost-only discovery of scripts/_env.sh.

    Drop from ``environ`` (default ``os.environ``) the private domain and localhost-only
    discovery that scripts/_env.sh set where the user had none (a robot's base is on the
    user's domain, on the network), keeping every value the user set; return the settings
    then in force. For hardware mode and check_base; simulations keep their private ones.
    """
    environ = os.environ if environ is None else environ
    for item in environ.pop(ROS_DEFAULTS_VARIABLE, '').split():
        name, _, value = item.partition('=')
        # A value changed since (by the user, a test harness) is not ours to drop.
        if name in _PRIVATE_DEFAULTS and environ.get(name) == value:
            del environ[name]
    return ros_network(environ)
