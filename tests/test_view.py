"""`lbc view`: the live bus served to Foxglove over its WebSocket protocol, watched by a WebSocket client
speaking that protocol (foxglove.sdk.v1, or the older foxglove.websocket.v1) while a trial runs through the real services."""
from __future__ import annotations

import json
import signal
import struct
import threading

import pytest
from websockets.sync.client import connect

from deploy.router import free_port
from tests.conftest import wait_until
from tests.test_cli import Running

pytestmark = pytest.mark.integration
WATCHED = ("/cmd_vel", "/controller/tracking", "/tf", "/route")


class FoxgloveClient:
    """Subscribes to every advertised channel in WATCHED; keeps what arrives per topic."""

    def __init__(self, uri: str):
        self.uri = uri
        self.ws = None
        self.topics: dict[int, str] = {}          # subscription id -> topic
        self.received: dict[str, list[bytes]] = {t: [] for t in WATCHED}
        self.advertised: dict[str, dict] = {}
        self.connected = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        assert self.connected.wait(10), f"no WebSocket connection to {uri}"

    def _run(self) -> None:
        # the protocol's name in foxglove-sdk, and the older one
        with connect(self.uri, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"], open_timeout=10) as ws:
            self.ws = ws
            self.connected.set()
            try:
                for frame in ws:
                    if isinstance(frame, str):
                        self._on_json(json.loads(frame))
                    elif frame[0] == 0x01:            # message data: op, subscription id, log time, payload
                        sub_id, = struct.unpack_from("<I", frame, 1)
                        self.received[self.topics[sub_id]].append(bytes(frame[13:]))
            except Exception:   # the connection closed
                return

    def _on_json(self, msg: dict) -> None:
        if msg.get("op") != "advertise":
            return
        subs = []
        for ch in msg["channels"]:
            self.advertised[ch["topic"]] = ch
            if ch["topic"] in WATCHED:
                sub_id = len(self.topics) + 1
                self.topics[sub_id] = ch["topic"]
                subs.append({"id": sub_id, "channelId": ch["id"]})
        if subs:
            self.ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

    def close(self) -> None:
        self.ws.close()
        self._thread.join(5)


def _cdr_stamp(payload: bytes) -> float:
    """header.stamp of a CDR (little endian) message that starts with a std_msgs/Header."""
    sec, nanosec = struct.unpack_from("<iI", payload, 4)
    return sec + nanosec * 1e-9


def test_a_foxglove_client_sees_at_least_9_of_10_control_ticks_live(deployment):
    dep, port = deployment, free_port()
    view = Running("view", "--connect", dep.endpoint, "--port", str(port))
    client = None
    try:
        assert view.wait_for("serving the bus", 60), "".join(filter(None, view.lines))
        client = FoxgloveClient(f"ws://127.0.0.1:{port}")
        dep.exp.teach()
        rec = dep.exp.repeat(1, 0.8)
        ticks = {round(s.stamp_s, 3) for s in rec.stepped_status()}
        wait_until(lambda: len({round(_cdr_stamp(p), 3) for p in client.received["/cmd_vel"]} & ticks)
                   >= 0.9 * len(ticks), 30, "the viewer to see 9 of 10 control ticks",
                   lambda: f"{len(client.received['/cmd_vel'])} commands for {len(ticks)} ticks")
        assert len(ticks) > 100
        # the same channels as the MCAP: the ROS 2 topics in CDR with ros2msg schemas, the project's own
        ad = client.advertised
        assert ad["/cmd_vel"]["encoding"] == "cdr" and ad["/cmd_vel"]["schemaName"] == "geometry_msgs/TwistStamped"
        assert ad["/controller/tracking"]["encoding"] == "json"
        assert ad["lbc/r1/cmd/vel"]["encoding"] == "msgpack" and ad["lbc/r1/cmd/vel"]["schemaEncoding"] == "jsonschema"
        wait_until(lambda: client.received["/route"], 10, "the taught route for the map (latched)",
                   lambda: "".join(filter(None, view.lines))[-2000:] + f" advertised {sorted(client.advertised)}")
        tracking = [json.loads(p) for p in client.received["/controller/tracking"]]
        assert tracking and max(abs(t["lateral_m"]) for t in tracking) < 0.2
    finally:
        if client is not None:
            client.close()
        view.proc.send_signal(signal.SIGINT)
        rc, err = view.finish(30)
    assert rc == 0 and "stopped:" in err, err[-2000:]
