"""Message definitions and type hashes of installed ROS interfaces, as rosbag2 stores them.

rosbag2's MCAP storage keeps, per message type, a schema with the type's full definition
(``MessageDefinitionCache::get_full_text`` of [1]) and, per channel, the type's RIHS01
hash. Both are read here from the interface files that the message packages install
(``<prefix>/share/<pkg>/msg/<Type>.msg``, ``.idl`` and ``.json``), without rclpy.

References
----------
.. [1] ros2/rosbag2 (jazzy): rosbag2_storage_mcap/src/message_definition_cache.cpp.
"""

import functools
import json
import os
import pathlib
import re
import sys
from typing import NamedTuple

DEFINITION_DELIMITER = '=' * 80 + '\n'

# Type names 'pkg/Type', 'pkg/msg/Type' (PACKAGE_TYPENAME_REGEX of [1]).
_TYPE_NAME_RE = re.compile(r'^([a-zA-Z][a-zA-Z0-9_]*)/((?:msg|srv)/)?([a-zA-Z][a-zA-Z0-9_]*)$')
# Field types of a .msg file ('pkg/Type' in 'pkg/Type[] name'), MSG_FIELD_TYPE_REGEX of [1].
_MSG_FIELD_TYPE_RE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
# Included files of an .idl file, IDL_FIELD_TYPE_REGEX of [1].
_IDL_INCLUDE_RE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
# Built-in field types. [1] lists these without 'wstring'; a wstring field would send it
# looking for 'pkg/wstring' and fall back to IDL, so 'wstring' is added here.
PRIMITIVE_TYPES = frozenset((
    'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
    'int32', 'uint32', 'int64', 'uint64', 'string', 'wstring'))
_MAX_DEFINITION_DEPTH = 50  # MESSAGE_DEFINITION_SOURCE_MAX_RECURSION_DEPTH of [1]


class BagWriterError(Exception):
    """A bag cannot be written as asked."""


class MessageDefinitionError(BagWriterError, LookupError):
    """The interface files of a message type cannot be found or parsed."""


class MessageDefinition(NamedTuple):
    """Full message definition of a type as stored in an MCAP schema record."""

    encoding: str  # 'ros2msg' or 'ros2idl'
    text: str


def split_type_name(type_name):
    """Split ``pkg/msg/Type`` or ``pkg/Type`` into ``(package, namespace, name)``."""
    match = _TYPE_NAME_RE.match(type_name)
    if match is None:
        raise MessageDefinitionError(
            f'type name {type_name!r} is not of the form pkg/msg/Type or pkg/Type')
    return match.group(1), (match.group(2) or 'msg/').rstrip('/'), match.group(3)


def _share_directory(package):
    """Return the share directory of an installed ROS package.

    Looks the package up in the ament index (``AMENT_PREFIX_PATH``) and, when that variable
    is unset or misses the package, in this Python's prefix, where the ROS wheels from PyPI
    install their share directories.
    """
    try:
        from ament_index_python.packages import get_package_share_directory
        return pathlib.Path(get_package_share_directory(package))
    except (ImportError, LookupError, OSError, ValueError):
        pass
    candidate = pathlib.Path(sys.prefix) / 'share' / package
    marker = (pathlib.Path(sys.prefix) / 'share' / 'ament_index' / 'resource_index'
              / 'packages' / package)
    if marker.is_file() and candidate.is_dir():
        return candidate
    raise MessageDefinitionError(
        f'package {package!r} not found in the ament index '
        f'(AMENT_PREFIX_PATH={os.environ.get("AMENT_PREFIX_PATH", "")!r}) '
        f'nor in {sys.prefix}/share')


def interface_file(type_name, extension):
    """Return the path of an installed interface file of a type, e.g. its ``.msg``.

    Parameters
    ----------
    type_name : str
        ``pkg/msg/Type`` or ``pkg/Type``.
    extension : str
        '.msg', '.idl' or '.json'.

    Raises
    ------
    MessageDefinitionError
        If the package or the file is not installed.
    """
    package, namespace, name = split_type_name(type_name)
    path = _share_directory(package) / namespace / f'{name}{extension}'
    if not path.is_file():
        raise MessageDefinitionError(f'{type_name}: no {path}')
    return path


@functools.lru_cache(maxsize=None)
def _read_text(type_name, extension):
    return interface_file(type_name, extension).read_text(encoding='utf-8')


def _msg_dependencies(text, package):
    """Non-primitive field types of a .msg text, as 'pkg/Type', sorted like std::set."""
    dependencies = set()
    for match in _MSG_FIELD_TYPE_RE.finditer(text):
        field_type = match.group(1)
        if field_type in PRIMITIVE_TYPES:
            continue
        dependencies.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(dependencies)


def _idl_dependencies(text):
    return sorted(set(_IDL_INCLUDE_RE.findall(text)))


@functools.lru_cache(maxsize=None)
def message_definition(type_name):
    """Return the full definition of a message type in rosbag2's MCAP schema format.

    Like ``MessageDefinitionCache::get_full_text`` of [1]: the type's ``.msg`` file as
    installed, then each dependency once (depth first, dependencies of a type in sorted
    order), each preceded by a line of 80 '=' and a line ``MSG: pkg/Type``. When a ``.msg``
    file is missing, the same is done with ``.idl`` files (``IDL: pkg/msg/Type``), and the
    encoding is 'ros2idl'.

    Parameters
    ----------
    type_name : str
        ``pkg/msg/Type`` (or ``pkg/Type``).

    Returns
    -------
    MessageDefinition
        ``(encoding, text)``.

    Raises
    ------
    MessageDefinitionError
        If neither the .msg nor the .idl files of the type and its dependencies are found.
    """
    split_type_name(type_name)  # Validates the name first.
    try:
        return MessageDefinition('ros2msg', _full_text(type_name, '.msg'))
    except MessageDefinitionError as msg_error:
        try:
            text = _full_text(type_name, '.idl')
        except MessageDefinitionError:
            raise msg_error from None
        return MessageDefinition(
            'ros2idl', f'{DEFINITION_DELIMITER}IDL: {type_name}\n{text}')


def _full_text(root_type_name, extension):
    seen = set()
    label = 'MSG' if extension == '.msg' else 'IDL'

    def append_recursive(type_name, depth):
        if depth <= 0:
            raise MessageDefinitionError(
                f'{root_type_name}: more than {_MAX_DEFINITION_DEPTH} nested dependencies')
        text = _read_text(type_name, extension)
        if extension == '.msg':
            dependencies = _msg_dependencies(text, split_type_name(type_name)[0])
        else:
            dependencies = _idl_dependencies(text)
        parts = [text]
        for dependency in dependencies:
            if dependency not in seen:
                seen.add(dependency)
                parts.append(f'\n{DEFINITION_DELIMITER}{label}: {dependency}\n')
                parts.append(append_recursive(dependency, depth - 1))
        return ''.join(parts)

    return append_recursive(root_type_name, _MAX_DEFINITION_DEPTH)


@functools.lru_cache(maxsize=None)
def type_description_hash(type_name):
    """Return the RIHS01 type hash of an installed message type, or '' if unknown.

    Jazzy's rosidl installs ``<share>/<pkg>/msg/<Type>.json`` (the type description) with a
    ``type_hashes`` list; the entry of the type itself is its hash (REP 2011), the same
    string that publishers advertise (``TopicEndpointInfo.topic_type_hash``).
    """
    try:
        description = json.loads(_read_text(type_name, '.json'))
        package, namespace, name = split_type_name(type_name)
        wanted = f'{package}/{namespace}/{name}'
        for entry in description.get('type_hashes', ()):
            if entry.get('type_name') == wanted:
                return str(entry.get('hash_string', ''))
    except (MessageDefinitionError, ValueError, AttributeError):
        pass
    return ''
