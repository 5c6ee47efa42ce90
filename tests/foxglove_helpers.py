"""Decoding protobuf messages with the schema a file or a server gives (a FileDescriptorSet)."""
from __future__ import annotations


def protobuf_decoder(name: str, descriptor_set: bytes):
    """A function bytes -> message ``name`` (e.g. foxglove.SceneUpdate) of ``descriptor_set``."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    pool = descriptor_pool.DescriptorPool()
    for f in descriptor_pb2.FileDescriptorSet.FromString(descriptor_set).file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name)).FromString
