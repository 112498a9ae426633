"""Fixed-layout message schemas, self-described as ROS 2 ``.msg`` text and encoded as CDR.

A :class:`StructSchema` is a flat list of ROS 2 primitive fields (and fixed-size arrays of
them). From it follow, with no hand-written per-message code:

- the ``ros2msg`` schema text stored in the MCAP Schema record (schema encoding ``ros2msg``),
  which Foxglove and the ROS 2 tooling decode without a plugin;
- the CDR byte layout of one message (message encoding ``cdr``): the 4-byte encapsulation
  header ``00 01 00 00`` (plain CDR, little-endian), then each field aligned to
  ``min(size, 8)`` counted from the byte after the header, fixed arrays inline with no length;
- a precompiled :class:`struct.Struct` that packs a tuple of values in one call;
- a numpy structured dtype with explicit offsets, so that many payloads of one channel decode
  at once with a single ``view`` instead of one Python call per message.

:func:`parse_ros2msg` turns the schema text back into a :class:`StructSchema`, which is what
makes a log readable without this project's channel list.
"""

from __future__ import annotations

import re
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ballbeam.errors import LogFormatError

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"

#: Encapsulation header of a plain-CDR little-endian payload (representation id 0x0001, options 0).
CDR_LE_HEADER = b"\x00\x01\x00\x00"
CDR_HEADER_BYTES = len(CDR_LE_HEADER)

# ros2 primitive -> (struct code, numpy code, size in bytes). "byte" is an unsigned octet;
# "char" is left out on purpose: tools disagree on its sign.
PRIMITIVES: dict[str, tuple[str, str, int]] = {
    "bool": ("?", "?", 1),
    "byte": ("B", "u1", 1),
    "int8": ("b", "i1", 1),
    "uint8": ("B", "u1", 1),
    "int16": ("h", "<i2", 2),
    "uint16": ("H", "<u2", 2),
    "int32": ("i", "<i4", 4),
    "uint32": ("I", "<u4", 4),
    "int64": ("q", "<i8", 8),
    "uint64": ("Q", "<u8", 8),
    "float32": ("f", "<f4", 4),
    "float64": ("d", "<f8", 8),
}
# Byte-like arrays pack from one bytes object ("8s") rather than eight ints.
_BYTE_TYPES = frozenset({"byte", "uint8"})
_PACKABLE_BYTES = (bytes, bytearray)  # what struct's "Ns" takes as it is

# ROS 2 naming rules, so that every tool that validates .msg files accepts ours.
_FIELD_NAME = re.compile(r"[a-z](?:_?[a-z0-9]+)*")
_TYPE = re.compile(r"([a-z][a-z0-9]*)(?:\[(\d+)\])?")
_CONSTANT = re.compile(r"\S+\s+[A-Za-z][A-Za-z0-9_]*\s*=")
_MAX_ARRAY = 1 << 20  # a sanity bound: nothing we log is near it

_SCALAR, _BYTES, _ARRAY = 0, 1, 2


@dataclass(frozen=True)
class FieldLayout:
    """Where one field lives in a CDR payload (``offset`` counts the 4 header bytes)."""

    name: str
    type: str
    base: str
    count: int | None  # None for a scalar, N for a fixed array T[N]
    offset: int
    size: int


def _parse_type(type_: str) -> tuple[str, int | None]:
    match = _TYPE.fullmatch(type_)
    if match is None or match.group(1) not in PRIMITIVES:
        raise ValueError(
            f"unsupported field type {type_!r}: only fixed-size ROS 2 primitives "
            f"({', '.join(PRIMITIVES)}) and fixed arrays T[N] are allowed"
        )
    base, count_text = match.group(1), match.group(2)
    if count_text is None:
        return base, None
    count = int(count_text)
    if not 1 <= count <= _MAX_ARRAY:
        raise ValueError(f"array length of {type_!r} must be in 1..{_MAX_ARRAY}")
    return base, count


@dataclass(frozen=True)
class StructSchema:
    """A named, flat, fixed-size message layout.

    ``fields`` is a tuple of ``(field_name, ros2_type)`` pairs, e.g.
    ``(("bus_time_s", "float64"), ("arbitration_id", "uint32"), ("data", "uint8[8]"))``.
    ``name`` is the ROS 2 type name shown by viewers, e.g. ``"ballbeam_msgs/msg/CanFrame"``.
    """

    name: str
    fields: tuple[tuple[str, str], ...]
    layout: tuple[FieldLayout, ...] = field(init=False, repr=False, compare=False)
    #: Bytes of one CDR payload, header included.
    size: int = field(init=False, repr=False, compare=False)
    #: Structured dtype over one whole payload (the header bytes are unnamed padding).
    dtype: np.dtype[np.void] = field(init=False, repr=False, compare=False)
    #: Precompiled packer: ``packer.pack(CDR_LE_HEADER, *flat_values)``.
    packer: struct.Struct = field(init=False, repr=False, compare=False)
    _plan: tuple[tuple[int, int], ...] = field(init=False, repr=False, compare=False)
    _flat: bool = field(init=False, repr=False, compare=False)
    _byte_fields: tuple[tuple[int, int], ...] | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Normalise lists to tuples so equal schemas compare and hash equal.
        object.__setattr__(self, "fields", tuple((str(n), str(t)) for n, t in self.fields))
        if not self.name or any(c.isspace() for c in self.name):
            raise ValueError(f"schema name must be non-empty with no whitespace: {self.name!r}")
        if not self.fields:
            raise ValueError(f"schema {self.name!r} has no fields")
        seen: set[str] = set()
        layout: list[FieldLayout] = []
        fmt = ["<4s"]  # the encapsulation header, passed as one bytes value
        plan: list[tuple[int, int]] = []
        pos = 0  # CDR alignment counts from the byte after the encapsulation header
        for name, type_ in self.fields:
            if not _FIELD_NAME.fullmatch(name):
                raise ValueError(
                    f"field name {name!r} in {self.name!r} breaks ROS 2 naming "
                    "(lowercase letters, digits, single underscores, starting with a letter)"
                )
            if name in seen:
                raise ValueError(f"duplicate field {name!r} in {self.name!r}")
            seen.add(name)
            base, count = _parse_type(type_)
            code, _, elem_size = PRIMITIVES[base]
            align = min(elem_size, 8)
            padded = -(-pos // align) * align
            if padded > pos:
                fmt.append(f"{padded - pos}x")
            size = elem_size * (count or 1)
            layout.append(FieldLayout(name, type_, base, count, CDR_HEADER_BYTES + padded, size))
            if count is None:
                fmt.append(code)
                plan.append((_SCALAR, 1))
            elif base in _BYTE_TYPES:
                fmt.append(f"{count}s")
                plan.append((_BYTES, count))
            else:
                fmt.append(f"{count}{code}")
                plan.append((_ARRAY, count))
            pos = padded + size
        total = CDR_HEADER_BYTES + pos
        formats: list[Any] = [
            PRIMITIVES[f.base][1] if f.count is None else (PRIMITIVES[f.base][1], (f.count,))
            for f in layout
        ]
        dtype = np.dtype(
            {
                "names": [f.name for f in layout],
                "formats": formats,
                "offsets": [f.offset for f in layout],
                "itemsize": total,
            }
        )
        object.__setattr__(self, "layout", tuple(layout))
        object.__setattr__(self, "size", total)
        object.__setattr__(self, "dtype", dtype)
        object.__setattr__(self, "packer", struct.Struct("".join(fmt)))
        object.__setattr__(self, "_plan", tuple(plan))
        object.__setattr__(self, "_flat", all(kind == _SCALAR for kind, _ in plan))
        # Scalars and byte arrays only (a CAN frame's record): packed in one call once each
        # byte array is checked for its exact length (struct would pad or cut it silently).
        object.__setattr__(self, "_byte_fields", tuple(
            (index, count) for index, (kind, count) in enumerate(plan) if kind == _BYTES
        ) if all(kind != _ARRAY for kind, _ in plan) else None)

    @property
    def field_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.fields)

    @property
    def ros2msg(self) -> str:
        """The schema text: one ``type name`` line per field."""
        return "".join(f"{type_} {name}\n" for name, type_ in self.fields)

    def pack(self, values: Sequence[Any] | Mapping[str, Any]) -> bytes:
        """Encode one message as a CDR payload.

        ``values`` is a tuple in field order, or a mapping by field name. Byte-like arrays
        (``uint8[N]``, ``byte[N]``) take a bytes-like object of exactly N bytes;
        other arrays take a sequence of N numbers. Raises ValueError on a wrong shape or a
        value out of the field's range.
        """
        if not isinstance(values, tuple) and isinstance(values, Mapping):  # ABC check: slow
            try:
                values = tuple(values[name] for name, _ in self.fields)
            except KeyError as exc:
                raise ValueError(f"{self.name}: missing field {exc.args[0]!r}") from None
        if len(values) != len(self._plan):
            raise ValueError(f"{self.name}: expected {len(self._plan)} values, got {len(values)}")
        try:
            if self._flat:
                return self.packer.pack(CDR_LE_HEADER, *values)
            if self._byte_fields is not None and all(
                type(values[index]) in _PACKABLE_BYTES and len(values[index]) == count
                for index, count in self._byte_fields
            ):
                return self.packer.pack(CDR_LE_HEADER, *values)
            args: list[Any] = [CDR_LE_HEADER]
            for (kind, count), value in zip(self._plan, values, strict=True):
                if kind == _SCALAR:
                    args.append(value)
                elif kind == _BYTES:
                    raw = bytes(value)
                    if len(raw) != count:
                        # struct would pad or truncate silently; a log must not.
                        raise ValueError(f"expected {count} bytes, got {len(raw)}")
                    args.append(raw)
                else:
                    items = tuple(value)
                    if len(items) != count:
                        raise ValueError(f"expected {count} items, got {len(items)}")
                    args.extend(items)
            return self.packer.pack(*args)
        except (struct.error, TypeError) as exc:
            raise ValueError(f"{self.name}: {exc}") from exc
        except ValueError as exc:
            raise ValueError(f"{self.name}: {exc}") from exc

    def unpack(self, payload: bytes) -> tuple[Any, ...]:
        """Decode one CDR payload into a tuple in field order (arrays as bytes or tuples)."""
        if len(payload) != self.size:
            raise ValueError(f"{self.name}: payload has {len(payload)} bytes, expected {self.size}")
        if payload[:2] != CDR_LE_HEADER[:2]:
            raise ValueError(f"{self.name}: not a little-endian plain CDR payload")
        flat = self.packer.unpack(payload)[1:]
        if self._flat:
            return tuple(flat)
        out: list[Any] = []
        i = 0
        for kind, count in self._plan:
            if kind == _ARRAY:
                out.append(tuple(flat[i : i + count]))
                i += count
            else:
                out.append(flat[i])
                i += 1
        return tuple(out)


def parse_ros2msg(text: str, name: str) -> StructSchema:
    """Parse ``.msg`` text (as stored in a ``ros2msg`` Schema record) into a StructSchema.

    Accepts comments, blank lines, constants (``int32 MAX=5``, which take no space) and default
    values (``float64 gain 1.0``); stops at a ``===`` line (dependent type definitions follow it
    in MCAP). Raises LogFormatError for anything without a fixed layout: strings, sequences,
    bounded arrays or nested types.
    """
    fields: list[tuple[str, str]] = []
    for line_no, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith("==="):
            break
        if _CONSTANT.match(line):
            continue  # "type NAME=value" declares a constant, which takes no space
        parts = line.split(None, 2)
        if len(parts) < 2:
            raise LogFormatError(f"schema {name!r} line {line_no}: expected 'type name': {line!r}")
        fields.append((parts[1], parts[0]))
    try:
        return StructSchema(name, tuple(fields))
    except ValueError as exc:
        raise LogFormatError(f"schema {name!r}: {exc}") from exc
