"""Source speed: synthetic-world rendering and CDR Image decoding.

    .venv/bin/python bench/sources.py          # writes bench/results/sources.json

* ``synthetic_render_fps``: frames per second of :meth:`SyntheticWorld.render` at 416x240 along the
  default route (it must reach >= 200 so that the source never limits the pipeline), and
  ``synthetic_source_fps`` for whole :class:`SourceFrame`\\ s (render + odometry + ground truth).
* ``cdr_image``: microseconds per sensor_msgs/msg/Image payload (640x480 rgb8 and 416x240 rgb8)
  for our zero-copy parser and for rosbags' generic CDR deserialiser.

Single-threaded; the median of a few repeats, so background load on a shared machine counts less.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("OMP_NUM_THREADS", "1")

from neoslam_stream.sources import cdr  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402

OUT = Path(__file__).resolve().parent / "results" / "sources.json"


def _median_rate(fn, n: int, repeats: int = 3) -> float:
    rates = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(n)
        rates.append(n / (time.perf_counter() - t0))
    return statistics.median(rates)


def bench_synthetic(n: int = 300) -> dict:
    src = SyntheticWorldSource()
    world, gt = src.world, src.gt
    world.render(*gt[0])  # builds the texture atlas once

    def render(k: int) -> None:
        for i in range(k):
            world.render(*gt[(i * 7) % len(gt)])

    def stream(k: int) -> None:
        for _sf in SyntheticWorldSource(frames=k):
            pass

    return {"synthetic_render_fps": round(_median_rate(render, n), 1),
            "synthetic_source_fps": round(_median_rate(stream, n), 1),
            "synthetic_size": [world.width, world.height], "synthetic_route_frames": src.route_len}


def bench_cdr(repeats: int = 200) -> dict:
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    out = {}
    for w, h in ((640, 480), (416, 240)):
        img = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
        header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=1, nanosec=0), frame_id="cam")
        msg = T["sensor_msgs/msg/Image"](header=header, height=h, width=w, encoding="rgb8", is_bigendian=0,
                                         step=w * 3, data=img.reshape(-1))
        raw = bytes(ts.serialize_cdr(msg, "sensor_msgs/msg/Image"))
        assert np.array_equal(cdr.parse_image(raw)["image"], img)

        def ours(k: int, raw: bytes = raw) -> None:
            for _ in range(k):
                cdr.parse_image(raw)

        def rosbags(k: int, raw: bytes = raw) -> None:
            for _ in range(k):
                ts.deserialize_cdr(raw, "sensor_msgs/msg/Image")

        us_ours = 1e6 / _median_rate(ours, repeats)
        us_ref = 1e6 / _median_rate(rosbags, repeats)
        out[f"{w}x{h}_rgb8"] = {"parse_image_us": round(us_ours, 2), "rosbags_us": round(us_ref, 2),
                                "speedup": round(us_ref / us_ours, 1)}
    return {"cdr_image": out}


def main() -> None:
    res = {**bench_synthetic(), **bench_cdr(),
           "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                       "loadavg_1min": os.getloadavg()[0]}}
    OUT.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(OUT.read_text()) if OUT.exists() else {}
    OUT.write_text(json.dumps({**old, **res}, indent=2) + "\n")
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
