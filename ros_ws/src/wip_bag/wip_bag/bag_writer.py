"""Write rosbag2 bags (MCAP storage) without rosbag2, which is not on PyPI.

The layout follows rosbag2 Jazzy (``rosbag2_storage_mcap`` and ``rosbag2_storage``, metadata
version 9), so that ``ros2 bag info/play`` on a full ROS 2 install, ``rosbags`` and the MCAP
tools read the bags:

- a bag is a directory ``<name>/`` holding ``<name>_0.mcap`` (and ``<name>_1.mcap`` ... when
  split by size or duration) and ``metadata.yaml``;
- the MCAP file has profile ``ros2``; one schema per message type, named like
  ``std_msgs/msg/Header``, with encoding ``ros2msg`` and the full message definition as data
  (see :mod:`wip_bag.message_definitions`); one channel per topic with message encoding
  ``cdr`` and the metadata keys ``offered_qos_profiles`` (a YAML string) and
  ``topic_type_hash`` (``RIHS01_...``); messages carry the receive time as log time;
- at close, a metadata record ``rosbag2`` with key ``serialized_metadata`` (what
  ``MCAPStorage::update_metadata`` writes), then ``metadata.yaml`` with the top-level key
  ``rosbag2_bagfile_information``.

Robustness: MCAP chunks are self-contained (compressed, with their own CRC), so a file whose
writer died keeps every chunk written before the crash; :mod:`wip_bag.bag_repair` rewrites
such files and rebuilds ``metadata.yaml`` from the files' contents.

MCAP chunk compression (zstd, lz4) is a property of the storage, as with rosbag2's MCAP
storage configuration, so ``compression_format`` and ``compression_mode`` of metadata.yaml
stay empty (they describe rosbag2's own file/message compression, which is not used).

This module imports neither rclpy nor rosbag2: the message definitions and type hashes are
read from the interface files that the message packages install
(:mod:`wip_bag.message_definitions`).

References
----------
.. [1] ros2/rosbag2 (jazzy): rosbag2_storage_mcap/src/mcap_storage.cpp,
   rosbag2_storage_mcap/src/message_definition_cache.cpp, rosbag2_storage/src/qos.cpp,
   rosbag2_storage/include/rosbag2_storage/yaml.hpp.
"""

import os
import pathlib

from mcap.writer import CompressionType, Writer
import yaml

from .message_definitions import BagWriterError, message_definition, type_description_hash
from .qos_yaml import dump_offered_qos, normalize_offered_qos

METADATA_VERSION = 9  # rosbag2 Jazzy
METADATA_FILE_NAME = 'metadata.yaml'
STORAGE_IDENTIFIER = 'mcap'
MCAP_PROFILE = 'ros2'
DEFAULT_CHUNK_SIZE = 1024 * 1024  # [bytes] of uncompressed chunk data
SERIALIZATION_FORMAT = 'cdr'

COMPRESSION = {
    'none': CompressionType.NONE,
    'zstd': CompressionType.ZSTD,
    'lz4': CompressionType.LZ4,
}

# Bytes a message adds to an MCAP file besides its data: its record (opcode 1, length 8,
# channel id 2, sequence 4, log time 8, publish time 8) and its message index entry (16).
_MESSAGE_RECORD_OVERHEAD = 31 + 16
# With max_bag_size, a file is closed once less than 1/_MIN_FILL_FRACTION of it is left.
_MIN_FILL_FRACTION = 16


class BagExistsError(BagWriterError, FileExistsError):
    """The output directory exists and is not empty: it is never overwritten."""


def _time_dict(nanoseconds, key):
    return {key: int(nanoseconds)}


class FileStatistics:
    """Messages of one MCAP file of a bag: count and first/last log time [ns]."""

    __slots__ = ('path', 'count', 'start_ns', 'end_ns')

    def __init__(self, path, count=0, start_ns=None, end_ns=None):
        self.path = str(path)
        self.count = int(count)
        self.start_ns = start_ns
        self.end_ns = end_ns

    def add(self, log_time_ns):
        self.count += 1
        if self.start_ns is None or log_time_ns < self.start_ns:
            self.start_ns = log_time_ns
        if self.end_ns is None or log_time_ns > self.end_ns:
            self.end_ns = log_time_ns


class Rosbag2McapWriter:
    """Writer of one rosbag2 bag directory with MCAP storage, split into files on demand.

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
    max_bag_size : int
        Split: a new file is started before a message that could make the data section of
        the current one larger than this [bytes]. The summary written when the file is
        closed comes on top (the schemas, channels and bag metadata, a few KiB, and about
        100 bytes per chunk). 0 (default): no limit. Like rosbag2's ``max_bagfile_size``.
    max_bag_duration : float
        Split: a new file is started before a message logged ``max_bag_duration`` [s] or more
        after the first message of the current file. 0 (default): no limit.

    Notes
    -----
    Files are named ``<directory name>_<index>.mcap`` (index from 0), as rosbag2 names them,
    and listed in order in ``relative_file_paths`` and ``files`` of ``metadata.yaml``. Each
    file is a complete MCAP file of its own: every topic is declared again in each file.
    ``metadata.yaml`` is written at each split (listing the files closed so far) and at
    :meth:`close`.

    Not thread-safe: call it from one thread (the recorder queues messages to one writer
    thread). Use it as a context manager, or call :meth:`close`, which finishes the MCAP file
    (summary, indexes) and writes ``metadata.yaml``; without it the last file has no footer
    (see :func:`wip_bag.bag_repair.repair_bag`).
    """

    def __init__(self, directory, compression='zstd', chunk_size=DEFAULT_CHUNK_SIZE,
                 ros_distro=None, custom_data=None, max_bag_size=0, max_bag_duration=0.0):
        if compression not in COMPRESSION:
            raise ValueError(
                f'compression {compression!r} not supported; expected one of '
                f'{sorted(COMPRESSION)}')
        if int(chunk_size) <= 0:
            raise ValueError(f'chunk_size must be positive, got {chunk_size}')
        if int(max_bag_size) < 0:
            raise ValueError(f'max_bag_size must be >= 0 bytes, got {max_bag_size}')
        if not float(max_bag_duration) >= 0.0:
            raise ValueError(f'max_bag_duration must be >= 0 s, got {max_bag_duration}')
        self.directory = pathlib.Path(directory)
        if self.directory.exists():
            if not self.directory.is_dir():
                raise BagExistsError(f'{self.directory} exists and is not a directory')
            if any(self.directory.iterdir()):
                raise BagExistsError(
                    f'{self.directory} exists and is not empty; refusing to overwrite a bag')
        self.directory.mkdir(parents=True, exist_ok=True)
        self.compression = compression
        self.chunk_size = int(chunk_size)
        self.max_bag_size = int(max_bag_size)
        self.max_bag_duration_ns = int(round(float(max_bag_duration) * 1e9))
        self.ros_distro = ros_distro or os.environ.get('ROS_DISTRO') or 'jazzy'
        self.custom_data = {str(k): str(v) for k, v in (custom_data or {}).items()}
        self.metadata_path = self.directory / METADATA_FILE_NAME
        self._topics = {}  # topic -> dict(type, qos, hash, count, definition, encoding, ...)
        self._files = []  # FileStatistics of the closed files, in order
        self._file = None  # FileStatistics of the current file
        self._message_count = 0
        self._closed = False
        self._open_file(0)

    # -- files -----------------------------------------------------------------------------
    def _open_file(self, index):
        self.file_name = f'{self.directory.name}_{index}.mcap'
        self.mcap_path = self.directory / self.file_name
        self._stream = open(self.mcap_path, 'xb')  # noqa: SIM115 - closed with the file
        self._writer = Writer(self._stream, chunk_size=self.chunk_size,
                              compression=COMPRESSION[self.compression])
        self._writer.start(profile=MCAP_PROFILE, library=library_identifier())
        self._file = FileStatistics(self.file_name)
        self._schema_ids = {}  # type name -> schema id in the current file
        self._stream_position = self._stream.tell()
        self._pending_bytes = 0  # estimated uncompressed bytes of the chunk in progress
        for name, info in self._topics.items():  # Every file declares every topic.
            info['channel_id'] = self._register(name, info)

    def _register(self, name, info):
        schema_id = self._schema_ids.get(info['type'])
        if schema_id is None:
            schema_id = self._writer.register_schema(
                info['type'], info['encoding'], info['definition'].encode('utf-8'))
            self._schema_ids[info['type']] = schema_id
        return self._writer.register_channel(
            topic=name, message_encoding=SERIALIZATION_FORMAT, schema_id=schema_id,
            metadata={'offered_qos_profiles': dump_offered_qos(info['qos']),
                      'topic_type_hash': str(info['hash'])})

    def _finish_file(self):
        """Finish the current MCAP file (summary, footer) and close it."""
        try:
            # What MCAPStorage::update_metadata stores, so that a lone .mcap file still
            # carries the bag metadata.
            self._writer.add_metadata('rosbag2', {'serialized_metadata': _dump_yaml(
                self.metadata())})
            self._writer.finish()
            self._stream.flush()
            os.fsync(self._stream.fileno())
        finally:
            self._stream.close()
        self._files.append(self._file)

    def split(self):
        """Close the current file and continue in the next one (``<name>_<i+1>.mcap``)."""
        self._check_open()
        self._finish_file()
        self._file = None
        write_metadata_file(self.metadata_path, self.metadata())
        self._open_file(len(self._files))

    @property
    def file_names(self):
        """Names of the bag's files so far, the current one last."""
        names = [f.path for f in self._files]
        if self._file is not None:
            names.append(self._file.path)
        return names

    def _size_estimate(self):
        """Bytes the current file would have if the chunk in progress were written now."""
        position = self._stream.tell()
        if position != self._stream_position:  # The writer wrote a chunk: none pending.
            self._stream_position = position
            self._pending_bytes = 0
        return position + self._pending_bytes

    def _should_split(self, log_time_ns, size):
        if self._file.count == 0:
            return False  # Never leave an empty file behind.
        if (self.max_bag_duration_ns > 0
                and log_time_ns - self._file.start_ns >= self.max_bag_duration_ns):
            return True
        if self.max_bag_size > 0 and self._size_estimate() + size > self.max_bag_size:
            # The estimate counts the chunk in progress uncompressed. Write it (compressed)
            # to know the real size; split only if the file is (nearly) full.
            self._writer.flush()
            remaining = self.max_bag_size - self._size_estimate()
            return remaining < size or remaining < self.max_bag_size // _MIN_FILL_FRACTION
        return False

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
            YAML string, see :mod:`wip_bag.qos_yaml`).
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
        known = next((t for t in self._topics.values() if t['type'] == type_name), None)
        if known is not None:  # One schema per type: the first definition given wins.
            definition_encoding, message_definition_text = known['encoding'], known[
                'definition']
        elif message_definition_text is None:
            definition_encoding, message_definition_text = message_definition(type_name)
        if definition_encoding not in ('ros2msg', 'ros2idl'):
            raise ValueError(f'unknown definition encoding {definition_encoding!r}')
        info = {'type': type_name, 'qos': qos, 'hash': str(type_hash), 'count': 0,
                'definition': message_definition_text, 'encoding': definition_encoding}
        info['channel_id'] = self._register(name, info)
        self._topics[name] = info

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

        Raises
        ------
        OSError
            When the file cannot be written (disk full, file size limit ...). The bag is then
            unusable: close it (which may fail too) and repair it (:mod:`wip_bag.bag_repair`).
        """
        self._check_open()
        info = self._topics.get(topic)
        if info is None:
            raise BagWriterError(f'unknown topic {topic!r}: call add_topic first')
        log_time_ns = int(log_time_ns)
        if log_time_ns < 0:
            raise ValueError(f'negative log time {log_time_ns} ns')
        publish_time_ns = log_time_ns if publish_time_ns is None else int(publish_time_ns)
        data = bytes(data)
        size = len(data) + _MESSAGE_RECORD_OVERHEAD
        if (self.max_bag_size or self.max_bag_duration_ns) and self._should_split(
                log_time_ns, size):
            self.split()
            info = self._topics[topic]
        self._writer.add_message(
            channel_id=info['channel_id'], log_time=log_time_ns, data=data,
            publish_time=publish_time_ns, sequence=int(sequence))
        if self.max_bag_size:
            self._size_estimate()  # Notices a chunk written by add_message.
            self._pending_bytes += size
        info['count'] += 1
        self._message_count += 1
        self._file.add(log_time_ns)

    def flush(self, fsync=False):
        """Close the chunk in progress and push everything written so far to the OS.

        Bounds what a crash loses: the file stays readable up to the last flush (see
        :mod:`wip_bag.bag_repair`). Each flush ends a chunk, so flushing very often costs
        compression ratio. With ``fsync`` the data also reaches the disk (survives a power
        loss), at the cost of a disk write.
        """
        self._check_open()
        self._writer.flush()
        if fsync:
            os.fsync(self._stream.fileno())

    # -- closing ---------------------------------------------------------------------------
    def metadata(self):
        """Return the bag metadata (the content of ``rosbag2_bagfile_information``)."""
        files = list(self._files)
        if self._file is not None:
            files.append(self._file)
        return bag_metadata(
            files=files,
            topics=[(name, info['type'], info['qos'], info['hash'], info['count'])
                    for name, info in self._topics.items()],
            custom_data=self.custom_data, ros_distro=self.ros_distro)

    def close(self):
        """Finish the MCAP file and write ``metadata.yaml``; idempotent.

        If finishing the file fails (e.g. the disk is full), the exception propagates, no
        ``metadata.yaml`` is written and the bag is left for :mod:`wip_bag.bag_repair`.
        """
        if self._closed:
            return
        self._closed = True
        self._finish_file()
        self._file = None
        write_metadata_file(self.metadata_path, self.metadata())

    def abandon(self):
        """Close the file without finishing it (after a write error); idempotent."""
        self._closed = True
        try:
            self._stream.close()
        except OSError:
            pass

    def _check_open(self):
        if self._closed:
            raise BagWriterError(f'bag {self.directory} is closed')


def library_identifier():
    """Return the ``library`` field of the MCAP header of the bags this package writes."""
    from mcap.writer import LIBRARY_IDENTIFIER
    return f'wip_bag.bag_writer ({LIBRARY_IDENTIFIER})'


def bag_metadata(files, topics, custom_data, ros_distro):
    """Build rosbag2's BagMetadata mapping (version 9, key order of yaml.hpp in [1]).

    Parameters
    ----------
    files : sequence of FileStatistics
        The bag's files in order (path relative to the bag directory).
    topics : sequence of (name, type, qos list, type hash, message count)
    """
    starts = [f.start_ns for f in files if f.start_ns is not None]
    ends = [f.end_ns for f in files if f.end_ns is not None]
    start_ns = min(starts) if starts else 0
    duration_ns = max(ends) - start_ns if ends else 0
    return {
        'version': METADATA_VERSION,
        'storage_identifier': STORAGE_IDENTIFIER,
        'duration': _time_dict(duration_ns, 'nanoseconds'),
        'starting_time': _time_dict(start_ns, 'nanoseconds_since_epoch'),
        'message_count': int(sum(f.count for f in files)),
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
        'relative_file_paths': [f.path for f in files],
        'files': [{
            'path': f.path,
            'starting_time': _time_dict(f.start_ns or 0, 'nanoseconds_since_epoch'),
            'duration': _time_dict(
                0 if f.start_ns is None else f.end_ns - f.start_ns, 'nanoseconds'),
            'message_count': int(f.count)} for f in files],
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
