"""The `lbc` command line."""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import signal
import sys
import threading

from common.bus import DEFAULT_ENDPOINT, add_log_level_argument
from common.config import ConfigError

BENCHES = ("bus", "gp", "store", "controller", "localizer", "scenarios", "deployment", "codec", "stops")


def _raise_interrupt(_signum, _frame):
    raise KeyboardInterrupt


def _say(command: str, text: str) -> None:
    print(f"lbc {command}: {text}", file=sys.stderr)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("lbc")
    except PackageNotFoundError:   # run from a source tree that was never installed
        return "unknown"


def _operator_session(args) -> tuple[str | None, str | dict | None]:
    """Where the runner connects and with which Zenoh config: --connect/--zenoh-config, or the
    operator's endpoint and certificate on a manifest's host."""
    if args.manifest is None:
        if args.host is not None:
            raise ConfigError("--host needs --manifest")
        return args.connect, args.zenoh_config
    from common.scenario import load_scenario
    from deploy import access
    from deploy.certs import OPERATOR
    from deploy.manifest import load_manifest
    if args.host is None or args.connect is not None:
        raise ConfigError("--manifest needs --host NAME (and replaces --connect)")
    m = load_manifest(args.manifest)
    ours, theirs = load_scenario(args.scenario), m.load_scenario()
    if ours.robot.name != theirs.robot.name:
        raise ConfigError(f"{args.scenario} drives robot {ours.robot.name!r}, the deployment runs {theirs.robot.name!r}")
    conf = access.session_config(m, args.host, OPERATOR) if args.zenoh_config is None else args.zenoh_config
    return m.host(args.host).listen, conf


def _compare(args) -> int:
    import json
    from deploy.compare import CompareError, compare_dirs, describe
    try:
        c = compare_dirs(args.a, args.b, frozenset(args.ignore))
    except CompareError as exc:
        _say("experiment compare", str(exc))
        return 2
    print("\n".join(describe(c)))
    print(json.dumps(c.to_json()))
    return 0 if c.identical else 1


def _experiment(args) -> int:
    from deploy.experiment import ExperimentError, run_experiment
    signal.signal(signal.SIGTERM, _raise_interrupt)  # SIGTERM cleans up exactly like Ctrl-C
    try:
        connect, zenoh_conf = _operator_session(args)
        run_experiment(args.scenario, args.out, connect=connect, log_level=args.log_level,
                       overwrite=args.overwrite, connect_timeout_s=args.connect_timeout, zenoh_conf=zenoh_conf,
                       **({"ready_timeout_s": args.ready_timeout} if args.ready_timeout is not None else {}))
    except (ConfigError, ExperimentError) as exc:
        _say("experiment", str(exc))
        return 2 if isinstance(exc, ConfigError) else 1
    except KeyboardInterrupt:
        print(file=sys.stderr)
        _say("experiment", "interrupted; services stopped, summary of the finished trials kept")
        return 130
    return 0


def _launch(args) -> int:
    """Start router and services (a scenario on loopback, or one host of a manifest) until Ctrl-C."""
    from pathlib import Path

    from common.bus import install_stop_handlers
    from common.scenario import load_scenario
    from deploy.host import plan_host, plan_local, serve
    from deploy.manifest import load_manifest
    if (args.scenario is None) == (args.manifest is None) or (args.manifest is None) != (args.host is None):
        _say("launch", "give a SCENARIO, or --manifest FILE with --host NAME")
        return 2
    base = Path(args.dir)
    try:
        if args.manifest:
            m = load_manifest(args.manifest)
            plan = plan_host(m, args.host, base)
            hint = (f"Run: lbc experiment run {m.scenario} --out DIR --manifest {args.manifest} --host {args.host}   "
                    if "controller" in m.host(args.host).services else "")
        else:
            plan = plan_local(load_scenario(args.scenario), args.port, base)
            hint = f"Run: lbc experiment run {args.scenario} --out DIR --connect {plan.listen}   "
    except ConfigError as exc:
        _say("launch", str(exc))
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    return serve(plan, args.log_level, stop, lambda text: _say("launch", text), hint)


def _certs(args) -> int:
    from deploy.certs import make_certs
    from deploy.manifest import load_manifest
    try:
        m = load_manifest(args.manifest)
    except ConfigError as exc:
        _say("deploy certs", str(exc))
        return 2
    written = make_certs(m)
    print(f"CA {m.certs_dir}/ca.pem (its key ca.key stays here); {len(written)} certificates for hosts "
          f"{', '.join(m.hosts)}: copy ca.pem and <host>/ to each host", file=sys.stderr)
    return 0


def _check(args) -> int:
    import json

    from deploy.access_check import check_access
    from deploy.manifest import load_manifest
    try:
        m = load_manifest(args.manifest)
        m.host(args.host)
        sc = m.load_scenario()
    except ConfigError as exc:
        _say("deploy check", str(exc))
        return 2
    if m.security != "mtls":
        _say("deploy check", f"manifest {m.name} has security = {m.security!r}: there is no access control to check")
        return 1
    try:
        result = check_access(m, args.host, sc.robot.name, sc.path_id)
    except ConnectionError as exc:
        _say("deploy check", f"{exc}; is host {args.host} launched (lbc launch --manifest ... --host {args.host})?")
        return 1
    _say("deploy check", ("access control holds" if result.holds else "ACCESS CONTROL DOES NOT HOLD") +
         f" on host {args.host}: {result.rogue_puts_sent} puts and {result.rogue_control_requests} control requests "
         f"by certificates not entitled to them, {result.rogue_puts_delivered + result.rogue_control_replies} "
         f"got through; no certificate: {'refused' if result.unauthenticated_connect_refused else 'ACCEPTED'}")
    print(json.dumps(result.to_dict()))
    return 0 if result.holds else 1


def _bench(args) -> int:
    return importlib.import_module(f"bench.{args.name}").main(args.args)


def _fit_logs(args) -> int:
    from deploy import fit_logs
    return fit_logs.main(args.args)


def _view(args) -> int:
    from common.bus import install_stop_handlers
    from common.scenario import ConstraintsSection, load_scenario
    from deploy.view import serve
    try:
        if args.manifest is not None:
            from deploy import access
            from deploy.certs import OPERATOR
            from deploy.manifest import load_manifest
            if args.host is None or args.connect is not None:
                raise ConfigError("--manifest needs --host NAME (and replaces --connect)")
            m = load_manifest(args.manifest)
            endpoint, conf = m.host(args.host).listen, access.session_config(m, args.host, OPERATOR)
            corridor = m.load_scenario().constraints.lateral_m
        else:
            endpoint, conf = args.connect or DEFAULT_ENDPOINT, args.zenoh_config
            corridor = (load_scenario(args.scenario).constraints.lateral_m if args.scenario
                        else ConstraintsSection().lateral_m)
    except ConfigError as exc:
        _say("view", str(exc))
        return 2
    stop = threading.Event()
    install_stop_handlers(stop)
    return serve(endpoint, conf, corridor, args.address, args.port, stop, lambda text: _say("view", text))


def _router(args) -> int:
    from deploy import router
    return router.run(args)


def _help_of(parser: argparse.ArgumentParser):
    def show(_args) -> int:
        parser.print_help()
        return 0
    return show


def build_parser() -> argparse.ArgumentParser:
    from deploy import router, sched_cli, store_cli
    parser = argparse.ArgumentParser(prog="lbc", description="learning-based path-repeating control over Zenoh")
    parser.add_argument("--version", action="version", version=f"lbc {_version()}")
    parser.set_defaults(func=_help_of(parser))
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")

    exp_parser = sub.add_parser("experiment", help="run experiments")
    exp_parser.set_defaults(func=_help_of(exp_parser))
    exp_sub = exp_parser.add_subparsers(dest="sub", metavar="SUBCOMMAND")
    run = exp_sub.add_parser("run", help="teach and repeat a scenario through the real services")
    run.add_argument("scenario")
    run.add_argument("--out", required=True, help="output directory (summary.json, report.html, run.mcap)")
    run.add_argument("--connect", default=None, help="use a running deployment at this Zenoh endpoint")
    run.add_argument("--zenoh-config", default=None, metavar="FILE",
                     help="Zenoh JSON5 config of the runner's session (e.g. its TLS certificate)")
    run.add_argument("--manifest", default=None, help="run against a deployment manifest's host (with --host)")
    run.add_argument("--host", default=None, help="the manifest host to connect to, with its operator certificate")
    run.add_argument("--connect-timeout", type=float, default=30.0, metavar="S",
                     help="how long to wait for the router (default 30 s)")
    run.add_argument("--ready-timeout", type=float, default=None, metavar="S",
                     help="how long to wait for the services (default 60 s); against a running deployment, "
                          "the learning host's may stay missing after that and the run goes on without them")
    run.add_argument("--overwrite", action="store_true", help="replace an earlier run in the output directory")
    add_log_level_argument(run)
    run.set_defaults(func=_experiment)
    compare = exp_sub.add_parser(
        "compare", help="two runs of the same scenarios side by side: are they the same run, and where not, each "
                        "trial's figures; exit status 0 when every pair is the same run, 1 when not (as diff)")
    compare.add_argument("a", help="an experiment's output directory, or a directory of them (bench --out)")
    compare.add_argument("b", help="the same for the other run(s); directories of runs pair by name")
    compare.add_argument("--ignore", action="append", default=[], metavar="KEY",
                         help="leave this summary.json key out of the judgement, at the top level and in each "
                              "trial (repeatable; e.g. controller_note, where only a note's wording changed)")
    compare.set_defaults(func=_compare)

    launch = sub.add_parser("launch", help="start router and services (a scenario, or one host of a manifest) "
                                           "until Ctrl-C")
    launch.add_argument("scenario", nargs="?", default=None, help="one-host deployment on loopback")
    launch.add_argument("--manifest", default=None, help="deployment manifest (TOML): hosts, routers, services")
    launch.add_argument("--host", default=None, help="which host of the manifest this is")
    launch.add_argument("--port", type=int, default=7447, help="loopback port of a one-host deployment")
    launch.add_argument("--dir", default="runs/deployment", help="configs, logs and data of the deployment")
    add_log_level_argument(launch)
    launch.set_defaults(func=_launch)

    deploy_parser = sub.add_parser("deploy", help="deployment tools")
    deploy_parser.set_defaults(func=_help_of(deploy_parser))
    deploy_sub = deploy_parser.add_subparsers(dest="sub", metavar="SUBCOMMAND")
    certs = deploy_sub.add_parser(
        "certs", help="make the CA and every host's certificates for a manifest (mutual TLS, access control)")
    certs.add_argument("--manifest", required=True)
    certs.set_defaults(func=_certs)
    check = deploy_sub.add_parser("check", help="prove on a running deployment that its access control holds "
                                                "(from this host, with the certificates present here)")
    check.add_argument("--manifest", required=True)
    check.add_argument("--host", required=True, help="the host this runs on (its router is probed)")
    check.set_defaults(func=_check)

    store_cli.add_parser(sub)
    sched_cli.add_parser(sub)

    model = sub.add_parser("model", help="the learned model on a robot's own logs")
    model.set_defaults(func=_help_of(model))
    fit = model.add_subparsers(dest="sub", metavar="SUBCOMMAND").add_parser(
        "fit-logs", add_help=False, help="would learning help this robot? identify, fit the GP on training logs, "
                                         "report the held-out residuals (JSON on the last line; --help for more)")
    fit.add_argument("args", nargs=argparse.REMAINDER)
    fit.set_defaults(func=_fit_logs)

    view = sub.add_parser("view", help="serve the live bus to Foxglove (WebSocket), the channels of run.mcap")
    view.add_argument("--connect", default=None, help=f"the deployment's Zenoh endpoint (default {DEFAULT_ENDPOINT})")
    view.add_argument("--zenoh-config", default=None, metavar="FILE", help="Zenoh JSON5 config of the session (TLS)")
    view.add_argument("--manifest", default=None, help="connect to a manifest's host with its operator certificate")
    view.add_argument("--host", default=None, help="the manifest host to connect to")
    view.add_argument("--scenario", default=None, help="the corridor drawn is this scenario's (default: the "
                                                       "scenario default)")
    view.add_argument("--address", default="127.0.0.1", help="where the WebSocket server listens")
    view.add_argument("--port", type=int, default=8765, help="its port (Foxglove's default 8765)")
    view.set_defaults(func=_view)

    router_parser = sub.add_parser("router", help="run the local Zenoh router")
    router.add_arguments(router_parser)
    router_parser.set_defaults(func=_router)

    bench = sub.add_parser("bench", help="benchmarks; each prints one JSON object on its last line")
    bench.add_argument("name", choices=BENCHES)
    bench.add_argument("args", nargs=argparse.REMAINDER)
    bench.set_defaults(func=_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:   # Ctrl-C is how a user ends a command: no traceback
        print(file=sys.stderr)
        _say(args.command or "", "interrupted")
        return 130
    except BrokenPipeError:   # the reader went away (`lbc ... | head`): what it wanted is out, end quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # Python's own flush at exit would fail
        return 141


if __name__ == "__main__":
    raise SystemExit(main())
