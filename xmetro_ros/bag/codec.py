"""ROS message objects ⇄ CDR bytes, on demand: the only place the bag package touches ROS.

The rest of ``bag/`` works on raw CDR bytes, schema text and metadata, and imports nothing from ROS. Writing or
reading *message objects* (an rclpy message handed to :meth:`BagWriter.write`, or ``BagReader.messages()`` with
``deserialize=True``) needs the message classes and ``rclpy.serialization``; they are imported here, lazily, when
first used. ``rclpy.serialization`` creates no DDS participant. The layer test (test/test_layers.py) allows this
module, and only this one in the core, to import ROS.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

from .schema import UnknownTypeError, normalize_type

__all__ = ["deserialize", "message_class", "serialize"]


@functools.cache
def message_class(type_name: str) -> Any:
    """The rclpy message class of ``type_name`` (imported as ``pkg.msg.Type``). Raises UnknownTypeError."""
    pkg, sub, name = normalize_type(type_name)
    try:
        module = importlib.import_module(f"{pkg}.{sub}")
        return getattr(module, name)
    except (ImportError, AttributeError) as e:
        raise UnknownTypeError(f"message type {pkg}/{sub}/{name} is not installed: {e}") from e


def serialize(msg: Any) -> bytes:
    """CDR bytes of an rclpy message object."""
    from rclpy.serialization import serialize_message

    return serialize_message(msg)


def deserialize(data: bytes, type_name: str) -> Any:
    """The rclpy message of ``type_name`` held in the CDR bytes ``data``. Raises UnknownTypeError."""
    from rclpy.serialization import deserialize_message

    return deserialize_message(data, message_class(type_name))
