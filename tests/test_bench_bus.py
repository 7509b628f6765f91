import json
import math
import os
from pathlib import Path

import pytest

from bench import bus


def _leftover_children() -> list[str]:
    """Our child processes that are the bench's router/responder, or zombies nobody waited for."""
    me, found = os.getpid(), []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
            cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        state, ppid = stat.rsplit(")", 1)[1].split()[:2]
        if int(ppid) == me and (state == "Z" or "bench.bus" in cmdline or "deploy.router" in cmdline):
            found.append(f"{proc.name} {state} {cmdline}")
    return found


@pytest.mark.integration
def test_bench_bus_reports_rtts_and_leaves_no_children(capsys):
    assert bus.main(["--n", "100", "--warmup", "20", "--log-level", "WARNING"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for kind in ("query", "pingpong"):
        p50, p99 = result[f"{kind}_rtt_ms_p50"], result[f"{kind}_rtt_ms_p99"]
        for v in (p50, p99):
            assert isinstance(v, float) and math.isfinite(v) and v > 0
        assert p99 >= p50
    assert result["n"] == 100 and result["payload_bytes"] > 0
    assert _leftover_children() == []
