"""Records every bus message under `lbc/**` into an MCAP file, exactly as it travelled (msgpack, each
channel with its dataclass as a JSON Schema), and beside them the standard ROS 2 topics made of them
(CDR, ros2msg schemas: ros2_export.py), which Foxglove and the ROS 2 tools decode.

The Zenoh callback only enqueues; a writer thread owns the file. `close()` always finishes the
file (an unfinished MCAP cannot be opened by indexed readers), so call it in a `finally`.
Traffic that no service would accept (a key the project does not use, a payload its message type
rejects) is kept only up to a budget, enough to see what it was: a flood of garbage must not fill the
disk. The same holds for a backlog the writer cannot keep up with.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path

import zenoh
from mcap.writer import Writer

from common import keys
from common.codec import DecodeError, decode, encode
from common.messages import AliveEvent
from deploy.ros2_export import Ros2Export
from deploy.wire import TopicEncoder, WireSchema, project_schema

log = logging.getLogger(__name__)

REJECTED_KEEP_MESSAGES = 200          # of traffic no service would accept, this much is recorded ...
REJECTED_KEEP_BYTES = 1 << 20         # ... and at most this many bytes of it
MAX_BACKLOG = 200_000                 # messages waiting for the writer; beyond, new ones are counted, not kept


class McapRecorder:
    def __init__(self, path: str | Path, session: zenoh.Session, key: str = keys.everything(),
                 stereo_every: int = 1, ros2: Ros2Export | None = None):
        """`stereo_every`: keep one stereo frame in this many (per key); everything else is kept.
        `ros2`: also write the standard ROS 2 topics it makes of the messages (ros2_export.py)."""
        self.ros2 = ros2
        self._topics = TopicEncoder()
        self.path = Path(path)
        self.stereo_every = max(int(stereo_every), 1)
        self.stereo_skipped = 0
        self.rejected = 0              # published messages no service would accept
        self.rejected_skipped = 0      # ... of which not recorded (over the budget)
        self.backlog_skipped = 0       # not recorded because the writer was too far behind
        self._rejected_bytes = 0
        self._stereo_seen: dict[str, int] = {}
        self._fh = open(self.path, "wb")
        self._writer = Writer(self._fh)
        self._writer.start(profile="", library="lbc")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._queue: queue.Queue = queue.Queue()
        self.count = 0
        self._thread = threading.Thread(target=self._run, name="mcap-writer", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(key, self._on_sample)
        self._alive = session.liveliness().declare_subscriber(f"{keys.ROOT}/alive/**", self._on_alive, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if self.stereo_every > 1 and key.endswith("/sensors/stereo"):
            n = self._stereo_seen.get(key, 0)
            self._stereo_seen[key] = n + 1
            if n % self.stereo_every:
                self.stereo_skipped += 1
                return
        if self._queue.qsize() >= MAX_BACKLOG:
            self.backlog_skipped += 1
            return
        self._queue.put((key, sample.payload.to_bytes(), time.time_ns(), True))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        t = time.time_ns()
        event = AliveEvent(stamp_s=t * 1e-9, alive=sample.kind == zenoh.SampleKind.PUT)
        self._queue.put((str(sample.key_expr), encode(event), t, False))

    def record(self, key: str, data: bytes) -> None:
        """Add a message that did not travel as a publication (e.g. a control request)."""
        self._queue.put((key, data, time.time_ns(), False))

    def _channel(self, topic: str, schema: WireSchema) -> int:
        ch = self._channels.get(topic)
        if ch is None:
            sid = self._schemas.get(schema.name)
            if sid is None:
                sid = self._schemas[schema.name] = self._writer.register_schema(
                    name=schema.name, encoding=schema.encoding, data=schema.data)
            ch = self._channels[topic] = self._writer.register_channel(
                topic=topic, message_encoding=schema.message_encoding, schema_id=sid)
        return ch

    def _add(self, ch: int, key: str, data: bytes, t_ns: int) -> None:
        seq = self._seq.get(key, 0)
        self._seq[key] = seq + 1
        self._writer.add_message(channel_id=ch, log_time=t_ns, publish_time=t_ns, data=data, sequence=seq)
        self.count += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            key, data, t_ns, published = item
            msg = self._decoded(key, data)
            if published and msg is None:
                self.rejected += 1
                if self.rejected > REJECTED_KEEP_MESSAGES or self._rejected_bytes + len(data) > REJECTED_KEEP_BYTES:
                    self.rejected_skipped += 1
                    continue
                self._rejected_bytes += len(data)
            try:
                self._add(self._channel(key, project_schema(keys.message_type(key))), key, data, t_ns)
                if self.ros2 is not None and msg is not None:
                    for r in self.ros2.convert(msg):
                        self._add(self._channel(r.topic, self._topics.schema(r)), r.topic, self._topics.encode(r),
                                  t_ns)
            except Exception:  # keep recording the rest
                log.exception("cannot record message on %s", key)

    @staticmethod
    def _decoded(key: str, data: bytes):
        """The message, or None if no service would accept it."""
        cls = keys.message_type(key)
        if cls is None:
            return None
        try:
            return decode(cls, data)
        except DecodeError:
            return None

    def close(self) -> None:
        for sub in (self._sub, self._alive):
            try:
                sub.undeclare()
            except Exception:
                pass
        self._queue.put(None)
        self._thread.join(timeout=30)
        if self.rejected_skipped or self.backlog_skipped:
            log.warning("recorder: %d messages no service would accept (%d of them not recorded), %d not recorded "
                        "because the writer fell behind", self.rejected, self.rejected_skipped, self.backlog_skipped)
        try:
            self._writer.finish()
        finally:
            self._fh.close()
