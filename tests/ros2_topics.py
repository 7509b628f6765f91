"""Reads a run's MCAP as a ROS 2 tool would: every CDR channel decoded by mcap_ros2's decoder (an
implementation independent of the recorder's), per topic the decoded messages."""
from __future__ import annotations

from collections import defaultdict

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

STANDARD = {"/tf": "tf2_msgs/TFMessage", "/odom": "nav_msgs/Odometry", "/cmd_vel": "geometry_msgs/TwistStamped",
            "/route": "nav_msgs/Path", "/corridor": "visualization_msgs/MarkerArray",
            "/localization/pose": "geometry_msgs/PoseWithCovarianceStamped"}


def ros2_topics(mcap_path) -> dict[str, list]:
    """Topic -> decoded messages of every ROS 2 (cdr) channel; also checks each channel's schema."""
    out: dict[str, list] = defaultdict(list)
    with open(mcap_path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        cdr = {c.topic for c in summary.channels.values() if c.message_encoding == "cdr"}
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            if ch.message_encoding == "cdr":
                assert schema.encoding == "ros2msg", (ch.topic, schema.encoding)
                if ch.topic in STANDARD:
                    assert schema.name == STANDARD[ch.topic], (ch.topic, schema.name)
            elif ch.message_encoding == "msgpack" and schema.name != "unknown":
                assert schema.encoding == "jsonschema" and schema.data, ch.topic
        for _schema, channel, _message, decoded in reader.iter_decoded_messages(topics=sorted(cdr)):
            out[channel.topic].append(decoded)
    return dict(out)


def check_standard_topics(mcap_path, robot: str) -> dict[str, list]:
    topics = ros2_topics(mcap_path)
    missing = set(STANDARD) - set(topics)
    assert not missing, f"missing ROS 2 topics {sorted(missing)}; have {sorted(topics)}"
    frames = {(t.header.frame_id, t.child_frame_id) for m in topics["/tf"] for t in m.transforms}
    assert {("world", f"{robot}/truth"), ("map", f"{robot}/base_link")} <= frames, frames
    route = topics["/route"][-1]
    assert len(route.poses) > 10 and route.header.frame_id == "map"
    assert all(len(m.markers) == 2 and len(m.markers[0].points) == len(route.poses) for m in topics["/corridor"])
    pose = topics["/localization/pose"][-1]
    assert len(pose.pose.covariance) == 36 and pose.pose.covariance[0] > 0
    assert any(abs(m.twist.linear.x) > 0.1 for m in topics["/cmd_vel"])
    return topics


def layout_topics(layout_path) -> set[str]:
    """Every topic the Foxglove layout shows (3D topics, plot paths, image topics)."""
    import json
    config = json.loads(open(layout_path).read())["configById"]
    out = set()
    for panel in config.values():
        out |= set(panel.get("topics", {}))
        out |= {p["value"].split(".")[0] for p in panel.get("paths", [])}
        if "imageMode" in panel:
            out.add(panel["imageMode"]["imageTopic"])
    return out
