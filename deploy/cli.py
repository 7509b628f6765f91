"""The `lbc` command line."""
from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading

from common.bus import add_log_level_argument
from common.config import ConfigError

BENCHES = ("bus", "gp", "store", "controller", "localizer", "scenarios")


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


def _experiment(args) -> int:
    from deploy.experiment import ExperimentError, run_experiment
    signal.signal(signal.SIGTERM, _raise_interrupt)  # SIGTERM cleans up exactly like Ctrl-C
    try:
        run_experiment(args.scenario, args.out, connect=args.connect, log_level=args.log_level,
                       overwrite=args.overwrite, connect_timeout_s=args.connect_timeout)
    except (ConfigError, ExperimentError) as exc:
        _say("experiment", str(exc))
        return 2 if isinstance(exc, ConfigError) else 1
    except KeyboardInterrupt:
        print(file=sys.stderr)
        _say("experiment", "interrupted; services stopped, summary of the finished trials kept")
        return 130
    return 0


def _launch(args) -> int:
    """Start router and services for a scenario and keep them up until Ctrl-C."""
    from pathlib import Path

    from common.scenario import load_scenario
    from deploy.configs import service_configs, write_service_configs
    from deploy.experiment import check_supported
    from deploy.launcher import port_in_use
    try:
        sc = load_scenario(args.scenario)
        check_supported(sc)
    except ConfigError as exc:
        _say("launch", str(exc))
        return 2
    if port_in_use(args.port):
        _say("launch", f"port {args.port} on 127.0.0.1 is already in use (another router or `lbc launch`?); "
                       "stop it or choose another with --port")
        return 1
    base = Path(args.dir)
    paths = write_service_configs(service_configs(sc, (base / "data").resolve()), base / "config")
    return _keep_deployment_up(args, sc, paths, base)


def _keep_deployment_up(args, sc, paths: dict, base) -> int:
    """Say that the deployment is up only once the router listens and every service is alive."""
    from common import keys
    from common.bus import install_stop_handlers, open_session
    from deploy.experiment import FLEET_SERVICES, services_of
    from deploy.launcher import Launcher, LaunchError
    endpoint = f"tcp/127.0.0.1:{args.port}"
    services = services_of(sc)
    expected = {s: keys.alive(keys.STORE_ROBOT if s in FLEET_SERVICES else sc.robot.name, s) for s in services}
    stop = threading.Event()
    install_stop_handlers(stop)
    with Launcher(endpoint, base / "logs") as launcher:
        try:
            launcher.start_router(args.port)
            launcher.wait_router()
            for s in services:
                launcher.start_service(s, paths[s], args.log_level)
            session = open_session(endpoint, stop=stop, timeout_s=15.0)
            try:
                up = launcher.wait_alive(session, expected, stop=stop)
            finally:
                session.close()
        except (LaunchError, ConnectionError) as exc:
            if stop.is_set():
                return 130
            _say("launch", f"{exc}\n(logs in {base / 'logs'})")
            return 1
        if not up:
            return 130
        print(f"router on {endpoint}; services {', '.join(services)} up; logs in {base / 'logs'}. "
              f"Run: lbc experiment run {args.scenario} --out DIR --connect {endpoint}   (Ctrl-C stops)",
              file=sys.stderr)
        while not stop.wait(0.5):
            dead = launcher.exited()
            if dead:
                _say("launch", f"{dead[0].name} exited ({dead[0].proc.returncode}):\n{dead[0].tail()}")
                return 1
    _say("launch", "stopped")
    return 0


def _bench(args) -> int:
    return importlib.import_module(f"bench.{args.name}").main(args.args)


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
    run = exp_parser.add_subparsers(dest="sub", metavar="SUBCOMMAND").add_parser(
        "run", help="teach and repeat a scenario through the real services")
    run.add_argument("scenario")
    run.add_argument("--out", required=True, help="output directory (summary.json, report.html, run.mcap)")
    run.add_argument("--connect", default=None, help="use a running deployment at this Zenoh endpoint")
    run.add_argument("--connect-timeout", type=float, default=30.0, metavar="S",
                     help="how long to wait for the router (default 30 s)")
    run.add_argument("--overwrite", action="store_true", help="replace an earlier run in the output directory")
    add_log_level_argument(run)
    run.set_defaults(func=_experiment)

    launch = sub.add_parser("launch", help="start router and services for a scenario until Ctrl-C")
    launch.add_argument("scenario")
    launch.add_argument("--port", type=int, default=7447)
    launch.add_argument("--dir", default="runs/deployment", help="configs, logs and data of the deployment")
    add_log_level_argument(launch)
    launch.set_defaults(func=_launch)

    store_cli.add_parser(sub)
    sched_cli.add_parser(sub)

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


if __name__ == "__main__":
    raise SystemExit(main())
