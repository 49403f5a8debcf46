"""Transport between two worker processes: message rate and latency, SHM on/off.

Writes bench/results/transport.json. For each payload (1 KB, 260 KB = one AlexNet conv3 feature
vector, 1 MB) and shared memory on/off:

* throughput: the publisher sends as fast as it can for ``--seconds`` in lossless mode (congestion
  control BLOCK into the subscriber's bounded FIFO, exactly as pipeline workers do); msg/s and MB/s
  at the subscriber;
* latency: 200 messages paced at 100 Hz, one-way time from ``put`` to the subscriber's queue
  (both processes read the same CLOCK_REALTIME), p50/p95.

Run: ``.venv/bin/python bench/transport.py [--seconds 2]``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import platform
import struct
import time
from pathlib import Path

import numpy as np

from neoslam_stream.runtime.bus import Bus, InputQueue, open_session, wait_for_peers
from neoslam_stream.runtime.ports import free_port

HEADER = struct.Struct("<qd")  # sequence number, send time


def subscriber(ep: str, shm: bool, n_expected: int, q: mp.Queue, ready: mp.Event) -> None:
    session = open_session(listen=[ep], shm=shm)
    bus = Bus(session, "bench", lossless=True)
    inq = InputQueue({"x": 16}, lossless=True)
    bus.subscribe("x", inq)
    ready.set()
    got, lat, t_first, t_last, nbytes = 0, [], None, None, 0
    t_last_mono = time.monotonic()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        item = inq.get(timeout=1.0)
        if item is None:
            if got and time.monotonic() - t_last_mono > 1.0:
                break
            continue
        _, payload, received = item
        seq, sent = HEADER.unpack_from(payload, 0)
        if seq < 0:
            break
        np.frombuffer(payload, dtype=np.uint8)  # what a numpy consumer does
        got += 1
        nbytes += len(payload)
        lat.append(received - sent)
        t_first = time.time() if t_first is None else t_first
        t_last = time.time()
        t_last_mono = time.monotonic()
    q.put({"received": got, "seconds": (t_last - t_first) if got > 1 else 0.0, "bytes": nbytes,
           "latency": lat})
    bus.close()
    session.close()


def publisher(ep: str, shm: bool, size: int, seconds: float, paced_hz: float | None, count: int | None,
              ready: mp.Event) -> None:
    session = open_session(listen=[], connect=[ep], shm=shm)
    wait_for_peers(session, 1, 10)
    ready.wait(10)
    bus = Bus(session, "bench", lossless=True)
    pub = bus.publisher("x")
    time.sleep(0.5)
    body = bytearray(size)
    seq = 0
    t0 = time.monotonic()
    while True:
        if count is not None and seq >= count:
            break
        if count is None and time.monotonic() - t0 >= seconds:
            break
        if paced_hz:
            target = t0 + seq / paced_hz
            while time.monotonic() < target:
                time.sleep(max(0.0, target - time.monotonic()))
        HEADER.pack_into(body, 0, seq, time.time())
        pub.put(bytes(body))
        seq += 1
    HEADER.pack_into(body, 0, -1, time.time())
    pub.put(bytes(body))
    time.sleep(1.0)  # in-flight samples are lost if the session closes at once
    bus.close()
    session.close()


def one(size: int, shm: bool, seconds: float, paced_hz: float | None, count: int | None) -> dict:
    ctx = mp.get_context("spawn")
    ep = f"tcp/127.0.0.1:{free_port()}"
    q = ctx.Queue()
    ready = ctx.Event()
    s = ctx.Process(target=subscriber, args=(ep, shm, count or 0, q, ready))
    s.start()
    ready.wait(30)
    p = ctx.Process(target=publisher, args=(ep, shm, size, seconds, paced_hz, count, ready))
    p.start()
    res = q.get(timeout=120)
    p.join(30)
    s.join(30)
    lat = np.asarray(res["latency"]) * 1e3
    out = {"received": res["received"]}
    if paced_hz:
        out.update({"latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
                    "latency_p95_ms": float(np.percentile(lat, 95)) if lat.size else None})
    else:
        secs = max(res["seconds"], 1e-9)
        out.update({"msg_per_s": res["received"] / secs, "mb_per_s": res["bytes"] / secs / 1e6})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "transport.json"))
    args = ap.parse_args()
    sizes = {"1KB": 1024, "260KB": 64896 * 4, "1MB": 2**20}
    results: dict = {"machine": {"cpus": mp.cpu_count(), "python": platform.python_version()},
                     "method": "two spawned processes on loopback, lossless (BLOCK + FIFO 16); latency "
                               "at 100 Hz, 200 messages", "payloads": {}}
    for label, size in sizes.items():
        for shm in (True, False):
            thr = one(size, shm, args.seconds, None, None)
            lat = one(size, shm, 0, 100.0, 200)
            row = {**thr, **{k: v for k, v in lat.items() if k != "received"}}
            key = f"{label}_shm_{'on' if shm else 'off'}"
            results["payloads"][key] = row
            print(key, {k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(results, indent=2))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
