"""Key expressions, all under `lbc/`. Per-robot topics live under `lbc/<robot>/`; routes (and later
the experience store) are shared by every robot so a fleet learns together."""
from __future__ import annotations

from common import messages as m
from common.messages import check_name

ROOT = "lbc"
SERVICES = ("bridge", "localizer", "controller", "gp_store", "scheduler")


def _robot(robot: str) -> str:
    return f"{ROOT}/{check_name('robot', robot)}"


def clock(robot: str) -> str:
    return f"{_robot(robot)}/clock"


def odom(robot: str) -> str:
    return f"{_robot(robot)}/sensors/odom"


def stereo(robot: str) -> str:
    return f"{_robot(robot)}/sensors/stereo"


def truth(robot: str) -> str:
    return f"{_robot(robot)}/truth/pose"


def loc_state(robot: str) -> str:
    return f"{_robot(robot)}/loc/state"


def cmd_vel(robot: str) -> str:
    return f"{_robot(robot)}/cmd/vel"


def ctrl_status(robot: str) -> str:
    return f"{_robot(robot)}/ctrl/status"


def ctrl_corridor(robot: str) -> str:
    return f"{_robot(robot)}/ctrl/corridor"


def ctrl_model(robot: str, path_id: str) -> str:
    """The controller's nominal model identified on a route's teach pass (pub + queryable; '*': all routes)."""
    return f"{_robot(robot)}/ctrl/model/{path_id if path_id == '*' else check_name('path_id', path_id)}"


def bridge_status(robot: str) -> str:
    return f"{_robot(robot)}/bridge/status"


def trial_event(robot: str) -> str:
    return f"{_robot(robot)}/trial/event"


def control(robot: str, service: str) -> str:
    """Queryable of one service for trial control; `service='*'` addresses all of a robot's."""
    if service != "*" and service not in SERVICES:
        raise ValueError(f"unknown service {service!r}")
    return f"{_robot(robot)}/{service}/control"


def alive(robot: str, service: str) -> str:
    return f"{ROOT}/alive/{check_name('robot', robot)}/{service}"


def alive_all(robot: str = "*") -> str:
    return f"{ROOT}/alive/{robot}/*"


def route(path_id: str) -> str:
    return f"{ROOT}/paths/{check_name('path_id', path_id)}"


def experience(robot: str) -> str:
    return f"{_robot(robot)}/experience"


def experience_ack(robot: str) -> str:
    return f"{_robot(robot)}/experience/ack"


STORE_ROBOT = "fleet"   # the store is shared by every robot: its liveliness/control live under this name


def _store(path_id: str, what: str) -> str:
    chunk = path_id if path_id == "*" else check_name("path_id", path_id)
    return f"{ROOT}/store/{chunk}/{what}"


def store_window(path_id: str) -> str:
    return _store(path_id, "window")


def store_hyper(path_id: str) -> str:
    return _store(path_id, "hyper")


def store_fit(path_id: str) -> str:
    return _store(path_id, "fit")


def store_dump(path_id: str) -> str:
    return _store(path_id, "dump")


def sched_schedule(path_id: str) -> str:
    return f"{ROOT}/sched/{check_name('path_id', path_id) if path_id != '*' else '*'}/schedule"


def sched_update(path_id: str) -> str:
    return f"{ROOT}/sched/{check_name('path_id', path_id) if path_id != '*' else '*'}/update"


def store_stats() -> str:
    return f"{ROOT}/store/stats"


def everything() -> str:
    return f"{ROOT}/**"


# message type carried by each per-robot topic (by key suffix), for recorders and tools
TOPIC_TYPES: dict[str, type] = {
    "clock": m.Clock, "sensors/odom": m.Odometry, "sensors/stereo": m.StereoFrame, "truth/pose": m.TruthPose, "loc/state": m.LocState,
    "cmd/vel": m.VelocityCommand, "ctrl/status": m.ControllerStatus,
    "ctrl/corridor": m.CorridorUpdate, "bridge/status": m.BridgeStatus,
    "trial/event": m.TrialEvent, "experience": m.ExperienceBatch, "experience/ack": m.ExperienceAck,
}


def message_type(key: str) -> type | None:
    parts = key.split("/")
    if len(parts) >= 3 and parts[0] == ROOT and parts[1] == "alive":
        return m.AliveEvent
    if len(parts) >= 3 and parts[0] == ROOT and parts[1] == "paths":
        return m.RouteMsg
    if len(parts) == 4 and parts[:2] == [ROOT, "sched"]:
        return {"schedule": m.SpeedSchedule, "update": m.ScheduleUpdate}.get(parts[3])
    if len(parts) == 4 and parts[:2] == [ROOT, "store"]:
        return {"hyper": m.HyperMsg, "window": m.ExperienceWindow, "fit": m.HyperMsg,
                "dump": m.ExperienceBatch}.get(parts[3])
    if len(parts) >= 4 and parts[-1] == "control":
        return m.ControlRequest
    if len(parts) >= 5 and parts[-1] == "reply" and parts[-2] == "control":
        return m.ControlReply
    return TOPIC_TYPES.get("/".join(parts[2:])) if len(parts) >= 3 and parts[0] == ROOT else None
