"""Two hosts on one machine: a network namespace each (own interfaces, addresses, ports), joined by a
veth pair, for tests and `lbc bench deployment`. Needs root (`ip netns`)."""
from __future__ import annotations

import os
import subprocess


class NetnsUnavailable(RuntimeError):
    """Namespaces cannot be made here (not root, no iproute2, a container without CAP_NET_ADMIN)."""


def _sh(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=30)


class TwoHosts:
    """`robot` and `learning`, at <subnet>.1 and <subnet>.2; names are unique per process."""

    HOSTS = ("robot", "learning")

    def __init__(self, tag: str | None = None):
        tag = tag or str(os.getpid() % 100000)
        self.ns = {"robot": f"lbcR{tag}", "learning": f"lbcL{tag}"}
        self.veth = {"robot": f"lvR{tag}", "learning": f"lvL{tag}"}
        subnet = f"10.{200 + os.getpid() % 50}.{os.getpid() % 250}"
        self.addr = {"robot": f"{subnet}.1", "learning": f"{subnet}.2"}

    def prefix(self, host: str) -> tuple[str, ...]:
        """Prepend to a command to run it on `host`."""
        return ("ip", "netns", "exec", self.ns[host])

    def __enter__(self) -> "TwoHosts":
        if os.geteuid() != 0:
            raise NetnsUnavailable("network namespaces need root")
        try:
            for host in self.HOSTS:
                _sh("ip", "netns", "add", self.ns[host])
                _sh(*self.prefix(host), "ip", "link", "set", "lo", "up")
            _sh("ip", "link", "add", self.veth["robot"], "type", "veth", "peer", "name", self.veth["learning"])
            for host in self.HOSTS:
                _sh("ip", "link", "set", self.veth[host], "netns", self.ns[host])
                _sh(*self.prefix(host), "ip", "addr", "add", f"{self.addr[host]}/24", "dev", self.veth[host])
                _sh(*self.prefix(host), "ip", "link", "set", self.veth[host], "up")
        except (subprocess.CalledProcessError, FileNotFoundError) as exc:
            self.close()
            raise NetnsUnavailable(f"cannot make network namespaces here: "
                                   f"{getattr(exc, 'stderr', '') or exc}".strip()) from None
        return self

    def link(self, up: bool) -> None:
        """Take the link between the hosts down (as a cable pulled) or up again."""
        _sh(*self.prefix("robot"), "ip", "link", "set", self.veth["robot"], "up" if up else "down")

    def close(self) -> None:
        for host in self.HOSTS:     # deleting a namespace deletes its end of the veth, and so the pair
            subprocess.run(["ip", "netns", "del", self.ns[host]], capture_output=True, timeout=30)

    def __exit__(self, *exc) -> None:
        self.close()
