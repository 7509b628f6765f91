"""`lbc sched show --path P`: the speed schedule a running scheduler has for a route."""
from __future__ import annotations

import json
import sys

import numpy as np

from common import keys
from common.bus import DEFAULT_ENDPOINT, open_session, query_one
from common.messages import SpeedSchedule


def _show(args) -> int:
    try:
        session = open_session(args.connect, timeout_s=10.0)
    except (ConnectionError, ValueError) as exc:   # no router there / a malformed endpoint
        print(f"lbc sched: {exc}", file=sys.stderr)
        return 2
    try:
        s = query_one(session, keys.sched_schedule(args.path), SpeedSchedule, timeout_s=10.0)
    except LookupError as exc:
        print(f"lbc sched show: {exc}", file=sys.stderr)
        return 1
    finally:
        session.close()
    if args.json:
        print(json.dumps({"path_id": s.path_id, "version": s.version, "based_on_robot": s.based_on_robot,
                          "based_on_trial": s.based_on_trial, "v_mps": s.v_mps, "decisions": s.decisions,
                          "notes": s.notes}))
        return 0
    v, d = np.asarray(s.v_mps), np.asarray(s.decisions)
    origin = f"from {s.based_on_robot} trial {s.based_on_trial}" if s.based_on_robot else "the first trial's"
    print(f"route {s.path_id}: schedule v{s.version} ({origin}), {len(v)} vertices, "
          f"{v.min():.2f}-{v.max():.2f} m/s, mean {v.mean():.2f} m/s")
    print(f"  last decisions: {int(np.sum(d > 0))} faster, {int(np.sum(d == 0))} kept, {int(np.sum(d < 0))} slower")
    for n in s.notes:
        print(f"  note: {n}")
    step = max(1, len(v) // 20)
    print("  vertex  v_mps")
    for i in range(0, len(v), step):
        print(f"  {i:6d}  {v[i]:.2f}")
    return 0


def add_parser(sub) -> None:
    group = sub.add_parser("sched", help="inspect the speed scheduler")
    group.set_defaults(func=lambda _args: group.print_help() or 0)   # `lbc sched` alone: its help
    sched = group.add_subparsers(dest="sub", metavar="SUBCOMMAND")
    show = sched.add_parser("show", help="the latest speed schedule of a route")
    show.add_argument("--path", required=True)
    show.add_argument("--json", action="store_true")
    show.add_argument("--connect", default=DEFAULT_ENDPOINT, help="Zenoh router of the deployment")
    show.set_defaults(func=_show)
