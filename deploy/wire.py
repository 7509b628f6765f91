"""How each channel of a run goes out, in run.mcap (recorder.py) and live (view.py): the project's own
messages as they travelled (msgpack, their dataclass as a JSON Schema) and the topics made of them
(ros2_export.py: CDR with a ros2msg schema, or JSON with a JSON Schema)."""
from __future__ import annotations

import functools
import json
from dataclasses import dataclass

from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap_ros2._dynamic import serialize_dynamic   # the CDR encoder mcap_ros2's own Writer uses

from deploy.json_schema import json_schema
from deploy.ros2_export import JSON_SCHEMAS, Ros2Message
from deploy.ros2_msgs import msgdef


@dataclass(frozen=True)
class WireSchema:
    name: str
    encoding: str              # of the schema: ros2msg, jsonschema, "" (none)
    data: bytes
    message_encoding: str      # cdr, json, msgpack


@functools.cache            # called for every message recorded or served: build each schema once
def project_schema(cls: type | None) -> WireSchema:
    """A project channel's schema; None: a key no message type belongs to (traffic no service accepts)."""
    if cls is None:
        return WireSchema("unknown", "", b"", MessageEncoding.MessagePack)
    return WireSchema(cls.__name__, SchemaEncoding.JSONSchema, json.dumps(json_schema(cls)).encode(),
                      MessageEncoding.MessagePack)


class TopicEncoder:
    """Schemas and payloads of converted topics, with one CDR encoder per ROS 2 type."""

    def __init__(self):
        self._cdr: dict = {}
        self._schemas: dict[tuple[str, str], WireSchema] = {}

    def schema(self, r: Ros2Message) -> WireSchema:
        key = (r.datatype, r.encoding)
        if key not in self._schemas:
            self._schemas[key] = (
                WireSchema(r.datatype, SchemaEncoding.JSONSchema, json.dumps(JSON_SCHEMAS[r.datatype]).encode(),
                           MessageEncoding.JSON) if r.encoding == "json" else
                WireSchema(r.datatype, SchemaEncoding.ROS2, msgdef(r.datatype).encode(), MessageEncoding.CDR))
        return self._schemas[key]

    def encode(self, r: Ros2Message) -> bytes:
        if r.encoding == "json":
            return json.dumps(r.message).encode()
        if r.datatype not in self._cdr:
            self._cdr[r.datatype] = serialize_dynamic(r.datatype, msgdef(r.datatype))[r.datatype]
        return self._cdr[r.datatype](r.message)
