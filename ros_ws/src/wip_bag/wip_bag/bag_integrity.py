"""Integrity of MCAP files: every chunk's CRC, the data-section and summary CRCs, the end.

A bag is read only after this check (:mod:`wip_bag.bag_reader`), so a flipped bit or a
file cut short is never decoded into a silently wrong result (a speed of 3e273 m/s, a run
that looks successful but ends at half its length). What is found damaged is reported
with its time range and the topics it held; :mod:`wip_bag.bag_repair` recovers every
intact chunk, before and after a damaged one.

The scan walks the file's records by their framing (opcode, length). MCAP chunks are
self-contained: each carries the CRC32 of its uncompressed records (MCAP specification,
"Chunk"), so a chunk whose CRC matches is intact whatever happened around it. Where the
framing itself is broken (a flipped length), the scan looks for the next chunk whose
header is consistent and whose CRC matches, and goes on from there.
"""

from __future__ import annotations

import io
import mmap
import pathlib
import struct
import zlib
from typing import Iterator, NamedTuple

from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Message, MessageIndex, Metadata, Schema
from mcap.stream_reader import get_chunk_data_stream

MAGIC = b'\x89MCAP0\r\n'
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 1, 2, 3, 4, 5, 6
OP_MESSAGE_INDEX, OP_DATA_END = 7, 15
_KNOWN_OPCODES = set(range(1, 16))
_UNFINISHED = 'unfinished file (cut short, or its recorder was killed)'
_FOOTER_SIZE = 1 + 8 + 20  # opcode, length, summary_start, summary_offset_start, crc
_COMPRESSIONS = (b'', b'zstd', b'lz4')
# What decoding damaged bytes can raise.
_DECODE_ERRORS = (McapError, EOFError, ValueError, IndexError, KeyError, MemoryError,
                  OverflowError, UnicodeDecodeError, struct.error, zlib.error, RuntimeError)


class Damage(NamedTuple):
    """A part of a file that cannot be read."""

    offset: int  # byte offset where it starts
    reason: str  # 'chunk CRC mismatch', 'broken record framing', 'unfinished file' ...
    after_ns: int | None  # log time of the last intact message before it (None: none)
    before_ns: int | None  # log time of the first intact message after it (None: none)
    topics: tuple  # topics whose messages it held, when known (else empty)


class GoodChunk(NamedTuple):
    """An intact chunk: where it is and what its header says."""

    offset: int
    start_ns: int
    end_ns: int
    compression: str


class FileScan:
    """What :func:`scan_file` found in one MCAP file."""

    def __init__(self, path: pathlib.Path) -> None:
        self.path = path
        self.size = 0
        self.chunks: list[GoodChunk] = []
        self.damage: list[Damage] = []
        self.unfinished = False  # no valid DataEnd/Footer/magic at the end
        self.summary_ok = False  # a summary section whose CRC matched
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: list[Metadata] = []
        self.loose: list[tuple[int, int]] = []  # (offset, length) of records outside chunks
        #: channel id -> [message count, first and last log time] of the intact chunks.
        self.message_stats: dict[int, list[int]] = {}
        self.notes: list[str] = []  # damage that loses no message (a broken summary)

    @property
    def intact(self) -> bool:
        """Finished, and no damaged byte anywhere."""
        return not self.damage and not self.unfinished

    @property
    def seekable(self) -> bool:
        """Intact with a summary: a SeekingReader may use its indexes."""
        return self.intact and self.summary_ok and not self.notes

    def topic_of(self, channel_id: int) -> str:
        channel = self.channels.get(channel_id)
        return channel.topic if channel is not None else f'<channel {channel_id}>'

    def problems(self, origin_ns: int | None = None) -> list[str]:
        """One human-readable line per damaged part (times relative to ``origin_ns``)."""
        lines = []
        for d in self.damage:
            where = describe_range(d.after_ns, d.before_ns, origin_ns)
            topics = ', '.join(d.topics) if d.topics else 'topics unknown'
            lines.append(f'{self.path.name}: {d.reason} at byte {d.offset}: messages {where} '
                         f'lost ({topics})')
        if self.unfinished and not any(d.reason.startswith('unfinished') for d in self.damage):
            lines.append(f'{self.path.name}: unfinished (no summary/footer: the recorder '
                         'was killed?)')
        return lines


def describe_range(after_ns: int | None, before_ns: int | None,
                   origin_ns: int | None) -> str:
    """'between t = 1.200 s and t = 1.700 s' (relative to origin_ns), open ends named."""
    def t(ns):
        if origin_ns is None:
            return f'{ns * 1e-9:.3f} s'
        return f't = {(ns - origin_ns) * 1e-9:.3f} s'
    if after_ns is None and before_ns is None:
        return 'of unknown time'
    if after_ns is None:
        return f'before {t(before_ns)}'
    if before_ns is None:
        return f'after {t(after_ns)}'
    return f'between {t(after_ns)} and {t(before_ns)}'


def _u64(data, pos: int) -> int:
    return struct.unpack_from('<Q', data, pos)[0]


def _u32(data, pos: int) -> int:
    return struct.unpack_from('<I', data, pos)[0]


def _parse_chunk(data, pos: int, limit: int) -> tuple[Chunk, int] | None:
    """Return the chunk record at ``pos`` if its framing is consistent (not its CRC); its end."""
    if pos + 9 > limit or data[pos] != OP_CHUNK:
        return None
    length = _u64(data, pos + 1)
    end = pos + 9 + length
    body = pos + 9
    if length < 8 + 8 + 8 + 4 + 4 + 8 or end > limit:
        return None
    start_ns, end_ns, uncompressed_size, crc = struct.unpack_from('<QQQI', data, body)
    name_length = _u32(data, body + 28)
    name_end = body + 32 + name_length
    if name_length > 8 or name_end + 8 > end:
        return None
    compression = bytes(data[body + 32:name_end])
    if compression not in _COMPRESSIONS:
        return None
    records_length = _u64(data, name_end)
    if name_end + 8 + records_length != end or start_ns > end_ns:
        return None
    if uncompressed_size > 1 << 34 or (compression == b'' and uncompressed_size != records_length):
        return None
    chunk = Chunk(compression=compression.decode(), data=bytes(data[name_end + 8:end]),
                  message_start_time=start_ns, message_end_time=end_ns,
                  uncompressed_crc=crc, uncompressed_size=uncompressed_size)
    return chunk, end


_MESSAGE_HEAD = struct.Struct('<HIQQ')   # channel id, sequence, log time, publish time


def chunk_records(chunk: Chunk) -> list | None:
    """Return the records of a chunk if its CRC (and decompression) is intact, else None.

    What mcap's ``breakup_chunk`` returns (its schemas, channels and messages), with the
    messages' headers read by one ``struct`` unpack each where mcap reads field by field;
    a record running past the chunk's end makes it damaged.
    """
    try:
        stream, size = get_chunk_data_stream(chunk, validate_crc=True)
        data = stream.read(size)
        records: list = []
        pos = 0
        while pos < size:
            opcode = data[pos]
            body = pos + 9
            end = body + _u64(data, pos + 1)
            if end > size:
                return None
            if opcode == OP_MESSAGE:
                if end - body < _MESSAGE_HEAD.size:
                    return None
                channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(
                    data, body)
                records.append(Message(channel_id=channel_id, log_time=log_time,
                                       data=data[body + _MESSAGE_HEAD.size:end],
                                       publish_time=publish_time, sequence=sequence))
            elif opcode in (OP_SCHEMA, OP_CHANNEL):
                kind = Schema if opcode == OP_SCHEMA else Channel
                records.append(kind.read(ReadDataStream(io.BytesIO(data[body:end]))))
            pos = end
        return records
    except Exception:  # noqa: BLE001 (zstd and lz4 raise types of their own on bad data)
        return None


def _read_loose(opcode: int, body: bytes):
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == OP_SCHEMA:
        return Schema.read(stream)
    if opcode == OP_CHANNEL:
        return Channel.read(stream)
    if opcode == OP_MESSAGE_INDEX:
        return MessageIndex.read(stream)
    if opcode == 0x0C:
        return Metadata.read(stream)
    return None


def _resync(data, pos: int, limit: int) -> int | None:
    """Offset of the next intact chunk after ``pos`` (framing and CRC), or None."""
    while True:
        pos = data.find(bytes((OP_CHUNK,)), pos, limit)
        if pos < 0:
            return None
        parsed = _parse_chunk(data, pos, limit)
        if parsed is not None and parsed[0].uncompressed_crc != 0 \
                and chunk_records(parsed[0]) is not None:
            return pos
        pos += 1


def _footer(data, size: int) -> tuple[int, int] | None:
    """(footer offset, summary_start) if the file ends with a valid footer and magic."""
    pos = size - len(MAGIC) - _FOOTER_SIZE
    if pos < len(MAGIC) or bytes(data[size - len(MAGIC):size]) != MAGIC:
        return None
    if data[pos] != OP_FOOTER or _u64(data, pos + 1) != 20:
        return None
    summary_start, _, summary_crc = struct.unpack_from('<QQI', data, pos + 9)
    if summary_start:
        if not len(MAGIC) <= summary_start < pos:
            return None
        if summary_crc and zlib.crc32(data[summary_start:pos + 9 + 16]) != summary_crc:
            return None
    return pos, summary_start


def scan_file(path: str | pathlib.Path) -> FileScan:
    """Check every byte of an MCAP file that can be checked; see the module docstring."""
    path = pathlib.Path(path)
    scan = FileScan(path)
    with open(path, 'rb') as stream:
        scan.size = size = stream.seek(0, io.SEEK_END)
        if size == 0:
            scan.unfinished = True
            scan.damage.append(Damage(0, 'unfinished file (empty)', None, None, ()))
            return scan
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            _scan(data, size, scan)
    return scan


class _DamageTracker:
    """Damaged stretches of a file: one opens at a bad record, the next good chunk closes it."""

    def __init__(self) -> None:
        self.last_end_ns: int | None = None  # end of the last good chunk's messages
        self.open: list | None = None  # [offset, reason, after_ns, channel ids]
        self.closed: list[list] = []  # [offset, reason, after_ns, before_ns, channel ids]

    def begin(self, offset: int, reason: str) -> None:
        if self.open is None:
            self.open = [offset, reason, self.last_end_ns, set()]

    def close(self, before_ns: int | None) -> None:
        if self.open is not None:
            offset, reason, after, channels = self.open
            self.closed.append([offset, reason, after, before_ns, channels])
            self.open = None


def _scan(data, size: int, scan: FileScan) -> None:
    footer = _footer(data, size)
    damage = _DamageTracker()
    pos, data_end = _walk_records(data, footer[0] if footer is not None else size,
                                  footer is not None, scan, damage)
    if data_end is None:
        scan.unfinished = True
        damage.begin(pos if pos is not None else size, _UNFINISHED)
    damage.close(None)
    if footer is not None and data_end is not None and footer[1]:
        # The summary's channels name the topics of a damaged chunk that defined them.
        _read_summary(data, footer[1], footer[0], scan)
        scan.summary_ok = True
    elif data_end is not None and footer is None:
        scan.notes.append(f'{scan.path.name}: damaged summary or footer (every message is '
                          'intact; scripts/bag_repair rebuilds it)')
    every_topic = {channel.topic for channel in scan.channels.values()}
    for offset, reason, after, before, channels in damage.closed:
        # A file cut short lost the tail of every topic; a damaged chunk those of its index.
        topics = ({scan.topic_of(c) for c in channels} if channels
                  else every_topic if reason.startswith('unfinished') or before is None
                  else set())
        scan.damage.append(Damage(offset, reason, after, before, tuple(sorted(topics))))


def _walk_records(data, limit: int, has_footer: bool, scan: FileScan,
                  damage: _DamageTracker) -> tuple[int | None, int | None]:
    """Read the data section's records up to ``limit``; (where it stopped, DataEnd's offset)."""
    pos: int | None = len(MAGIC)
    if bytes(data[:len(MAGIC)]) != MAGIC:
        damage.begin(0, 'damaged file header')
        pos = _resync(data, 0, limit)
    while pos is not None and pos < limit:
        if pos + 9 > limit:
            damage.begin(pos, _UNFINISHED)
            break
        opcode = data[pos]
        length = _u64(data, pos + 1)
        end = pos + 9 + length
        if opcode not in _KNOWN_OPCODES or end > limit:
            if not has_footer and opcode in _KNOWN_OPCODES and _resync(
                    data, pos + 1, limit) is None:
                damage.begin(pos, _UNFINISHED)
                break
            damage.begin(pos, 'broken record framing')
            pos = _resync(data, pos + 1, limit)
            continue
        if opcode == OP_CHUNK:
            _keep_chunk(data, pos, limit, scan, damage)
        elif opcode == OP_MESSAGE_INDEX:
            if damage.open is not None:  # The index of the damaged chunk: its channels.
                record = _try_read(opcode, data, pos, end)
                if record is not None:
                    damage.open[3].add(record.channel_id)
        elif opcode == OP_DATA_END:
            crc = _u32(data, pos + 9) if length >= 4 else 0
            if (crc and damage.open is None and not damage.closed
                    and zlib.crc32(data[:pos]) != crc):
                damage.begin(pos, 'data section CRC mismatch')
            return pos, pos
        elif opcode in (OP_SCHEMA, OP_CHANNEL, 0x0C):
            record = _try_read(opcode, data, pos, end)
            if record is None:
                damage.begin(pos, 'damaged record')
            else:
                _keep(scan, record)
        elif opcode == OP_MESSAGE:
            scan.loose.append((pos, length))
        elif opcode == OP_FOOTER:
            break
        pos = end
    return pos, None


def _keep_chunk(data, pos: int, limit: int, scan: FileScan, damage: _DamageTracker) -> None:
    """Keep the records of an intact chunk; a damaged one opens a damaged stretch."""
    parsed = _parse_chunk(data, pos, limit)
    records = chunk_records(parsed[0]) if parsed is not None else None
    if records is None:
        damage.begin(pos, 'chunk CRC mismatch' if parsed is not None else 'broken chunk header')
        return
    chunk = parsed[0]
    damage.close(chunk.message_start_time)
    stats = scan.message_stats
    for record in records:
        if record.__class__ is Message:
            found = stats.get(record.channel_id)
            if found is None:
                stats[record.channel_id] = [1, record.log_time, record.log_time]
            else:
                found[0] += 1
                found[1] = min(found[1], record.log_time)
                found[2] = max(found[2], record.log_time)
        else:
            _keep(scan, record)
    scan.chunks.append(GoodChunk(pos, chunk.message_start_time, chunk.message_end_time,
                                 chunk.compression))
    damage.last_end_ns = (chunk.message_end_time if damage.last_end_ns is None
                          else max(damage.last_end_ns, chunk.message_end_time))


def _keep(scan: FileScan, record) -> None:
    if isinstance(record, Schema):
        scan.schemas.setdefault(record.id, record)
    elif isinstance(record, Channel):
        scan.channels.setdefault(record.id, record)
    elif isinstance(record, Metadata):
        scan.metadata.append(record)


def _try_read(opcode: int, data, pos: int, end: int):
    try:
        return _read_loose(opcode, bytes(data[pos + 9:end]))
    except _DECODE_ERRORS:
        return None


def _read_summary(data, start: int, footer_pos: int, scan: FileScan) -> None:
    pos = start
    while pos + 9 <= footer_pos:
        opcode, length = data[pos], _u64(data, pos + 1)
        end = pos + 9 + length
        if end > footer_pos:
            return
        if opcode in (OP_SCHEMA, OP_CHANNEL):
            record = _try_read(opcode, data, pos, end)
            if record is not None:
                _keep(scan, record)
        pos = end


def iter_chunk_records(path: str | pathlib.Path, scan: FileScan,
                       chunks: list[GoodChunk] | None = None) -> Iterator[list]:
    """Yield ``(chunk, records)`` of each intact chunk of ``scan`` (re-read from disk).

    In file order, or in the order of ``chunks`` (some of ``scan.chunks``).
    """
    chunks = scan.chunks if chunks is None else chunks
    if not chunks:
        return
    with open(path, 'rb') as stream, mmap.mmap(stream.fileno(), 0,
                                               access=mmap.ACCESS_READ) as data:
        for good in chunks:
            parsed = _parse_chunk(data, good.offset, len(data))
            records = chunk_records(parsed[0]) if parsed is not None else None
            if records is not None:  # (changed on disk since the scan otherwise)
                yield good, records
