"""One host of a deployment: its router and its services, configured, started, watched and restarted.

`plan_local` is the one-host deployment of a scenario on loopback (`lbc launch SCENARIO`); `plan_host`
is one host of a manifest (`lbc launch --manifest FILE --host NAME`): its router listens where the
manifest says, links to the routers it names, and enforces mutual TLS and access control; its
services connect to it with their own certificates.
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from common import keys
from common.bus import open_session
from common.config import ConfigError
from common.scenario import Scenario
from deploy import access
from deploy.certs import OPERATOR, missing_certs
from deploy.configs import service_configs, write_service_configs
from deploy.experiment import FLEET_SERVICES, check_supported, services_of
from deploy.launcher import Launcher, LaunchError, port_in_use
from deploy.manifest import Manifest, parse_endpoint
from deploy.supervisor import Supervisor


@dataclass(frozen=True)
class HostPlan:
    host: str
    listen: str                               # the router's endpoint; the services connect to it
    port: int
    address: str
    router_conf: Path | None                  # Zenoh JSON5 of the router (links, TLS, access control)
    service_configs: dict[str, Path]          # service -> its TOML config
    session_confs: dict[str, Path]            # service or operator -> Zenoh JSON5 (its certificate)
    expected_alive: dict[str, str]            # service -> liveliness key
    log_dir: Path


def _alive_keys(sc: Scenario, services) -> dict[str, str]:
    return {s: keys.alive(keys.STORE_ROBOT if s in FLEET_SERVICES else sc.robot.name, s) for s in services}


def plan_local(sc: Scenario, port: int, base: Path) -> HostPlan:
    check_supported(sc)
    paths = write_service_configs(service_configs(sc, (base / "data").resolve()), base / "config")
    return HostPlan("local", f"tcp/127.0.0.1:{port}", port, "127.0.0.1", None, paths, {},
                    _alive_keys(sc, services_of(sc)), base / "logs")


def plan_host(m: Manifest, host: str, base: Path) -> HostPlan:
    """Write this host's configs under `base` (config/, zenoh/) and say how to start it."""
    spec = m.host(host)
    sc = m.load_scenario()
    check_supported(sc)
    unplaced = [s for s in services_of(sc) if not any(s in h.services for h in m.hosts.values())]
    if unplaced:
        raise ConfigError(f"manifest {m.name}: the scenario needs {', '.join(unplaced)}, which no host runs")
    if m.security == "mtls":
        missing = missing_certs(m, host)
        if missing:
            raise ConfigError(f"certificates of host {host} missing ({missing[0]}, ...): run "
                              f"`lbc deploy certs --manifest FILE` and copy {m.certs_dir}/ca.pem and "
                              f"{m.certs_dir}/{host}/ to this host")
    # a service the manifest places here but the scenario does not use (a scheduler switched off) stays down
    configs = {s: c for s, c in service_configs(sc, (base / "data").resolve()).items() if s in spec.services}
    paths = write_service_configs(configs, base / "config")
    zdir = base / "zenoh"
    router_conf = access.write_json5(access.router_config(m, host, sc.robot.name), zdir / "router.json5")
    sessions = {role: access.write_json5(access.session_config(m, host, role), zdir / f"{role}.json5")
                for role in (OPERATOR, *spec.services)}
    ep = parse_endpoint(spec.listen, f"hosts.{host}.listen")
    return HostPlan(host, spec.listen, ep.port, ep.address, router_conf, paths, sessions,
                    _alive_keys(sc, configs), base / "logs")


def serve(plan: HostPlan, log_level: str, stop: threading.Event, say: Callable[[str], None],
          ready_hint: str = "") -> int:
    """Start the router and services, say so once all are alive, then keep them running until `stop`."""
    if port_in_use(plan.port, plan.address):
        say(f"port {plan.port} on {plan.address} is already in use (another router or `lbc launch`?)")
        return 1
    with Launcher(plan.listen, plan.log_dir) as launcher:
        try:
            launcher.start_router(plan.port, plan.listen, plan.router_conf)
            launcher.wait_router()
            for s, cfg in plan.service_configs.items():
                launcher.start_service(s, cfg, log_level, plan.session_confs.get(s))
            session = open_session(plan.listen, stop=stop, timeout_s=15.0,
                                   zenoh_conf=_str(plan.session_confs.get(OPERATOR)))
            try:
                up = launcher.wait_alive(session, plan.expected_alive, stop=stop)
            finally:
                session.close()
        except (LaunchError, ConnectionError, ValueError) as exc:
            if stop.is_set():
                return 130
            say(f"{exc}\n(logs in {plan.log_dir})")
            return 1
        if not up:
            return 130
        say(f"host {plan.host}: router on {plan.listen}; services {', '.join(plan.service_configs) or 'none'} up; "
            f"logs in {plan.log_dir}. {ready_hint}(Ctrl-C stops)")
        supervisor = Supervisor(launcher, say)
        while not stop.wait(0.5):
            reason = supervisor.poll()
            if reason:
                say(reason)
                return 1
    say("stopped")
    return 0


def _str(path: Path | None) -> str | None:
    return None if path is None else str(path)
