"""Write rosbag2 bags (MCAP storage) without rosbag2, which is not on PyPI.

The layout follows rosbag2 Jazzy (``rosbag2_storage_mcap`` and ``rosbag2_storage``, metadata
version 9), so that ``ros2 bag info/play`` on a full ROS 2 install, ``rosbags`` and the MCAP
tools read the bags:

- a bag is a directory ``<name>/`` holding ``<name>_0.mcap`` and ``metadata.yaml``;
- the MCAP file has profile ``ros2``; one schema per message type, named like
  ``std_msgs/msg/Header``, with encoding ``ros2msg`` and the full message definition as data
  (see :func:`message_definition`); one channel per topic with message encoding ``cdr`` and
  the metadata keys ``offered_qos_profiles`` (a YAML string) and ``topic_type_hash``
  (``RIHS01_...``); messages carry the receive time as log time;
- at close, a metadata record ``rosbag2`` with key ``serialized_metadata`` (what
  ``MCAPStorage::update_metadata`` writes), then ``metadata.yaml`` with the top-level key
  ``rosbag2_bagfile_information``.

MCAP chunk compression (zstd, lz4) is a property of the storage, as with rosbag2's MCAP
storage configuration, so ``compression_format`` and ``compression_mode`` of metadata.yaml
stay empty (they describe rosbag2's own file/message compression, which is not used).

This module imports neither rclpy nor rosbag2: the message definitions and type hashes are
read from the interface files that the message packages install
(``<prefix>/share/<pkg>/msg/<Type>.msg`` and ``.json``).

References
----------
.. [1] ros2/rosbag2 (jazzy): rosbag2_storage_mcap/src/mcap_storage.cpp,
   rosbag2_storage_mcap/src/message_definition_cache.cpp, rosbag2_storage/src/qos.cpp,
   rosbag2_storage/include/rosbag2_storage/yaml.hpp.
"""

import functools
import json
import os
import pathlib
import re
import sys
from typing import NamedTuple

from mcap.writer import CompressionType, Writer
import yaml

from .qos_yaml import dump_offered_qos, normalize_offered_qos

METADATA_VERSION = 9  # rosbag2 Jazzy
METADATA_FILE_NAME = 'metadata.yaml'
STORAGE_IDENTIFIER = 'mcap'
MCAP_PROFILE = 'ros2'
DEFAULT_CHUNK_SIZE = 1024 * 1024  # [bytes] of uncompressed chunk data
SERIALIZATION_FORMAT = 'cdr'
DEFINITION_DELIMITER = '=' * 80 + '\n'

_COMPRESSION = {
    'none': CompressionType.NONE,
    'zstd': CompressionType.ZSTD,
    'lz4': CompressionType.LZ4,
}

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


class BagExistsError(BagWriterError, FileExistsError):
    """The output directory exists and is not empty: it is never overwritten."""


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


def _time_dict(nanoseconds, key):
    return {key: int(nanoseconds)}


class Rosbag2McapWriter:
    """Writer of one rosbag2 bag directory with MCAP storage (one file, no splitting).

    Parameters
    ----------
    directory : str or pathlib.Path
        Bag directory to create. An existing empty directory is used; an existing non-empty
        one raises :class:`BagExistsError` (a bag is never overwritten).
    compression : str
        MCAP chunk compression: 'zstd' (default), 'lz4' or 'none'.
    chunk_size : int
        Uncompressed size [bytes] after which a chunk is closed and written to disk.
    ros_distro : str or None
        Value of ``ros_distro`` in the metadata; default ``$ROS_DISTRO`` or 'jazzy'.
    custom_data : dict of str to str, optional
        Free key-value pairs stored in ``custom_data`` of the metadata.

    Notes
    -----
    Not thread-safe: call it from one thread (the recorder queues messages to one writer
    thread). Use it as a context manager, or call :meth:`close`, which finishes the MCAP file
    (summary, indexes) and writes ``metadata.yaml``; without it the file has no footer (see
    :func:`recover_bag`).
    """

    def __init__(self, directory, compression='zstd', chunk_size=DEFAULT_CHUNK_SIZE,
                 ros_distro=None, custom_data=None):
        if compression not in _COMPRESSION:
            raise ValueError(
                f'compression {compression!r} not supported; expected one of '
                f'{sorted(_COMPRESSION)}')
        if int(chunk_size) <= 0:
            raise ValueError(f'chunk_size must be positive, got {chunk_size}')
        self.directory = pathlib.Path(directory)
        if self.directory.exists():
            if not self.directory.is_dir():
                raise BagExistsError(f'{self.directory} exists and is not a directory')
            if any(self.directory.iterdir()):
                raise BagExistsError(
                    f'{self.directory} exists and is not empty; refusing to overwrite a bag')
        self.directory.mkdir(parents=True, exist_ok=True)
        self.compression = compression
        self.ros_distro = ros_distro or os.environ.get('ROS_DISTRO') or 'jazzy'
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.file_name = f'{self.directory.name}_0.mcap'
        self.mcap_path = self.directory / self.file_name
        self.metadata_path = self.directory / METADATA_FILE_NAME
        self._stream = open(self.mcap_path, 'xb')
        self._writer = Writer(
            self._stream, chunk_size=int(chunk_size), compression=_COMPRESSION[compression])
        self._writer.start(profile=MCAP_PROFILE, library=_library_identifier())
        self._schema_ids = {}  # type name -> schema id
        self._topics = {}  # topic -> dict(channel_id, type, qos list, hash, count)
        self._message_count = 0
        self._start_ns = None
        self._end_ns = None
        self._closed = False

    # -- context manager -------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, traceback):
        self.close()

    # -- topics and messages ---------------------------------------------------------------
    @property
    def closed(self):
        return self._closed

    @property
    def message_count(self):
        """Number of messages written so far."""
        return self._message_count

    def message_counts(self):
        """Messages written so far per topic, as a dict topic -> count."""
        return {topic: info['count'] for topic, info in self._topics.items()}

    def has_topic(self, name):
        return name in self._topics

    def add_topic(self, name, type_name, message_definition_text=None, qos_profiles=None,
                  type_hash=None, definition_encoding='ros2msg'):
        """Declare a topic (an MCAP channel), and its type's schema on first use.

        Parameters
        ----------
        name : str
            Absolute topic name, e.g. '/imu/data'.
        type_name : str
            ROS type, e.g. 'sensor_msgs/msg/Imu'.
        message_definition_text : str, optional
            Full definition in rosbag2's format; default: built by :func:`message_definition`
            from the installed interface files.
        qos_profiles : str or sequence, optional
            QoS profiles offered by the publishers (rclpy profiles, rosbag2 v9 mappings or a
            YAML string, see :mod:`wip_sim.qos_yaml`).
        type_hash : str, optional
            RIHS01 type hash; default: :func:`type_description_hash` (may be '').
        definition_encoding : str
            Schema encoding of ``message_definition_text`` when given: 'ros2msg' or
            'ros2idl'.
        """
        self._check_open()
        if not name.startswith('/'):
            raise ValueError(f'topic name {name!r} must be absolute')
        if name in self._topics:
            existing = self._topics[name]['type']
            if existing != type_name:
                raise BagWriterError(
                    f'topic {name} already added with type {existing}, not {type_name}')
            return
        qos = normalize_offered_qos(qos_profiles)
        if type_hash is None:
            type_hash = type_description_hash(type_name)
        schema_id = self._schema_ids.get(type_name)
        if schema_id is None:
            if message_definition_text is None:
                definition_encoding, message_definition_text = message_definition(type_name)
            if definition_encoding not in ('ros2msg', 'ros2idl'):
                raise ValueError(f'unknown definition encoding {definition_encoding!r}')
            schema_id = self._writer.register_schema(
                type_name, definition_encoding, message_definition_text.encode('utf-8'))
            self._schema_ids[type_name] = schema_id
        channel_id = self._writer.register_channel(
            topic=name, message_encoding=SERIALIZATION_FORMAT, schema_id=schema_id,
            metadata={'offered_qos_profiles': dump_offered_qos(qos),
                      'topic_type_hash': str(type_hash)})
        self._topics[name] = {'channel_id': channel_id, 'type': type_name, 'qos': qos,
                              'hash': str(type_hash), 'count': 0}

    def write(self, topic, data, log_time_ns, publish_time_ns=None, sequence=0):
        """Write one serialized message.

        Parameters
        ----------
        topic : str
            A topic declared with :meth:`add_topic`.
        data : bytes
            The CDR-serialized message (as from a raw subscription).
        log_time_ns : int
            Receive time [ns] (rosbag2's recv_timestamp, the MCAP log time).
        publish_time_ns : int, optional
            Send time [ns] (rosbag2's send_timestamp, the MCAP publish time); default
            ``log_time_ns``.
        sequence : int
            Optional sequence number of the message.
        """
        self._check_open()
        info = self._topics.get(topic)
        if info is None:
            raise BagWriterError(f'unknown topic {topic!r}: call add_topic first')
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            raise ValueError(f'negative log time {log_time_ns} ns')
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        self._writer.add_message(
            channel_id=info['channel_id'], log_time=log_time_ns, data=bytes(data),
            publish_time=publish_time_ns, sequence=int(sequence))
        info['count'] += 1
        self._message_count += 1
        if self._start_ns is None or log_time_ns < self._start_ns:
            self._start_ns = log_time_ns
        if self._end_ns is None or log_time_ns > self._end_ns:
            self._end_ns = log_time_ns

    def flush(self):
        """Close the chunk in progress and push everything written so far to the OS.

        Bounds what a crash loses: the file stays readable up to the last flush (see
        :func:`recover_bag`). Each flush ends a chunk, so flushing very often costs
        compression ratio.
        """
        self._check_open()
        self._writer.flush()

    # -- closing ---------------------------------------------------------------------------
    def metadata(self):
        """Return the bag metadata (the content of ``rosbag2_bagfile_information``)."""
        return _bag_metadata(
            file_name=self.file_name,
            topics=[(name, info['type'], info['qos'], info['hash'], info['count'])
                    for name, info in self._topics.items()],
            start_ns=self._start_ns, end_ns=self._end_ns, message_count=self._message_count,
            custom_data=self.custom_data, ros_distro=self.ros_distro)

    def close(self):
        """Finish the MCAP file and write ``metadata.yaml``; idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            information = self.metadata()
            # What MCAPStorage::update_metadata stores, so that a lone .mcap file still
            # carries the bag metadata.
            self._writer.add_metadata('rosbag2', {'serialized_metadata': _dump_yaml(
                information)})
            self._writer.finish()
        finally:
            self._stream.close()
        write_metadata_file(self.metadata_path, information)

    def _check_open(self):
        if self._closed:
            raise BagWriterError(f'bag {self.directory} is closed')


def _library_identifier():
    from mcap.writer import LIBRARY_IDENTIFIER
    return f'wip_sim.bag_writer ({LIBRARY_IDENTIFIER})'


def _bag_metadata(file_name, topics, start_ns, end_ns, message_count, custom_data,
                  ros_distro):
    """Build rosbag2's BagMetadata mapping (version 9, key order of yaml.hpp in [1])."""
    start_ns = 0 if start_ns is None else start_ns
    duration_ns = 0 if end_ns is None else end_ns - start_ns
    return {
        'version': METADATA_VERSION,
        'storage_identifier': STORAGE_IDENTIFIER,
        'duration': _time_dict(duration_ns, 'nanoseconds'),
        'starting_time': _time_dict(start_ns, 'nanoseconds_since_epoch'),
        'message_count': int(message_count),
        'topics_with_message_count': [
            {'topic_metadata': {
                'name': name,
                'type': type_name,
                'serialization_format': SERIALIZATION_FORMAT,
                # A YAML sequence in version 9 (a string in versions <= 8).
                'offered_qos_profiles': list(qos),
                'type_description_hash': type_hash},
             'message_count': int(count)}
            for name, type_name, qos, type_hash, count in topics],
        'compression_format': '',
        'compression_mode': '',
        'relative_file_paths': [file_name],
        'files': [{
            'path': file_name,
            'starting_time': _time_dict(start_ns, 'nanoseconds_since_epoch'),
            'duration': _time_dict(duration_ns, 'nanoseconds'),
            'message_count': int(message_count)}],
        'custom_data': dict(custom_data) or None,
        'ros_distro': ros_distro,
    }


def _dump_yaml(data):
    return yaml.safe_dump(data, default_flow_style=False, sort_keys=False)


def write_metadata_file(path, information):
    """Write ``metadata.yaml`` atomically (temporary file, then rename)."""
    path = pathlib.Path(path)
    temporary = path.with_name(path.name + '.tmp')
    temporary.write_text(_dump_yaml({'rosbag2_bagfile_information': information}),
                         encoding='utf-8')
    os.replace(temporary, path)


def recover_bag(directory, compression='zstd'):
    """Make a readable bag of a directory whose writer died before :meth:`close`.

    Reads what the unfinished MCAP file holds up to its last complete chunk, rewrites it as a
    finished MCAP file (summary, indexes) and writes ``metadata.yaml``. The original file is
    kept as ``<name>.mcap.unfinished``.

    Parameters
    ----------
    directory : str or pathlib.Path
        Bag directory holding one ``*.mcap`` file.
    compression : str
        Chunk compression of the rewritten file.

    Returns
    -------
    dict
        The metadata written (``rosbag2_bagfile_information``).
    """
    from .bag_reader import scan_mcap_records  # Imported here: bag_reader is optional.

    directory = pathlib.Path(directory)
    files = sorted(directory.glob('*.mcap'))
    if len(files) != 1:
        raise BagWriterError(f'{directory}: expected one .mcap file, found {len(files)}')
    original = files[0]
    unfinished = original.with_name(original.name + '.unfinished')
    os.replace(original, unfinished)
    schemas, channels = {}, {}
    counts, qos, hashes = {}, {}, {}
    start_ns = end_ns = None
    message_count = 0
    with open(original, 'xb') as stream:
        writer = Writer(stream, compression=_COMPRESSION[compression])
        writer.start(profile=MCAP_PROFILE, library=_library_identifier())
        schema_ids, channel_ids = {}, {}
        for kind, record in scan_mcap_records(unfinished):
            if kind == 'schema' and record.id not in schema_ids:
                schemas[record.id] = record
                schema_ids[record.id] = writer.register_schema(
                    record.name, record.encoding, record.data)
            elif kind == 'channel' and record.id not in channel_ids:
                channels[record.id] = record
                channel_ids[record.id] = writer.register_channel(
                    record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0),
                    dict(record.metadata))
                counts[record.id] = 0
                qos[record.id] = normalize_offered_qos(
                    record.metadata.get('offered_qos_profiles', ''))
                hashes[record.id] = record.metadata.get('topic_type_hash', '')
            elif kind == 'message' and record.channel_id in channel_ids:
                writer.add_message(channel_ids[record.channel_id], record.log_time,
                                   record.data, record.publish_time, record.sequence)
                counts[record.channel_id] += 1
                message_count += 1
                start_ns = record.log_time if start_ns is None else min(start_ns,
                                                                        record.log_time)
                end_ns = record.log_time if end_ns is None else max(end_ns, record.log_time)
        topics = [
            (channel.topic, schemas[channel.schema_id].name if channel.schema_id in schemas
             else '', qos[cid], hashes[cid], counts[cid])
            for cid, channel in channels.items()]
        information = _bag_metadata(
            original.name, topics, start_ns, end_ns, message_count, {},
            os.environ.get('ROS_DISTRO') or 'jazzy')
        writer.add_metadata('rosbag2', {'serialized_metadata': _dump_yaml(information)})
        writer.finish()
    write_metadata_file(directory / METADATA_FILE_NAME, information)
    return information
