"""`lbc view --connect ENDPOINT`: the live bus served to Foxglove over its WebSocket protocol
(foxglove-sdk), with the channels a run's MCAP has: the project's own (msgpack, each with its JSON
Schema) and the standard ROS 2 topics made of them (ros2_export.py).

The Zenoh callback only enqueues; one thread decodes, converts and logs, so a slow viewer never
stalls the session. The taught route is not published on the bus (it is queried), so the view asks
for a route the first time an estimate on it arrives: the map, corridor and estimates need it.
"""
from __future__ import annotations

import json
import logging
import math
import queue
import threading
import time

import foxglove
import zenoh
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap_ros2._dynamic import serialize_dynamic

from common import keys
from common.bus import query
from common.codec import Decoder, encode
from common.messages import LocState, RouteMsg
from deploy.json_schema import json_schema
from deploy.ros2_export import JSON_SCHEMAS, Ros2Export, Ros2Message
from deploy.ros2_msgs import msgdef

log = logging.getLogger(__name__)

MAX_BACKLOG = 10_000          # messages waiting to be served; beyond, the newest are dropped and counted
LATCHED = ("/route", "/corridor")   # published once per route: a viewer that subscribes later gets the last one
RELOG = "__relog__"
ROUTE_RETRY_S = 5.0           # a route not available yet (still being taught) is asked for again after this


class _Listener(foxglove.ServerListener):
    def __init__(self, view: "LiveView"):
        self.view = view

    def on_subscribe(self, client, channel) -> None:
        self.view.on_subscribe(channel.topic)


class LiveView:
    def __init__(self, session: zenoh.Session, corridor_lateral_m: float, context: foxglove.Context):
        self.session = session
        self.corridor_lateral_m = corridor_lateral_m
        self.context = context
        self.decoder = Decoder(log)
        self.exports: dict[str, Ros2Export] = {}     # per robot
        self.channels: dict[str, foxglove.Channel] = {}
        self.encoders: dict = {}
        self.routes_served: set[str] = set()
        self.route_asked: dict[str, float] = {}      # path_id -> when last asked (monotonic)
        self.latched: dict[str, bytes] = {}          # topic -> its last message, for viewers that come later
        self.listener = _Listener(self)
        self.served = 0
        self.dropped = 0
        self._queue: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="view", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(keys.everything(), self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if self._queue.qsize() >= MAX_BACKLOG:
            self.dropped += 1
            return
        self._queue.put((str(sample.key_expr), sample.payload.to_bytes()))

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                if item[0] == RELOG:
                    self._relog(item[1])
                else:
                    self._serve(*item)
            except Exception:       # keep serving the rest
                log.exception("cannot serve %s", item[0])

    def on_subscribe(self, topic: str) -> None:
        """A viewer subscribed (foxglove's thread): a latched topic's last message goes out again for it."""
        if topic in LATCHED or topic.startswith(f"{keys.ROOT}/paths/"):
            self._queue.put((RELOG, topic))

    def _relog(self, topic: str) -> None:
        if topic in self.latched:
            self.channels[topic].log(self.latched[topic])

    def _serve(self, key: str, data: bytes) -> None:
        cls = keys.message_type(key)
        msg = self.decoder(cls, data, key) if cls is not None else None
        if msg is None:
            return
        self._channel(key, cls).log(data)
        robot = key.split("/")[1]
        if isinstance(msg, LocState) and msg.status != "teach" and msg.path_id not in self.routes_served:
            now = time.monotonic()
            if now - self.route_asked.get(msg.path_id, -math.inf) >= ROUTE_RETRY_S:
                self.route_asked[msg.path_id] = now
                self._fetch_route(robot, msg.path_id)
        for r in self._export(robot).convert(msg):
            self._log(r)
        self.served += 1

    def _export(self, robot: str) -> Ros2Export:
        if robot not in self.exports:
            self.exports[robot] = Ros2Export(robot, self.corridor_lateral_m)
        return self.exports[robot]

    def _fetch_route(self, robot: str, path_id: str) -> None:
        for rep in query(self.session, keys.route(path_id), timeout_s=5.0):
            route = self.decoder(RouteMsg, rep.payload, keys.route(path_id)) if rep.error is None else None
            if route is not None:
                self._log_raw(self._channel(keys.route(path_id), RouteMsg), keys.route(path_id), encode(route))
                for r in self._export(robot).convert(route):
                    self._log(r)
                self.routes_served.add(path_id)
                return
        log.warning("route %s not available yet: the map shows no route or estimates (asking again in %.0f s)",
                    path_id, ROUTE_RETRY_S)

    def _log(self, r: Ros2Message) -> None:
        if r.encoding == "json":
            ch = self._get(r.topic, lambda: foxglove.Channel(
                r.topic, message_encoding=MessageEncoding.JSON, context=self.context,
                schema=foxglove.Schema(name=r.datatype, encoding=SchemaEncoding.JSONSchema,
                                       data=json.dumps(JSON_SCHEMAS[r.datatype]).encode())))
            self._log_raw(ch, r.topic, json.dumps(r.message).encode())
            return
        if r.datatype not in self.encoders:
            self.encoders[r.datatype] = serialize_dynamic(r.datatype, msgdef(r.datatype))[r.datatype]
        ch = self._get(r.topic, lambda: foxglove.Channel(
            r.topic, message_encoding=MessageEncoding.CDR, context=self.context,
            schema=foxglove.Schema(name=r.datatype, encoding=SchemaEncoding.ROS2, data=msgdef(r.datatype).encode())))
        self._log_raw(ch, r.topic, self.encoders[r.datatype](r.message))

    def _log_raw(self, ch: foxglove.Channel, topic: str, data: bytes) -> None:
        if topic in LATCHED or topic.startswith(f"{keys.ROOT}/paths/"):
            self.latched[topic] = data
        ch.log(data)

    def _channel(self, key: str, cls: type) -> foxglove.Channel:
        return self._get(key, lambda: foxglove.Channel(
            key, message_encoding=MessageEncoding.MessagePack, context=self.context,
            schema=foxglove.Schema(name=cls.__name__, encoding=SchemaEncoding.JSONSchema,
                                   data=json.dumps(json_schema(cls)).encode())))

    def _get(self, topic: str, make) -> foxglove.Channel:
        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = make()
        return ch

    def close(self) -> None:
        try:
            self._sub.undeclare()
        except Exception:
            pass
        self._queue.put(None)
        self._thread.join(timeout=10)


def serve(endpoint: str, zenoh_conf: str | dict | None, corridor_lateral_m: float, address: str, port: int,
          stop: threading.Event, say) -> int:
    """Serve until `stop` is set; returns an exit code."""
    from common.bus import open_session
    try:
        session = open_session(endpoint, timeout_s=30.0, zenoh_conf=zenoh_conf, stop=stop)
    except (ConnectionError, ValueError) as exc:
        say(str(exc))
        return 1
    context = foxglove.Context()
    view = LiveView(session, corridor_lateral_m, context)
    try:
        server = foxglove.start_server(name="lbc", host=address, port=port, context=context,
                                       server_listener=view.listener)
    except Exception as exc:        # a busy port, mostly
        view.close()
        session.close()
        say(f"cannot serve on {address}:{port}: {exc}")
        return 1
    say(f"serving the bus at {endpoint} to Foxglove on ws://{address}:{server.port} (open a connection there; "
        "layout deploy/foxglove/lbc-run.json; Ctrl-C stops)")
    try:
        while not stop.wait(1.0):
            pass
    finally:
        view.close()
        server.stop()
        session.close()
    say(f"stopped: {view.served} messages served, {view.dropped} dropped (viewer behind)")
    return 0
