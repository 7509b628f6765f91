"""`lbc store ...`: look into, fit, export and import the experience store of a running deployment."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path as FsPath

import msgpack
import numpy as np
from mcap.reader import make_reader
from mcap.writer import Writer

from common import keys
from common.bus import DEFAULT_ENDPOINT, Node, open_session, query, query_one
from common.codec import DecodeError, decode
from common.messages import ExperienceBatch, ExperienceWindow, HyperMsg, StoreStats
from common.store_client import ExperienceOutbox
from services.controller.experience import A_NAMES, G_NAMES

EXPORT_TOPIC = "lbc/store/{path}/experiences"


class StoreCliError(RuntimeError):
    pass


def _stats(session, _args) -> int:
    replies = query(session, keys.store_stats(), timeout_s=5.0)
    stores = [decode(StoreStats, r.payload) for r in replies if r.error is None]
    if not stores:
        raise StoreCliError("no experience store answered on " + keys.store_stats())
    for st in stores:
        print(f"store {st.store}  ({st.db_path})")
        print(f"  {'route':24s} {'retained':>9s} {'ingested':>9s} {'bins':>6s} {'hyper':>6s}")
        for p in st.paths:
            print(f"  {p.path_id:24s} {p.retained:9d} {p.ingested:9d} {p.bins:6d} {'v' + str(p.hyper_version):>6s}")
    return 0


def _query(session, args) -> int:
    sel = f"{keys.store_window(args.path)}?vertex={args.vertex}&speed={args.speed}"
    if args.model:
        sel += f"&model={args.model}"
    try:
        w = query_one(session, sel, ExperienceWindow, timeout_s=5.0)
    except LookupError as exc:
        raise StoreCliError(str(exc)) from None
    A = np.frombuffer(w.a_f64, "<f8").reshape(-1, len(A_NAMES))
    G = np.frombuffer(w.g_f64, "<f8").reshape(-1, len(G_NAMES))
    print(f"{len(A)} experiences in vertices {w.vertex_lo}..{w.vertex_hi} x speed bins {w.bin_lo}..{w.bin_hi} "
          f"({w.v_bin_mps} m/s each) of route {w.path_id}")
    if args.json:
        print(json.dumps({"vertices": w.vertices, "speed_bins": w.speed_bins,
                          "a": {n: A[:, i].tolist() for i, n in enumerate(A_NAMES)},
                          "g": {n: G[:, i].tolist() for i, n in enumerate(G_NAMES)}}))
    elif len(A):
        for i, n in enumerate(G_NAMES):
            print(f"  g.{n:12s} mean {G[:, i].mean():+.5f}  std {G[:, i].std():.5f}")
    return 0


def _fit(session, args) -> int:
    t0 = time.monotonic()
    print(f"fitting GP hyperparameters for {args.path} ...", file=sys.stderr)
    try:
        h = query_one(session, keys.store_fit(args.path), HyperMsg, timeout_s=args.timeout)
    except LookupError as exc:
        raise StoreCliError(str(exc)) from None
    print(f"{args.path}: hyperparameters v{h.version} from {h.n_used}/{h.n_total} experiences of nominal model "
          f"{h.model or 'untagged'}, fit {h.fit_s:.1f} s ({time.monotonic() - t0:.1f} s wall)")
    for name, dim, lml in zip(G_NAMES, h.dims, h.lml):
        ells = ", ".join(f"{n}={v:.3g}" for n, v in zip(A_NAMES, dim.lengthscales))
        print(f"  {name:12s} sigma_f={dim.signal_std:.3g} sigma_n={dim.noise_std:.3g} LML={lml:.1f}\n    lengthscales: {ells}")
    return 0


def _export(session, args) -> int:
    replies = query(session, keys.store_dump(args.path), timeout_s=60.0)
    errors = [r.error for r in replies if r.error is not None]
    if errors:
        raise StoreCliError(f"export of {args.path} failed: {errors[0]}")
    out = FsPath(args.out)
    n = 0
    with open(out, "wb") as fh:
        writer = Writer(fh)
        writer.start(profile="", library="lbc")
        try:
            sid = writer.register_schema(name="ExperienceBatch", encoding="", data=b"")
            ch = writer.register_channel(topic=EXPORT_TOPIC.format(path=args.path), message_encoding="msgpack",
                                         schema_id=sid)
            writer.add_metadata("lbc-export", {"path_id": args.path, "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
                                               "schema_version": str(ExperienceBatch.SCHEMA_VERSION)})
            for seq, rep in enumerate(replies):
                batch = decode(ExperienceBatch, rep.payload)
                n += len(batch.experiences)
                t = time.time_ns()
                writer.add_message(channel_id=ch, log_time=t, publish_time=t, data=rep.payload, sequence=seq)
        finally:
            writer.finish()
    print(f"exported {n} experiences of {args.path} to {out}")
    return 0


def _decode_batch(data: bytes) -> ExperienceBatch:
    """One exported batch. An export written before experiences carried their nominal model (their
    maps have no "model") is read with model "" (unknown); anything else malformed is an error."""
    try:
        return decode(ExperienceBatch, data)
    except DecodeError:
        try:
            body = msgpack.unpackb(data, raw=False)
        except Exception:
            raise DecodeError("not valid msgpack") from None
        exps = body.get("experiences") if isinstance(body, dict) else None
        if not isinstance(exps, list) or not all(isinstance(e, dict) and "model" not in e for e in exps):
            raise
        for e in exps:
            e["model"] = ""
        return decode(ExperienceBatch, msgpack.packb(body, use_bin_type=True))


def _import(session, args, endpoint: str) -> int:
    batches = []
    with open(args.file, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.message_encoding != "msgpack" or not channel.topic.endswith("/experiences"):
                continue
            try:
                batches.append(_decode_batch(message.data))
            except DecodeError as exc:
                raise StoreCliError(f"{args.file}: bad experience batch on {channel.topic}: {exc}") from None
    if not batches:
        raise StoreCliError(f"{args.file}: no experience batches (is it an `lbc store export` file?)")
    node = Node("store-import", args.robot, endpoint)
    try:
        outboxes: dict[str, ExperienceOutbox] = {}
        for b in batches:
            box = outboxes.get(b.source)
            if box is None:   # keep each experience's (source, seq): importing twice stores it once
                box = outboxes[b.source] = ExperienceOutbox(node, args.robot, source=b.source)
            for e in b.experiences:
                box.add_existing(e)
        total = sum(len(b.experiences) for b in batches)
        for box in outboxes.values():
            if not box.wait_acked(args.timeout):
                raise StoreCliError(f"{box.pending} experiences were not acknowledged by a store")
        rejected = sum(box.rejected for box in outboxes.values())
        print(f"imported {total - rejected} experiences ({rejected} rejected) from {args.file}")
        return 0 if rejected == 0 else 1
    finally:
        node.close()


def add_parser(sub) -> None:
    group = sub.add_parser("store", help="inspect and manage the experience store")
    group.set_defaults(func=lambda _args: group.print_help() or 0)   # `lbc store` alone: its help
    store = group.add_subparsers(dest="sub", metavar="SUBCOMMAND")

    def common(p):
        p.add_argument("--connect", default=DEFAULT_ENDPOINT, help="Zenoh router of the deployment")
        return p
    common(store.add_parser("stats", help="experiences and hyperparameters per route"))
    q = common(store.add_parser("query", help="the local window of a vertex and speed"))
    q.add_argument("--path", required=True)
    q.add_argument("--vertex", type=int, required=True)
    q.add_argument("--speed", type=float, required=True)
    q.add_argument("--model", default="", help="the nominal model's experiences (e.g. unicycle-dt100ms-tauv0ms-"
                                               "tauw400ms; default: that of the route's newest experience)")
    q.add_argument("--json", action="store_true", help="print every experience as JSON")
    f = common(store.add_parser("fit", help="fit GP hyperparameters now and wait for them"))
    f.add_argument("--path", required=True)
    f.add_argument("--timeout", type=float, default=1800.0)
    e = common(store.add_parser("export", help="write a route's experiences to an MCAP file"))
    e.add_argument("--path", required=True)
    e.add_argument("--out", required=True)
    i = common(store.add_parser("import", help="send the experiences of an exported MCAP file to the store"))
    i.add_argument("file")
    i.add_argument("--robot", default="import", help="robot name used for the acknowledgements")
    i.add_argument("--timeout", type=float, default=120.0)
    for name in ("stats", "query", "fit", "export", "import"):
        store.choices[name].set_defaults(func=run)


def run(args) -> int:
    try:
        session = open_session(args.connect, timeout_s=10.0)
    except (ConnectionError, ValueError) as exc:   # no router there / a malformed endpoint
        print(f"lbc store: {exc}", file=sys.stderr)
        return 2
    try:
        if args.sub == "import":
            return _import(session, args, args.connect)
        return {"stats": _stats, "query": _query, "fit": _fit, "export": _export}[args.sub](session, args)
    except (StoreCliError, OSError) as exc:
        print(f"lbc store {args.sub}: {exc}", file=sys.stderr)
        return 1
    finally:
        session.close()
