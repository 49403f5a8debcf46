"""A TCP relay that delays and stalls what it forwards: the bad link between two test hosts.

``python relay.py --listen 127.0.0.1:7500 --to 10.0.0.2:7447 --delay-ms 50 --jitter-ms 20``
accepts connections on ``--listen`` and forwards each to ``--to``, both directions. Every chunk
read is held ``delay +- jitter`` ms (uniform, seeded) before it is written on, never overtaking
the chunk before it, so the byte stream keeps its order. SIGUSR1 stalls forwarding (chunks wait),
SIGUSR2 lets them go again. When one side closes, the other is closed too. At exit (SIGTERM) it
writes the delays it applied (``--stats FILE``, JSON).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import random
import signal
import statistics
import time


class Relay:
    def __init__(self, target: tuple[str, int], delay_s: float, jitter_s: float, seed: int) -> None:
        self.target = target
        self.delay_s = delay_s
        self.jitter_s = jitter_s
        self.rng = random.Random(seed)
        self.applied: list[float] = []
        self.stalled = asyncio.Event()  # set while stalled
        self.connections = 0
        self.bytes = 0

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_r, up_w = await asyncio.open_connection(*self.target)
        except OSError:
            writer.close()
            return
        self.connections += 1
        tasks = [asyncio.ensure_future(self.pipe(reader, up_w)), asyncio.ensure_future(self.pipe(up_r, writer))]
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for w in (writer, up_w):  # one side gone: the other is closed too
            w.close()
        await asyncio.gather(*tasks, return_exceptions=True)

    async def pipe(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        queue: asyncio.Queue = asyncio.Queue()

        async def sender() -> None:
            try:
                while True:
                    due, data = await queue.get()
                    if data is None:
                        break
                    wait = due - time.monotonic()
                    if wait > 0:
                        await asyncio.sleep(wait)
                    while self.stalled.is_set():
                        await asyncio.sleep(0.01)
                    writer.write(data)
                    await writer.drain()
                    self.bytes += len(data)
            except (OSError, ConnectionError):
                reader.feed_eof()  # the far side is gone: stop reading this direction

        task = asyncio.ensure_future(sender())
        last_due = 0.0
        try:
            while True:
                data = await reader.read(65536)
                if not data:
                    break
                d = max(0.0, self.delay_s + self.rng.uniform(-self.jitter_s, self.jitter_s))
                if len(self.applied) < 200_000:
                    self.applied.append(d)
                last_due = max(last_due, time.monotonic() + d)  # never overtakes the previous chunk
                await queue.put((last_due, data))
        except (OSError, asyncio.IncompleteReadError):
            pass
        finally:
            await queue.put((0.0, None))
            try:
                await task
            except Exception:
                pass
            try:
                writer.close()
            except Exception:
                pass

    def stats(self) -> dict:
        ms = [d * 1e3 for d in self.applied]
        return {"connections": self.connections, "bytes": self.bytes, "chunks": len(ms),
                "delay_mean_ms": statistics.fmean(ms) if ms else None,
                "delay_min_ms": min(ms) if ms else None, "delay_max_ms": max(ms) if ms else None}


async def main(args: argparse.Namespace) -> None:
    host, port = args.listen.rsplit(":", 1)
    thost, tport = args.to.rsplit(":", 1)
    relay = Relay((thost, int(tport)), args.delay_ms / 1e3, args.jitter_ms / 1e3, args.seed)
    server = await asyncio.start_server(relay.handle, host, int(port))
    done = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGUSR1, relay.stalled.set)
    loop.add_signal_handler(signal.SIGUSR2, relay.stalled.clear)
    loop.add_signal_handler(signal.SIGTERM, done.set)
    loop.add_signal_handler(signal.SIGINT, done.set)
    print("relay ready", flush=True)
    async with server:
        await done.wait()
    if args.stats:
        with open(args.stats, "w") as fh:
            json.dump(relay.stats(), fh)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--listen", required=True)
    p.add_argument("--to", required=True)
    p.add_argument("--delay-ms", type=float, default=0.0)
    p.add_argument("--jitter-ms", type=float, default=0.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--stats")
    asyncio.run(main(p.parse_args()))
