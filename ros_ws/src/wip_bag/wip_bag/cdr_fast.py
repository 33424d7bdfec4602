"""Decode a bag's plain ROS 2 messages with :mod:`struct`, checked against mcap_ros2.

mcap_ros2's decoder reads a message field by field through its CDR reader; the numbers of
a message are one ``struct`` unpack (docs/recording.md, "Reading a bag").

:func:`layout_of` reads a ``ros2msg`` schema (the message's definition, then each
dependency's after a line of ``=``) into parts: fixed stretches (numbers, booleans,
fixed-size arrays of those, nested messages made of those), strings, sequences of numbers
or booleans and sequences of strings, after an optional leading ``std_msgs/Header``; a
schema with anything else (a sequence of messages, a byte array, a bounded type) gives
None, and the reader keeps mcap_ros2's decoder. The objects made are of mcap_ros2's own
classes (taken from a message it decoded), field for field equal: :class:`CheckedDecoder`
compares the two on the first message of each combination of the fixed stretches' places
(a string's length shifts what follows by 0-7 bytes) and keeps mcap_ros2's for good at the
first difference. Plain CDR, little endian (what ROS 2 writes) only; a message the fast
path cannot read is given to mcap_ros2, whose errors are the reader's.
"""

from __future__ import annotations

import struct
from typing import Any, Callable, NamedTuple

#: Primitive ROS 2 types of a fixed size: struct code, size (= CDR alignment).
PRIMITIVES = {'bool': ('?', 1), 'byte': ('B', 1), 'char': ('b', 1), 'int8': ('b', 1),
              'uint8': ('B', 1), 'int16': ('h', 2), 'uint16': ('H', 2), 'int32': ('i', 4),
              'uint32': ('I', 4), 'int64': ('q', 8), 'uint64': ('Q', 8), 'float32': ('f', 4),
              'float64': ('d', 8)}
HEADER_TYPES = ('std_msgs/Header', 'std_msgs/msg/Header', 'Header')
_SEPARATOR = '=' * 8
_HEADER = struct.Struct('<iI')      # a header's stamp: sec, nanosec
_U32 = struct.Struct('<I')
#: A fixed-size array of these is a list in mcap_ros2 (uint8/byte arrays are bytes: not taken).
_LIST_ARRAYS = {'bool', 'char', 'int8', 'int16', 'uint16', 'int32', 'uint32', 'int64',
                'uint64', 'float32', 'float64'}


def _definitions(schema_text: str, name: str) -> dict[str, list[tuple[str, str]]]:
    """Return {type name: [(field type, field name), ...]} of a ros2msg schema's sections."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = name
    sections[current] = []
    for raw in schema_text.splitlines():
        line = raw.split('#', 1)[0].strip()
        if not line:
            continue
        if line.startswith(_SEPARATOR):
            current = None
            continue
        if line.startswith('MSG:'):
            current = line[4:].strip()
            sections[current] = []
            continue
        if current is None:
            continue
        parts = line.split()
        if len(parts) < 2 or '=' in line:
            continue       # a constant (NAME=value, NAME = value), not a field
        sections[current].append((parts[0], parts[1]))
    return sections


def _resolve(type_name: str, package: str, sections: dict) -> str | None:
    """Return the section of a nested type ('T' is in the owner's package, 'p/msg/T' is 'p/T')."""
    if '/' not in type_name:
        type_name = f'{package}/{type_name}'
    pkg, base = type_name.split('/', 1)[0], type_name.rsplit('/', 1)[1]
    return next((c for c in (f'{pkg}/{base}', f'{pkg}/msg/{base}') if c in sections), None)


class Field(NamedTuple):
    """A field of a fixed part: its name, and either a value's place or a nested layout."""

    name: str
    first: int               # index of its first value in the part's unpacked tuple
    count: int               # 1, an array's length, or a nested message's value count
    kind: str                # 'value', 'array' or 'nested'
    nested: Any = None       # the nested message's fields for 'nested'


class Part(NamedTuple):
    """A stretch of a message: fixed fields at once, or one string or sequence field."""

    kind: str                # 'fixed', 'string', 'strings' or 'sequence'
    codes: list = []         # 'fixed': (struct code, alignment) of each value
    fields: list = []        # 'fixed': its fields
    name: str = ''           # the field of a string or a sequence
    element: tuple = ()      # 'sequence': (struct code, size) of an element


class Layout(NamedTuple):
    """A message's parts after its optional header."""

    has_header: bool
    parts: list[Part]


def layout_of(schema_name: str, schema_text: str) -> Layout | None:
    """Return the layout of a ros2msg schema, or None where the fast path does not apply.

    It applies to a message of numbers, booleans, strings, fixed-size arrays and sequences
    of numbers or booleans, sequences of strings, and nested messages of numbers (fixed
    size), after an optional leading header.
    """
    sections = _definitions(schema_text, schema_name)
    fields = sections.get(schema_name, [])
    has_header = bool(fields) and fields[0][0] in HEADER_TYPES
    if has_header:
        fields = fields[1:]
    if not fields:
        return None
    parts: list[Part] = []
    fixed: list[tuple[str, str]] = []
    for type_name, name in fields:
        base, bracket, size = type_name.partition('[')
        variable = None
        if type_name == 'string':
            variable = Part('string', name=name)
        elif type_name == 'string[]':
            variable = Part('strings', name=name)
        elif bracket and size == ']' and base in _LIST_ARRAYS:
            variable = Part('sequence', name=name, element=PRIMITIVES[base])
        if variable is None:
            fixed.append((type_name, name))
            continue
        if fixed and not _add_fixed(parts, schema_name, fixed, sections):
            return None
        fixed = []
        parts.append(variable)
    if fixed and not _add_fixed(parts, schema_name, fixed, sections):
        return None
    return Layout(has_header, parts)


def _add_fixed(parts: list, owner: str, fields, sections) -> bool:
    codes: list[tuple[str, int]] = []
    built = _fields(owner, fields, sections, codes, depth=0)
    if not built:
        return False
    parts.append(Part('fixed', codes, built))
    return True


def _fields(owner: str, fields, sections, codes, depth: int) -> list[Field] | None:
    if depth > 8:
        return None
    package = owner.split('/')[0]
    out = []
    for type_name, name in fields:
        base, bracket, size = type_name.partition('[')
        if bracket:
            length = size.rstrip(']')
            if base not in _LIST_ARRAYS or not length.isdigit() or int(length) == 0:
                return None           # a bounded sequence, a byte array, of messages
            code, align = PRIMITIVES[base]
            out.append(Field(name, len(codes), int(length), 'array'))
            codes.extend([(code, align)] * int(length))
        elif base in PRIMITIVES:
            out.append(Field(name, len(codes), 1, 'value'))
            codes.append(PRIMITIVES[base])
        else:
            section = _resolve(base, package, sections)
            if section is None or base in HEADER_TYPES:
                return None           # a string inside, a header inside, an unknown type
            first = len(codes)
            nested = _fields(section, sections[section], sections, codes, depth + 1)
            if not nested:
                return None
            out.append(Field(name, first, len(codes) - first, 'nested', nested))
    return out


def _struct_for(codes: list[tuple[str, int]], start: int) -> struct.Struct:
    """Return the little-endian struct of ``codes`` from CDR offset ``start``, pads included."""
    fmt, offset = ['<'], start
    for code, align in codes:
        pad = -offset % align
        if pad:
            fmt.append(f'{pad}x')
        fmt.append(code)
        offset += pad + align
    return struct.Struct(''.join(fmt))


class CheckedDecoder:
    """A channel's decoder: the fast path where it gives what mcap_ros2 gives, else mcap_ros2.

    The fixed parts' places depend on the lengths of the strings before them (each starts
    aligned): the fast path is compared with mcap_ros2 on the first message of each
    combination of places (``signature``), and taken from then on.
    """

    def __init__(self, layout: Layout | None, slow: Callable[[bytes], Any]) -> None:
        self.layout = layout
        self.slow = slow
        self.structs: dict[tuple[int, int], struct.Struct] = {}   # (part, offset mod 8)
        self.checked: set[tuple] = set()                           # signatures checked
        self.classes: Any = None                                   # mcap_ros2's classes

    def __call__(self, data: bytes) -> Any:
        if self.layout is None or data[:2] != b'\x00\x01':
            return self.slow(data)
        if self.classes is None:
            return self._check(data)
        try:
            message, signature = self._decode(data)
        except (struct.error, UnicodeDecodeError, ValueError, IndexError):
            return self.slow(data)
        if signature in self.checked:
            return message
        return self._check(data, message, signature)

    def _check(self, data: bytes, message=None, signature=None) -> Any:
        """Decode with mcap_ros2; keep the fast path for this signature if it agrees."""
        expected = self.slow(data)
        try:
            if self.classes is None:
                self.classes = _classes_of(expected, self.layout)
                message, signature = self._decode(data)
            # repr: every value exactly (a float's repr round-trips), NaN equal to NaN.
            if type(message) is type(expected) and repr(message) == repr(expected):
                self.checked.add(signature)
                return expected
        except (struct.error, UnicodeDecodeError, AttributeError, TypeError, ValueError,
                IndexError):
            pass
        self.layout = None        # a difference: mcap_ros2 from now on
        return expected

    def _decode(self, data: bytes) -> tuple[Any, tuple]:
        message_class, header_classes, nested_classes = self.classes
        message = message_class()
        offset = 0
        if self.layout.has_header:
            sec, nanosec = _HEADER.unpack_from(data, 4)
            frame_id, offset = _string(data, 8)
            header_class, time_class = header_classes
            stamp = time_class()
            stamp.sec, stamp.nanosec = sec, nanosec
            header = header_class()
            header.stamp, header.frame_id = stamp, frame_id
            message.header = header
        signature = []
        for index, part in enumerate(self.layout.parts):
            kind = part.kind
            if kind == 'fixed':
                key = (index, offset % 8)
                unpack = self.structs.get(key)
                if unpack is None:
                    unpack = self.structs[key] = _struct_for(part.codes, offset)
                _fill(message, part.fields, unpack.unpack_from(data, 4 + offset),
                      nested_classes)
                signature.append(key)
                offset += unpack.size
            elif kind == 'string':
                value, offset = _string(data, offset)
                setattr(message, part.name, value)
            elif kind == 'strings':
                count, offset = _count(data, offset)
                values = []
                for _ in range(count):
                    value, offset = _string(data, offset)
                    values.append(value)
                setattr(message, part.name, values)
            else:
                count, offset = _count(data, offset)
                code, size = part.element
                if count:
                    offset += -offset % size
                    values = struct.unpack_from(f'<{count}{code}', data, 4 + offset)
                    offset += count * size
                else:
                    values = ()
                setattr(message, part.name, list(values))
        return message, tuple(signature)


def _count(data: bytes, offset: int) -> tuple[int, int]:
    """Return the uint32 (a length or a count) at ``offset`` aligned to 4, and the offset after."""
    offset += -offset % 4
    return _U32.unpack_from(data, 4 + offset)[0], offset + 4


def _string(data: bytes, offset: int) -> tuple[str, int]:
    """Return the CDR string at ``offset`` (length with the NUL, bytes, NUL), the offset after."""
    size, offset = _count(data, offset)
    end = offset + size
    if 4 + end > len(data):
        raise ValueError('a string beyond the end')
    return (data[4 + offset:4 + end - 1].decode('utf-8') if size > 1 else ''), end


def _fill(target, fields: list[Field], values: tuple, classes: dict) -> None:
    for field in fields:
        if field.kind == 'value':
            setattr(target, field.name, values[field.first])
        elif field.kind == 'array':
            setattr(target, field.name, list(values[field.first:field.first + field.count]))
        else:
            cls, inner = classes[field.name]
            nested = cls()
            _fill(nested, field.nested, values, inner)
            setattr(target, field.name, nested)


def _classes_of(message, layout: Layout) -> tuple:
    """mcap_ros2's classes of a decoded message: (message, (header, time), nested by field)."""
    header = getattr(message, 'header', None) if layout.has_header else None
    header_classes = ((type(header), type(header.stamp)) if header is not None
                      else (None, None))
    nested = {}
    for part in layout.parts:
        if part.kind == 'fixed':
            nested.update(_nested_classes(message, part.fields))
    return type(message), header_classes, nested


def _nested_classes(message, fields: list[Field]) -> dict:
    classes = {}
    for field in fields:
        if field.kind == 'nested':
            value = getattr(message, field.name)
            classes[field.name] = (type(value), _nested_classes(value, field.nested))
    return classes
