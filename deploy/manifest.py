"""A deployment manifest: which hosts run which services, where each host's router listens and which
routers it links to. One TOML file describes the whole deployment; `lbc launch --manifest FILE --host
NAME` starts one host of it, `lbc deploy certs --manifest FILE` makes its certificates.

    name = "husky-two-host"
    scenario = "../examples/husky-sideslope.toml"   # the robot, route and service settings
    [hosts.robot]
    listen = "tls/10.0.0.1:7447"
    services = ["bridge", "localizer", "controller"]
    links = ["learning"]                            # this router connects to the learning host's
    [hosts.learning]
    listen = "tls/10.0.0.2:7447"
    services = ["gp_store", "scheduler"]
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from common import keys
from common.config import ConfigError, load_config
from common.messages import NAME_RE
from common.scenario import Scenario, load_scenario

Security = Literal["mtls", "none"]


@dataclass(frozen=True)
class HostSpec:
    listen: str                                        # this host's router endpoint, e.g. tls/10.0.0.1:7447
    services: list[str] = field(default_factory=list)  # the services this host runs
    links: list[str] = field(default_factory=list)     # hosts whose routers this host's router connects to
    # where the other hosts' routers connect to reach this one, when not `listen` (a NAT's port forward,
    # a proxy); its address must still be the one in `listen`, which the certificate names
    reach: str = ""

    @property
    def reach_endpoint(self) -> str:
        return self.reach or self.listen


@dataclass(frozen=True)
class Manifest:
    name: str
    scenario: str                                      # relative to the manifest file
    hosts: dict[str, HostSpec]
    security: Security = "mtls"                        # "none": plain TCP, no access control (a lab bench only)
    certs_dir: str = "certs"                           # relative to the manifest file

    def host(self, name: str) -> HostSpec:
        if name not in self.hosts:
            raise ConfigError(f"manifest {self.name}: no host {name!r} (hosts: {', '.join(self.hosts)})")
        return self.hosts[name]

    def host_of(self, service: str) -> str:
        return next(h for h, spec in self.hosts.items() if service in spec.services)

    def load_scenario(self) -> Scenario:
        return load_scenario(self.scenario)


@dataclass(frozen=True)
class Endpoint:
    protocol: str
    address: str
    port: int


def parse_endpoint(text: str, where: str) -> Endpoint:
    proto, sep, rest = text.partition("/")
    addr, colon, port = rest.rpartition(":")
    if not sep or not colon or proto not in ("tcp", "tls") or not port.isdigit() or not addr:
        raise ConfigError(f"{where}: {text!r} is not an endpoint like tls/10.0.0.1:7447 or tcp/host:7447")
    addr = addr.strip("[]")
    if addr in ("0.0.0.0", "::"):
        raise ConfigError(f"{where}: {text!r} listens on every interface; name the address the other hosts "
                          "reach (services connect to it and certificates are issued for it)")
    return Endpoint(proto, addr, int(port))


def load_manifest(path: str | Path) -> Manifest:
    """Load and check a manifest; its relative paths become absolute (relative to the file)."""
    m = load_config(Manifest, path)
    base = Path(path).resolve().parent
    m = replace(m, scenario=str(base / m.scenario), certs_dir=str(base / m.certs_dir))
    _check(m, str(path))
    return m


def _check(m: Manifest, where: str) -> None:
    if not m.hosts:
        raise ConfigError(f"{where}: no [hosts.*] tables")
    proto = "tls" if m.security == "mtls" else "tcp"
    seen: dict[str, str] = {}
    for name, spec in m.hosts.items():
        if not NAME_RE.match(name):
            raise ConfigError(f"{where}: host name {name!r} must be 1-64 characters of [A-Za-z0-9_-]")
        ep = parse_endpoint(spec.listen, f"{where}: hosts.{name}.listen")
        if spec.reach and parse_endpoint(spec.reach, f"{where}: hosts.{name}.reach").protocol != ep.protocol:
            raise ConfigError(f"{where}: hosts.{name}.reach must use {ep.protocol}/ like its listen endpoint")
        if ep.protocol != proto:
            raise ConfigError(f"{where}: hosts.{name}.listen is {ep.protocol}/ but security = {m.security!r} "
                              f"needs {proto}/")
        for link in spec.links:
            if link not in m.hosts or link == name:
                raise ConfigError(f"{where}: hosts.{name}.links names {link!r}, which is not another host")
        for s in spec.services:
            if s not in keys.SERVICES:
                raise ConfigError(f"{where}: hosts.{name}.services: unknown service {s!r} "
                                  f"(one of {', '.join(keys.SERVICES)})")
            if s in seen:
                raise ConfigError(f"{where}: {s} runs on both {seen[s]} and {name}; give it one host")
            seen[s] = name
    if len(m.hosts) > 1 and not any(spec.links for spec in m.hosts.values()):
        raise ConfigError(f"{where}: several hosts but no links between their routers")
