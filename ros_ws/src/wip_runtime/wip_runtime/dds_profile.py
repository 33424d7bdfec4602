"""Whether this process's DDS participant matches its own endpoints (no rclpy import).

Fast DDS matches the readers and writers of one participant (one per process and context
under rmw_fastrtps) unless its participant property ``fastdds.ignore_local_endpoints`` is
true. The intra-process bus must know which: with the property, DDS never delivers a
message of this process to this process, so the bus delivers every local one
(:mod:`.intra_process`). The property comes from the XML profiles file that Fast DDS reads
at start-up (``FASTRTPS_DEFAULT_PROFILES_FILE``, else ``FASTDDS_DEFAULT_PROFILES_FILE``):
its default participant profile.
"""

from __future__ import annotations

import os
import pathlib
from typing import Mapping
import xml.etree.ElementTree as ElementTree

IGNORE_LOCAL_PROPERTY = 'fastdds.ignore_local_endpoints'
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
FAST_DDS_RMWS = ('rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp')
#: The Fast DDS profile of the node processes where the user has none of their own (in
#: none of :data:`PROFILE_VARIABLES`, Fast DDS 2's and 3's names): reliable writers'
#: heartbeats every 20 ms (the file says why).
FASTDDS_PROFILE = pathlib.Path(__file__).with_name('fastdds_profile.xml')
#: The Fast DDS profile of the launchers' own processes (the probe of run_graph and hardware
#: mode, the tests' processes) where the user has none: the participant announces itself
#: every 0.1 s, nothing else (the file says why).
LAUNCHER_PROFILE = pathlib.Path(__file__).with_name('fastdds_launcher_profile.xml')


def profile_file(environ: Mapping[str, str] = os.environ) -> str | None:
    """Return the profiles file Fast DDS reads in a process with ``environ``, or None.

    The first of :data:`PROFILE_VARIABLES` set.
    """
    return next((environ[name] for name in PROFILE_VARIABLES if environ.get(name)), None)


def user_profile(environ: Mapping[str, str] = os.environ) -> str | None:
    """Return the user's own Fast DDS profiles file, or None.

    :func:`profile_file`, unless it is :data:`LAUNCHER_PROFILE` (which a launcher set for
    itself and its children inherit: not the user's).
    """
    path = profile_file(environ)
    return None if path == str(LAUNCHER_PROFILE) else path


def use_node_profile(env: dict[str, str]) -> None:
    """Give a node process's environment :data:`FASTDDS_PROFILE` where the user has none."""
    if user_profile(env) is None:
        for name in PROFILE_VARIABLES:
            env.pop(name, None)
        env[PROFILE_VARIABLES[0]] = str(FASTDDS_PROFILE)


def use_launcher_profile(environ: dict[str, str] = os.environ) -> bool:
    """Give this process :data:`LAUNCHER_PROFILE` where the user has none; True if set.

    Fast DDS reads the file when the process makes its first participant: called before
    that, it applies to every participant of the process; after, to none (and the process
    keeps matching its own endpoints, as that file says: nothing depends on which).
    """
    if profile_file(environ) is not None:
        return False
    environ[PROFILE_VARIABLES[0]] = str(LAUNCHER_PROFILE)
    return True


def _local_name(tag: str) -> str:
    return tag.rsplit('}', 1)[-1]


def profile_ignores_local_endpoints(text: str) -> bool:
    """Return True if the default participant profile of ``text`` ignores local endpoints.

    ``text`` is a Fast DDS XML profiles document; an unreadable one counts as not setting
    the property (Fast DDS would not apply it either).
    """
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError:
        return False
    for participant in root.iter():
        if (_local_name(participant.tag) != 'participant'
                or participant.get('is_default_profile', '').lower() != 'true'):
            continue
        for prop in participant.iter():
            if _local_name(prop.tag) != 'property':
                continue
            fields = {_local_name(child.tag): (child.text or '').strip() for child in prop}
            if fields.get('name') == IGNORE_LOCAL_PROPERTY:
                # Fast DDS takes 'true' and 'false' only; another value is an error to it,
                # and the endpoints match.
                return fields.get('value') == 'true'
    return False


def process_ignores_local_endpoints(rmw_identifier: str,
                                    environ: Mapping[str, str] = os.environ) -> bool:
    """Return True if the participant of a process with ``environ`` ignores its endpoints."""
    if rmw_identifier not in FAST_DDS_RMWS:
        return False
    path = profile_file(environ)
    if path is None:
        return False
    try:
        with open(path, encoding='utf-8') as stream:
            return profile_ignores_local_endpoints(stream.read())
    except OSError:
        return False
