"""The `lbc` command line."""
from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import threading

from common.config import ConfigError

BENCHES = ("bus", "gp", "store", "controller", "localizer")


def _raise_interrupt(_signum, _frame):
    raise KeyboardInterrupt


def _experiment(args) -> int:
    from deploy.experiment import ExperimentError, run_experiment
    signal.signal(signal.SIGTERM, _raise_interrupt)  # SIGTERM cleans up exactly like Ctrl-C
    try:
        run_experiment(args.scenario, args.out, connect=args.connect, log_level=args.log_level,
                       overwrite=args.overwrite)
    except (ConfigError, ExperimentError) as exc:
        print(f"lbc experiment: {exc}", file=sys.stderr)
        return 2 if isinstance(exc, ConfigError) else 1
    except KeyboardInterrupt:
        print("\nlbc experiment: interrupted; services stopped, partial summary kept", file=sys.stderr)
        return 130
    return 0


def _launch(args) -> int:
    """Start router and services for a scenario and keep them up until Ctrl-C."""
    from pathlib import Path

    from common.bus import install_stop_handlers
    from common.scenario import load_scenario
    from deploy.configs import service_configs, write_service_configs
    from deploy.experiment import check_supported, services_of
    from deploy.launcher import Launcher
    try:
        sc = load_scenario(args.scenario)
        check_supported(sc)
    except ConfigError as exc:
        print(f"lbc launch: {exc}", file=sys.stderr)
        return 2
    base = Path(args.dir)
    paths = write_service_configs(service_configs(sc, (base / "data").resolve()), base / "config")
    endpoint = f"tcp/127.0.0.1:{args.port}"
    stop = threading.Event()
    install_stop_handlers(stop)
    with Launcher(endpoint, base / "logs") as launcher:
        launcher.start_router(args.port)
        for s in services_of(sc):
            launcher.start_service(s, paths[s], args.log_level)
        print(f"router on {endpoint}; services {', '.join(services_of(sc))}; logs in {base / 'logs'}. "
              f"Run: lbc experiment run {args.scenario} --out DIR --connect {endpoint}   (Ctrl-C stops)",
              file=sys.stderr)
        while not stop.wait(0.5):
            dead = launcher.exited()
            if dead:
                print(f"lbc launch: {dead[0].name} exited ({dead[0].proc.returncode}):\n{dead[0].tail()}",
                      file=sys.stderr)
                return 1
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lbc", description="learning-based path-repeating control over Zenoh")
    sub = parser.add_subparsers(dest="command", required=True)

    exp = sub.add_parser("experiment", help="run experiments").add_subparsers(dest="sub", required=True)
    run = exp.add_parser("run", help="teach and repeat a scenario through the real services")
    run.add_argument("scenario")
    run.add_argument("--out", required=True, help="output directory (summary.json, report.html, run.mcap)")
    run.add_argument("--connect", default=None, help="use a running deployment at this Zenoh endpoint")
    run.add_argument("--overwrite", action="store_true", help="replace an earlier run in the output directory")
    run.add_argument("--log-level", default="INFO")
    run.set_defaults(func=_experiment)

    launch = sub.add_parser("launch", help="start router and services for a scenario until Ctrl-C")
    launch.add_argument("scenario")
    launch.add_argument("--port", type=int, default=7447)
    launch.add_argument("--dir", default="runs/deployment", help="configs, logs and data of the deployment")
    launch.add_argument("--log-level", default="INFO")
    launch.set_defaults(func=_launch)

    from deploy import sched_cli, store_cli
    store_cli.add_parser(sub)
    sched_cli.add_parser(sub)

    router = sub.add_parser("router", help="run the local Zenoh router")
    router.add_argument("args", nargs=argparse.REMAINDER)
    router.set_defaults(func=lambda a: importlib.import_module("deploy.router").main(a.args))

    bench = sub.add_parser("bench", help="benchmarks; each prints one JSON object on its last line")
    bench.add_argument("name", choices=BENCHES)
    bench.add_argument("args", nargs=argparse.REMAINDER)
    bench.set_defaults(func=lambda a: importlib.import_module(f"bench.{a.name}").main(a.args))

    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    return int(args.func(args) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
