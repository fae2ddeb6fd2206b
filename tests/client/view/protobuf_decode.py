"""foxglove.* protobuf messages decoded with the schema they carry (a FileDescriptorSet), as Lichtblick reads
them with protobufjs: a message that decodes here has the fields its schema names."""

from __future__ import annotations

from typing import Any

from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory


def decode(schema_name: str, schema: bytes, data: bytes) -> dict[str, Any]:
    """The message as a dict (field names as in the .proto, defaults included)."""
    files = descriptor_pb2.FileDescriptorSet.FromString(schema)
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    message_class = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema_name))
    message = message_class.FromString(data)
    return json_format.MessageToDict(
        message, preserving_proto_field_name=True, always_print_fields_with_no_presence=True
    )


def decode_foxglove(message: Any) -> dict[str, Any]:
    """A foxglove-sdk message object (it has no attributes to read) decoded from its own encoding."""
    schema = message.get_schema()
    return decode(schema.name, schema.data, message.encode())
