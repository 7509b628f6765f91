"""`lbc deploy check`: prove, on a running deployment, that its access control holds.

From one host, with the certificates present there: a session without a certificate must be refused;
every certificate must fail to put what it is not entitled to (robot commands, experiences, store
acknowledgements, corridor updates, schedules) and to get an answer to a trial-control request; the
operator's own corridor update and control request must get through, so that a blind observer cannot
pass the check. The probes are payloads no decoder accepts: if one got through, the service would
reject and count it, never act on it.
"""
from __future__ import annotations

import threading
from dataclasses import asdict, dataclass, field

from common import keys
from common.bus import open_session, query
from deploy import access
from deploy.certs import OPERATOR, ROUTER, cert_files, roles
from deploy.manifest import Manifest

MARK = b"lbc-access-check"          # not msgpack of any message: rejected by every decoder
ENTITLED = {"cmd_vel": "controller", "experience": "controller", "experience_ack": "gp_store",
            "ctrl_corridor": OPERATOR, "sched_schedule": "scheduler"}


@dataclass
class CheckResult:
    host: str
    unauthenticated_connect_refused: bool = False
    rogue_puts_sent: int = 0
    rogue_puts_delivered: int = 0
    rogue_control_requests: int = 0
    rogue_control_replies: int = 0
    entitled_puts_delivered: int = 0
    operator_control_replies: int = 0
    leaks: list[str] = field(default_factory=list)    # "<certificate> put <key>" that got through

    @property
    def holds(self) -> bool:
        return (self.unauthenticated_connect_refused and self.rogue_puts_delivered == 0
                and self.rogue_control_replies == 0 and self.entitled_puts_delivered > 0
                and self.operator_control_replies > 0)

    def to_dict(self) -> dict:
        return {**asdict(self), "holds": self.holds}


def _keys(robot: str, path_id: str) -> dict[str, str]:
    return {"cmd_vel": keys.cmd_vel(robot), "experience": keys.experience(robot),
            "experience_ack": keys.experience_ack(robot), "ctrl_corridor": keys.ctrl_corridor(robot),
            "sched_schedule": keys.sched_schedule(path_id)}


class _Observer:
    def __init__(self, session, watched: dict[str, str]):
        self._cond = threading.Condition()
        self.got: dict[str, int] = {name: 0 for name in watched}
        self._subs = [session.declare_subscriber(key, self._counter(name)) for name, key in watched.items()]

    def _counter(self, name: str):
        def on_sample(sample) -> None:
            if sample.payload.to_bytes().startswith(MARK):
                with self._cond:
                    self.got[name] += 1
                    self._cond.notify_all()
        return on_sample

    def counts(self) -> dict[str, int]:
        with self._cond:
            return dict(self.got)

    def wait(self, name: str, count: int, timeout_s: float) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: self.got[name] >= count, timeout_s)


def _available(m: Manifest) -> list[tuple[str, str]]:
    """(host, role) of every session certificate present on this machine."""
    return [(h, r) for h in m.hosts for r in roles(m, h)
            if r != ROUTER and cert_files(m, h, r).cert.exists() and cert_files(m, h, r).key.exists()]


def check_access(m: Manifest, host: str, robot: str, path_id: str, timeout_s: float = 10.0) -> CheckResult:
    endpoint = m.host(host).listen
    result = CheckResult(host)
    try:
        open_session(endpoint, timeout_s=3.0).close()
    except ConnectionError:
        result.unauthenticated_connect_refused = True
    watched = _keys(robot, path_id)
    observer_session = open_session(endpoint, timeout_s=timeout_s,
                                    zenoh_conf=access.session_config(m, host, OPERATOR))
    try:
        observer = _Observer(observer_session, watched)
        for h, role in _available(m):
            _probe(m, endpoint, h, role, robot, watched, result, timeout_s)
        # the operator's corridor update, last: once it arrives, anything sent before it has too
        s = open_session(endpoint, timeout_s=timeout_s, zenoh_conf=access.session_config(m, host, OPERATOR))
        try:
            s.put(watched["ctrl_corridor"], MARK)
            observer.wait("ctrl_corridor", 1, timeout_s)
            result.operator_control_replies = len(query(s, keys.control(robot, "bridge"), MARK, timeout_s))
        finally:
            s.close()
        got = observer.counts()
        result.entitled_puts_delivered = got["ctrl_corridor"]
        for name, n in got.items():
            others = n - (1 if name == "ctrl_corridor" else 0)
            if others > 0:
                result.rogue_puts_delivered += others
                result.leaks.append(f"{others} x put {watched[name]}")
    finally:
        observer_session.close()
    return result


def _probe(m: Manifest, endpoint: str, host: str, role: str, robot: str, watched: dict[str, str],
           result: CheckResult, timeout_s: float) -> None:
    s = open_session(endpoint, timeout_s=timeout_s, zenoh_conf=access.session_config(m, host, role))
    try:
        for name, key in watched.items():
            if ENTITLED[name] != role:
                s.put(key, MARK)
                result.rogue_puts_sent += 1
        if role != OPERATOR:
            result.rogue_control_requests += 1
            replies = query(s, keys.control(robot, "bridge"), MARK, timeout_s=2.0)
            result.rogue_control_replies += len(replies)
            if replies:
                result.leaks.append(f"{host}/{role}: control request answered")
    finally:
        s.close()
