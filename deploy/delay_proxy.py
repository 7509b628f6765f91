"""A TCP proxy that delays every byte by a fixed time in each direction: a long link between two
routers (a robot on a cellular link, a store in another building) where kernel netem is missing.
Order is kept; bandwidth is not limited. TLS passes through untouched (it is only bytes here).

    python -m deploy.delay_proxy --listen 10.0.0.2:7448 --to 10.0.0.2:7447 --delay-ms 50
"""
from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import time

from common.bus import add_log_level_argument, setup_logging
from common.lifecycle import die_with_parent

READY_LINE = "delay proxy listening on"
CHUNK = 64 * 1024


async def _pipe(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, delay_s: float) -> None:
    """Copy reader to writer, each chunk released `delay_s` after it arrived, in order."""
    queue: asyncio.Queue = asyncio.Queue()

    async def release() -> None:
        while True:
            due, data = await queue.get()
            if data is None:
                break
            wait = due - time.monotonic()
            if wait > 0:
                await asyncio.sleep(wait)
            writer.write(data)
            await writer.drain()
        writer.close()

    sender = asyncio.create_task(release())
    try:
        while data := await reader.read(CHUNK):
            queue.put_nowait((time.monotonic() + delay_s, data))
    except (ConnectionError, OSError):
        pass
    finally:
        queue.put_nowait((0.0, None))
        try:
            await sender
        except (ConnectionError, OSError):
            pass


async def serve(listen_host: str, listen_port: int, to_host: str, to_port: int, delay_s: float,
                log: logging.Logger, stop: asyncio.Event) -> None:
    async def on_client(c_reader, c_writer) -> None:
        try:
            s_reader, s_writer = await asyncio.open_connection(to_host, to_port)
        except OSError as exc:
            log.warning("cannot reach %s:%d: %s", to_host, to_port, exc)
            c_writer.close()
            return
        await asyncio.gather(_pipe(c_reader, s_writer, delay_s), _pipe(s_reader, c_writer, delay_s))

    server = await asyncio.start_server(on_client, listen_host, listen_port)
    log.info("%s %s:%d -> %s:%d, %.0f ms each way", READY_LINE, listen_host, listen_port, to_host, to_port,
             delay_s * 1e3)
    async with server:
        await stop.wait()


def _split(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host, int(port)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m deploy.delay_proxy", description=__doc__.splitlines()[0])
    parser.add_argument("--listen", required=True, metavar="HOST:PORT")
    parser.add_argument("--to", required=True, metavar="HOST:PORT")
    parser.add_argument("--delay-ms", type=float, required=True)
    add_log_level_argument(parser)
    args = parser.parse_args(argv)
    die_with_parent()
    log = setup_logging("delay_proxy", args.log_level)

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        await serve(*_split(args.listen), *_split(args.to), args.delay_ms / 1e3, log, stop)
    asyncio.run(run())
    log.info("delay proxy stopped")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
