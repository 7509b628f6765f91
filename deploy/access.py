"""Zenoh configs of a secured deployment: mutual TLS on every link and access control in every router.

Each router denies by default and allows, per certificate (subject by common name):
- every entitled session: to subscribe to anything under lbc/, and to receive what it subscribed to;
- each service: to put only the keys it publishes, to answer only its own queryables, to query only
  what it asks, and to declare only its own liveliness token (so a valid certificate of the learning
  host cannot command the robot, and only the store answers store queries);
- the operator (experiment runner, CLI): trial control, store/scheduler queries, corridor updates;
- the other routers of the deployment: everything, since each router enforces the rules on the
  sessions connected to it.
A session without a certificate signed by the deployment's CA is refused by TLS before any of this.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from common import keys
from common.messages import LARGEST_MESSAGE_BYTES
from deploy.certs import OPERATOR, ROUTER, cert_files, common_name
from deploy.manifest import Manifest

OBSERVE = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
EVERY_MESSAGE = ["put", "delete", "query", "reply", "declare_subscriber", "declare_queryable",
                 "liveliness_token", "liveliness_query", "declare_liveliness_subscriber"]
ALL_KEYS = [f"{keys.ROOT}/**"]
PATHS = f"{keys.ROOT}/paths/*"


@dataclass(frozen=True)
class Entitlement:
    """What one role may do on the bus, as key expressions."""
    puts: tuple[str, ...] = ()
    answers: tuple[str, ...] = ()     # queryables it declares and replies it sends
    asks: tuple[str, ...] = ()        # queries it sends
    token: str | None = None          # its liveliness token


def entitlement(role: str, robot: str) -> Entitlement:
    r, fleet = robot, keys.STORE_ROBOT
    if role == "bridge":
        return Entitlement(puts=(keys.clock(r), keys.odom(r), keys.stereo(r), keys.truth(r), keys.bridge_status(r),
                                 keys.trial_event(r)),
                           answers=(keys.control(r, "bridge"),), token=keys.alive(r, "bridge"))
    if role == "localizer":
        return Entitlement(puts=(keys.loc_state(r),), answers=(keys.control(r, "localizer"), PATHS),
                           token=keys.alive(r, "localizer"))
    if role == "controller":
        return Entitlement(puts=(keys.cmd_vel(r), keys.ctrl_status(r), keys.ctrl_model(r, "*"), keys.experience(r)),
                           answers=(keys.control(r, "controller"), keys.ctrl_model(r, "*")),
                           asks=(PATHS, keys.sched_schedule("*"), keys.store_window("*"), keys.store_hyper("*")),
                           token=keys.alive(r, "controller"))
    if role == "gp_store":
        return Entitlement(puts=(f"{keys.ROOT}/*/experience/ack", keys.store_hyper("*")),
                           answers=(keys.control(fleet, "gp_store"), keys.store_window("*"), keys.store_hyper("*"),
                                    keys.store_dump("*"), keys.store_fit("*"), keys.store_stats()),
                           asks=(PATHS,), token=keys.alive(fleet, "gp_store"))
    if role == "scheduler":
        return Entitlement(puts=(keys.sched_schedule("*"),),
                           answers=(keys.control(fleet, "scheduler"), keys.sched_schedule("*"), keys.sched_update("*")),
                           asks=(PATHS,), token=keys.alive(fleet, "scheduler"))
    if role == OPERATOR:
        return Entitlement(puts=(keys.ctrl_corridor(r),),
                           asks=(keys.control(r, "*"), keys.control(fleet, "*"), f"{keys.ROOT}/store/**",
                                 f"{keys.ROOT}/sched/**", PATHS, keys.ctrl_model(r, "*")))
    raise ValueError(f"no entitlement for role {role!r}")


def _rule(rule_id: str, messages: list[str], flows: list[str], key_exprs) -> dict:
    return {"id": rule_id, "permission": "allow", "messages": messages, "flows": flows, "key_exprs": list(key_exprs)}


def access_control(m: Manifest, robot: str) -> dict:
    """The same rules for every router of the deployment: a session is entitled by its certificate,
    whichever router it connects to."""
    rules = [_rule("observe", OBSERVE, ["ingress"], ALL_KEYS),
             _rule("deliver", EVERY_MESSAGE, ["egress"], ALL_KEYS),
             _rule("link", EVERY_MESSAGE, ["ingress", "egress"], ALL_KEYS)]
    subjects, policies = [], []
    routers = [common_name(h, ROUTER) for h in m.hosts]
    subjects.append({"id": "routers", "cert_common_names": routers})
    policies.append({"id": "routers", "rules": ["link"], "subjects": ["routers"]})
    sessions = [common_name(h, role) for h, spec in m.hosts.items() for role in (OPERATOR, *spec.services)]
    subjects.append({"id": "sessions", "cert_common_names": sessions})
    policies.append({"id": "sessions", "rules": ["observe", "deliver"], "subjects": ["sessions"]})
    for host, spec in m.hosts.items():
        for role in (OPERATOR, *spec.services):
            ent, who = entitlement(role, robot), common_name(host, role)
            own = []
            for name, messages, exprs in (("put", ["put"], ent.puts),
                                          ("answer", ["declare_queryable", "reply"], ent.answers),
                                          ("ask", ["query"], ent.asks),
                                          ("token", ["liveliness_token"], [ent.token] if ent.token else [])):
                if exprs:
                    rules.append(_rule(f"{who}:{name}", messages, ["ingress"], exprs))
                    own.append(f"{who}:{name}")
            subjects.append({"id": who, "cert_common_names": [who]})
            policies.append({"id": who, "rules": own, "subjects": [who]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _tls(m: Manifest, host: str, role: str, listen: bool) -> dict:
    f = cert_files(m, host, role)
    tls = {"root_ca_certificate": str(f.ca), "enable_mtls": True,
           "connect_certificate": str(f.cert), "connect_private_key": str(f.key)}
    if listen:
        tls.update({"listen_certificate": str(f.cert), "listen_private_key": str(f.key)})
    return tls


def _link(m: Manifest, host: str, role: str, listen: bool) -> dict:
    # Zenoh drops a message whose fragments add up to more than this while reassembling it, so a
    # flood of huge payloads costs at most this much memory per link, not the payload's size
    link: dict = {"rx": {"max_message_size": LARGEST_MESSAGE_BYTES}}
    if m.security == "mtls":
        link["tls"] = _tls(m, host, role, listen)
    return {"link": link}


def router_zid(m: Manifest, host: str) -> str:
    """A fixed Zenoh id per host's router (so that the other routers' configs can name it): 32 hex
    digits from the deployment's and the host's names, not starting with 0 (Zenoh refuses that)."""
    digest = hashlib.sha256(f"lbc-router/{m.name}/{host}".encode()).hexdigest()
    return "f" + digest[1:32]


def router_config(m: Manifest, host: str, robot: str) -> dict:
    spec = m.host(host)
    conf = {"mode": "router", "id": router_zid(m, host), "scouting": {"multicast": {"enabled": False}},
            "listen": {"endpoints": [spec.listen]},
            "connect": {"endpoints": [m.host(link).reach_endpoint for link in spec.links]},
            "transport": _link(m, host, ROUTER, listen=True)}
    others = [router_zid(m, h) for h in m.hosts if h != host]
    if others:
        # A publication this host's services send reliably (the localizer's estimates, say) also goes to
        # the other hosts' subscribers (the scheduler). Through a dead link that copy would fill the
        # queue and block this router's delivery to its own services too, for Zenoh's 5 s before it
        # gives the link up: the robot lost localization for 4.6 s with the learning host unplugged.
        # Between hosts, publications are therefore dropped rather than waited for; what must arrive
        # (experiences) is acknowledged and re-sent.
        conf["qos"] = {"network": [{"id": "between_hosts", "zids": others, "messages": ["put", "delete"],
                                    "flows": ["egress"], "overwrite": {"congestion_control": "drop"}}]}
    if m.security == "mtls":
        conf["access_control"] = access_control(m, robot)
    return conf


def session_config(m: Manifest, host: str, role: str) -> dict:
    """A service's or the operator's session: its certificate; mode and endpoint are set by the code."""
    return {"transport": _link(m, host, role, listen=False)}


def write_json5(conf: dict, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(conf, indent=2) + "\n")
    return path
