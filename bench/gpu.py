"""The front end on a CUDA GPU: what A and the fused A+B cost per frame, whether the bits and the
loop closures stay those of the CPU path, and the rate the pipeline then sustains.

Needs torch with CUDA and a GPU (exits with a message otherwise). Three parts, on the embedded
synthetic world (the default route, its first ``--frames`` frames):

* time per frame, one frame at a time (preprocessing and the copy back included): A alone and A+B
  on the CPU (one thread, as a pipeline worker runs it; B the default numba kernel) against A alone
  and A+B fused on the GPU (``projector.device: cuda``: only bits leave the GPU), for the default's
  backbone and the paper's AlexNet cost (``random_alexnet``);
* agreement: B's bits from the CPU path and from the GPU path for the same frames, then C and D on
  each bit stream: frames whose bits differ, frames whose template or loop-closure flag differs;
* the pipeline topology, lossless, as fast as it goes (``pacing: asap``) on every core of the
  machine, with the fused front end on the GPU: its steady rate and each worker's service time
  (bench/cores.py's measured run), next to the same run with every stage on the CPU.

Writes bench/results/gpu.json (``--out``).

Run: ``python bench/gpu.py [--frames 1200] [--out bench/results/gpu.json]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "bench")]

from cores import MARGIN, measured_run  # noqa: E402

from neoslam_stream.algorithms.frontend import FrontEnd  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.runtime.capacity import worker_service_ms  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402
from neoslam_stream.throughput import bench_config  # noqa: E402

BACKBONES = ("efficientnet_lite0", "random_alexnet")


def front_end(backbone: str, device: str) -> FrontEnd:
    """The default's front end with ``backbone``, A and B on ``device`` (cpu: one thread, B numba)."""
    cfg = load_config("default").front_end()
    feats = {"backbone": backbone, "device": device}
    if device == "cpu":
        feats["threads"] = 1
    return FrontEnd(cfg.model_copy(update={
        "features": cfg.features.model_copy(update=feats),
        "projector": cfg.projector.model_copy(update={"device": device})}))


def _ms(f, frames: list[np.ndarray]) -> dict[str, float]:
    for im in frames[:10]:  # warm: kernels chosen, caches filled
        f(im)
    t = []
    for im in frames:
        t0 = time.perf_counter()
        f(im)
        t.append(time.perf_counter() - t0)
    return {"p50_ms": 1e3 * float(np.median(t)), "mean_ms": 1e3 * float(np.mean(t)),
            "p95_ms": 1e3 * float(np.percentile(t, 95)), "frames": len(t)}


def timing(frames: list[np.ndarray]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for backbone in BACKBONES:
        row = {}
        for device in ("cpu", "cuda"):
            fe = front_end(backbone, device)
            fe.projector.warm_up()
            row[f"A_{device}"] = _ms(lambda im, fe=fe: fe.extractor.extract(im), frames)
            row[f"AB_{device}"] = _ms(lambda im, fe=fe: fe.bits_of_frames([im]), frames)
        row["AB_speedup_p50"] = row["AB_cpu"]["p50_ms"] / row["AB_cuda"]["p50_ms"]
        out[backbone] = row
        print(f"{backbone}: A+B {row['AB_cpu']['p50_ms']:.2f} ms on the CPU, "
              f"{row['AB_cuda']['p50_ms']:.2f} ms on the GPU (p50)", flush=True)
    return out


def agreement(frames: list[np.ndarray]) -> dict[str, Any]:
    """The default front end's CPU and GPU paths on the same frames, through C and D."""
    runs = {}
    for device in ("cpu", "cuda"):
        fe = front_end(load_config("default").front_end().resolved().features.backbone, device)
        bits = [fe.bits_of_frames([im])[0] for im in frames]
        tpl = [fe.template(fe.cells(b), float(i)) for i, b in enumerate(bits)]
        runs[device] = (bits, tpl)
    (bc, tc), (bg, tg) = runs["cpu"], runs["cuda"]
    bit_diff = [len(np.setxor1d(a, b)) for a, b in zip(bc, bg, strict=True)]
    return {"frames": len(frames), "frames_bits_differ": sum(1 for d in bit_diff if d),
            "bits_differing": int(sum(bit_diff)),
            "frames_template_differs": sum(1 for a, b in zip(tc, tg, strict=True) if a["id"] != b["id"]),
            "frames_closure_differs": sum(1 for a, b in zip(tc, tg, strict=True)
                                          if a["is_loop_closure"] != b["is_loop_closure"]),
            "closures_cpu": sum(1 for t in tc if t["is_loop_closure"]),
            "closures_cuda": sum(1 for t in tg if t["is_loop_closure"])}


def pipeline_rate(device: str, skip: int, frames: int) -> dict[str, Any]:
    over = {"features": {"device": device}, "projector": {"device": device}}
    cfg = bench_config("default", "pipeline", "lossless", None, over)
    cfg.source.pacing = "asap"
    cfg.source.max_frames = skip + frames + MARGIN
    with tempfile.TemporaryDirectory() as tmp:
        m = measured_run(cfg, Path(tmp) / f"gpu-{device}", None, skip, frames)
    return {"rate_hz": m["rate_hz"], "frames": m["frames"], "cpu_ms_per_frame": m["cpu_ms_per_frame"],
            "worker_ms": worker_service_ms(m["report"]), "loss": m["report"]["loss"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=1200, help="route frames for the agreement (the first 200 timed)")
    ap.add_argument("--run-frames", type=int, default=900, help="frames measured in each pipeline run")
    ap.add_argument("--out", default=str(ROOT / "bench" / "results" / "gpu.json"))
    args = ap.parse_args()
    import torch

    if not torch.cuda.is_available():
        raise SystemExit("bench/gpu.py needs torch with CUDA and a GPU: torch.cuda.is_available() is False")
    res: dict[str, Any] = {"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__,
                           "cpu_cores": len(os.sched_getaffinity(0))}
    route = [sf.image for sf in SyntheticWorldSource(**{**load_config("default").source.params,
                                                         "frames": args.frames})]
    res["time_per_frame"] = timing(route[:200])
    Path(args.out).write_text(json.dumps(res, indent=2))
    res["agreement"] = agreement(route)
    print(f"agreement: {json.dumps(res['agreement'])}", flush=True)
    Path(args.out).write_text(json.dumps(res, indent=2))
    res["pipeline_asap"] = {}
    for device in ("cuda", "cpu"):
        res["pipeline_asap"][device] = pipeline_rate(device, 150, args.run_frames)
        print(f"pipeline, front end on {device}: {res['pipeline_asap'][device]['rate_hz']:.1f} Hz", flush=True)
        Path(args.out).write_text(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
