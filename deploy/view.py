"""`lbc view --connect ENDPOINT`: the live bus served to Foxglove over its WebSocket protocol
(foxglove-sdk), with the channels a run's MCAP has: the project's own (msgpack, each with its JSON
Schema) and the standard ROS 2 topics made of them (ros2_export.py).

The Zenoh callback only enqueues; one thread decodes, converts and logs, so a slow viewer never
stalls the session. The taught route is not published on the bus (it is queried), so the view asks
for a route the first time an estimate on it arrives: the map, corridor and estimates need it.
"""
from __future__ import annotations

import logging
import math
import queue
import threading
import time

import foxglove
import zenoh

from common import keys
from common.bus import query
from common.codec import Decoder, encode
from common.messages import LocState, RouteMsg
from deploy.ros2_export import TOPICS, Ros2Export, Ros2Message, announcement
from deploy.wire import TopicEncoder, WireSchema, project_schema

log = logging.getLogger(__name__)

MAX_BACKLOG = 10_000          # messages waiting to be served; beyond, the newest are dropped and counted
LATCHED = ("/route", "/corridor")   # published once per route: a viewer that subscribes later gets the last one
RELOG = "__relog__"
LATCH_REPEAT_S = 2.0          # ... and, for a viewer that subscribed in a race, again this often
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
        self.topics = TopicEncoder()
        self.routes_served: set[str] = set()
        self.route_asked: dict[str, float] = {}      # path_id -> when last asked (monotonic)
        self.latched: dict[str, bytes] = {}          # topic -> its last message, for viewers that come later
        self.listener = _Listener(self)
        self.served = 0
        self.dropped = 0
        # the standard topics' channels exist before any viewer connects: it gets them in its first
        # advertisement (a channel declared while a viewer is subscribing could be refused as unknown)
        for topic in TOPICS:
            self._get(topic, self.topics.schema(announcement(topic)))
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

    def repeat_latched(self) -> None:
        """Every latched topic's last message again: the server may call on_subscribe before the
        subscription takes effect, and a viewer must not miss the map for that."""
        for topic in list(self.latched):
            self._queue.put((RELOG, topic))

    def _relog(self, topic: str) -> None:
        if topic in self.latched:
            self.channels[topic].log(self.latched[topic])

    def _serve(self, key: str, data: bytes) -> None:
        cls = keys.message_type(key)
        msg = self.decoder(cls, data, key) if cls is not None else None
        if msg is None:
            return
        self._get(key, project_schema(cls)).log(data)
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
                self._log_raw(self._get(keys.route(path_id), project_schema(RouteMsg)), keys.route(path_id),
                              encode(route))
                for r in self._export(robot).convert(route):
                    self._log(r)
                self.routes_served.add(path_id)
                return
        log.warning("route %s not available yet: the map shows no route or estimates (asking again in %.0f s)",
                    path_id, ROUTE_RETRY_S)

    def _log(self, r: Ros2Message) -> None:
        self._log_raw(self._get(r.topic, self.topics.schema(r)), r.topic, self.topics.encode(r))

    def _log_raw(self, ch: foxglove.Channel, topic: str, data: bytes) -> None:
        if topic in LATCHED or topic.startswith(f"{keys.ROOT}/paths/"):
            self.latched[topic] = data
        ch.log(data)

    def _get(self, topic: str, schema: WireSchema) -> foxglove.Channel:
        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = foxglove.Channel(
                topic, message_encoding=schema.message_encoding, context=self.context,
                schema=foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data))
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
        while not stop.wait(LATCH_REPEAT_S):
            view.repeat_latched()
    finally:
        view.close()
        server.stop()
        session.close()
    say(f"stopped: {view.served} messages served, {view.dropped} dropped (viewer behind)")
    return 0
