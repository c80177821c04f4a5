"""CDR bytes of an rclpy message with its alignment padding zeroed: the same message, the same bytes, every time.

``rclpy.serialization.serialize_message`` leaves the padding bytes that CDR inserts to align a field (e.g. the
3 bytes after a 9-byte ``frame_id`` before the next uint32) as they were in the freshly allocated buffer:
uninitialised memory, so serialising one message twice in one process gives different bytes (observed on the
node's ``~/deviations`` clouds). Readers ignore padding, so every value is unaffected; but a byte-for-byte check of
two runs' bags (``xmetro fleet predict --deterministic`` against ``xmetro predict``) needs it canonical.

:func:`padding_spans` walks the message with its rosidl type description (``SLOT_TYPES``) and computes where the
CDR stream (XCDR1, as ROS 2's rmw serialises: alignment to the value's size, 8 at most, relative to the end of the
4-byte encapsulation header) has padding; arrays of primitives are skipped in one step (no per-element loop over a
cloud's ``data``). Written here because no library we use exposes padding-free serialisation of rclpy messages
(``mcap_ros2``'s pure-Python encoder wants dicts/lists and re-encodes every value).
"""

from __future__ import annotations

from typing import Any

__all__ = ["CdrLayoutError", "canonical_cdr", "padding_spans"]

_SIZES = {
    "boolean": 1, "octet": 1, "char": 1, "uint8": 1, "int8": 1,
    "int16": 2, "uint16": 2, "wchar": 2,
    "int32": 4, "uint32": 4, "float": 4,
    "int64": 8, "uint64": 8, "double": 8, "long double": 8,
}
_HEADER = 4  # CDR encapsulation header (representation id + options)


class CdrLayoutError(ValueError):
    """The walk over the message's types does not end at the end of its CDR bytes (a type not handled here)."""


def _align(pos: int, n: int, spans: list[tuple[int, int]]) -> int:
    rel = pos - _HEADER
    new = _HEADER + (rel + n - 1) // n * n
    if new > pos:
        spans.append((pos, new))
    return new


def _walk_value(pos: int, value: Any, t: Any, spans: list[tuple[int, int]]) -> int:
    from rosidl_parser.definition import (
        AbstractNestedType,
        AbstractSequence,
        AbstractString,
        AbstractWString,
        Array,
        BasicType,
        NamespacedType,
    )

    if isinstance(t, BasicType):
        size = _SIZES[t.typename]
        return _align(pos, size, spans) + size
    if isinstance(t, AbstractWString):
        raise CdrLayoutError("wide strings are not handled")
    if isinstance(t, AbstractString):
        pos = _align(pos, 4, spans)
        return pos + 4 + len(value.encode("utf-8")) + 1
    if isinstance(t, NamespacedType):
        return _walk_message(pos, value, spans)
    if isinstance(t, AbstractNestedType):
        if isinstance(t, AbstractSequence):
            pos = _align(pos, 4, spans) + 4
            n = len(value)
        elif isinstance(t, Array):
            n = int(t.size)
        else:
            raise CdrLayoutError(f"type {t} is not handled")
        vt = t.value_type
        if n == 0:
            return pos
        if isinstance(vt, BasicType):  # contiguous: one alignment, no padding between elements
            size = _SIZES[vt.typename]
            return _align(pos, size, spans) + size * n
        for item in value:
            pos = _walk_value(pos, item, vt, spans)
        return pos
    raise CdrLayoutError(f"type {t} is not handled")


def _walk_message(pos: int, msg: Any, spans: list[tuple[int, int]]) -> int:
    slots = msg.__slots__
    types = msg.SLOT_TYPES
    if len(slots) != len(types):  # rclpy keeps a '_check_fields' slot on some versions: skip non-field slots
        slots = [s for s in slots if s != "_check_fields"]
    for slot, t in zip(slots, types, strict=True):
        pos = _walk_value(pos, getattr(msg, slot), t, spans)
    return pos


def padding_spans(msg: Any, size: int | None = None) -> list[tuple[int, int]]:
    """[start, end) byte ranges of the alignment padding in the CDR serialisation of ``msg``.

    Raises:
        CdrLayoutError: the walk does not end at ``size`` (when given).
    """
    spans: list[tuple[int, int]] = []
    end = _walk_message(_HEADER, msg, spans)
    if size is not None and end != size:
        raise CdrLayoutError(f"{type(msg).__name__}: layout walk ends at byte {end}, the CDR bytes have {size}")
    return spans


def canonical_cdr(msg: Any) -> bytes:
    """``serialize_message(msg)`` with every alignment padding byte set to 0."""
    from rclpy.serialization import serialize_message

    raw = bytearray(serialize_message(msg))
    for a, b in padding_spans(msg, len(raw)):
        raw[a:b] = bytes(b - a)
    return bytes(raw)
