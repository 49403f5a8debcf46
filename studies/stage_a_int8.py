"""Stage A quantised to int8 (measured, not shipped): its time per frame and what it keeps of A.

The default's backbone (EfficientNet-Lite0 up to block 10) quantised after training by torch's FX
graph mode (x86 engine: weights per output channel, activations per tensor from histograms),
calibrated on frames of validation parts only (synthetic world 1, Nordland section 2), then traced
and frozen like the default's ``features.inference: frozen``. Reported on held-out parts
(synthetic world 0, Nordland section 0): time per frame (one thread, one frame at a time, the
float and int8 networks interleaved), the cosine between the int8 and the float features of the
same frame, the share of B's bits they have in common (B without centring), and place recognition
by A's features alone: recall@1 of Nordland's winter frames against its summer frames by cosine
(the issue's measure for what the stages keep of A). Writes studies/results/stage_a_int8.json.

Run: ``.venv/bin/python studies/stage_a_int8.py [--out studies/results/stage_a_int8.json]``.
"""

from __future__ import annotations

import argparse
import copy
import json
import time
import warnings
from pathlib import Path

import _paths  # the package and bench/ on sys.path
import numpy as np
from bench_settings import load_settings
from nordland import load_frames

from neoslam_stream.algorithms.features import VisualFeatureExtractor
from neoslam_stream.algorithms.projector import BinaryProjector, ProjectorConfig
from neoslam_stream.config import load_config
from neoslam_stream.sources.synthetic import SyntheticWorldSource


def world_frames(seed: int, n: int, step: int) -> list[np.ndarray]:
    """Every ``step``-th of the first n*step frames of the synthetic world ``seed``."""
    return [sf.image for sf in SyntheticWorldSource(seed=seed, frames=n * step)][::step]


def quantised(float_net, calibration: list) -> object:
    import torch
    from torch.ao.quantization import get_default_qconfig_mapping
    from torch.ao.quantization.quantize_fx import convert_fx, prepare_fx

    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("ignore")
        prepared = prepare_fx(copy.deepcopy(float_net).eval(), get_default_qconfig_mapping("x86"),
                              example_inputs=(calibration[0],))
        for x in calibration:
            prepared(x)
        q = convert_fx(prepared)
        return torch.jit.freeze(torch.jit.trace(q, calibration[0]))


def features(net, xs: list, rounds_ms: list[float] | None = None) -> np.ndarray:
    import torch

    out = []
    with torch.inference_mode():
        for x in xs:
            t = time.perf_counter()
            y = net(x)
            if rounds_ms is not None:
                rounds_ms.append(1000 * (time.perf_counter() - t))
            out.append(y.reshape(-1).float().numpy())
    return np.array(out)


def recall_at_1(summer: np.ndarray, winter: np.ndarray, ids: list[int], tolerance: int) -> float:
    s = summer / np.linalg.norm(summer, axis=1, keepdims=True)
    w = winter / np.linalg.norm(winter, axis=1, keepdims=True)
    best = np.argmax(w @ s.T, axis=1)
    return float(np.mean([abs(ids[b] - ids[k]) <= tolerance for k, b in enumerate(best)]))


def main() -> int:
    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(_paths.RESULTS / "stage_a_int8.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_config("default").features.model_copy(update={"threads": 1})
    fx = VisualFeatureExtractor(cfg.model_copy(update={"inference": "frozen"}))
    eager = VisualFeatureExtractor(cfg.model_copy(update={"inference": "eager"})).module.eval()

    def tensors(frames: list[np.ndarray]) -> list:
        return [torch.from_numpy(fx.preprocess(f))[None] for f in frames]

    p = load_settings("nordland")["protocol"]
    print("calibrating on validation frames (synthetic world 1, Nordland section 2) ...", flush=True)
    calib_summer, _, _ = load_frames(p["step"], 60, p["min_std"], 2)
    q = quantised(eager, tensors(world_frames(1, 120, 4) + calib_summer))

    print("held out: synthetic world 0, Nordland section 0 ...", flush=True)
    world = tensors(world_frames(0, 200, 6))
    summer, winter, ids = load_frames(p["step"], None, p["min_std"], 0)
    nets = {"float": fx.net, "int8": q}
    times: dict[str, list[float]] = {k: [] for k in nets}
    feats = {}
    for _ in range(2):  # warm-up of both, then interleaved rounds over the world's frames
        for net in nets.values():
            features(net, world[:3])
    for _ in range(3):
        for k, net in nets.items():
            feats[k] = features(net, world, times[k])
    cos = np.sum(feats["float"] * feats["int8"], axis=1) / (
        np.linalg.norm(feats["float"], axis=1) * np.linalg.norm(feats["int8"], axis=1))
    bp = BinaryProjector(ProjectorConfig(input_dim=feats["float"].shape[1]))
    shared = [len(np.intersect1d(bp.bits(a), bp.bits(b))) / len(bp.bits(a))
              for a, b in zip(feats["float"], feats["int8"], strict=True)]
    summer_x, winter_x = tensors(summer), tensors(winter)  # preprocessed once for both networks
    recall = {k: recall_at_1(features(net, summer_x), features(net, winter_x), ids, p["tolerance"])
              for k, net in nets.items()}
    res = {"backbone": fx.backbone, "calibration": "synthetic world 1 (120 frames), Nordland section 2 (60 summer frames)",
           "held_out": {"world": "synthetic world 0, 200 frames", "nordland": f"section 0, {len(ids)} places"},
           "time_per_frame_ms": {k: {"p50": float(np.median(v)), "p95": float(np.percentile(v, 95))}
                                 for k, v in times.items()},
           "speedup_p50": float(np.median(times["float"]) / np.median(times["int8"])),
           "cosine_int8_float": {"mean": float(cos.mean()), "min": float(cos.min())},
           "b_bits_shared": {"mean": float(np.mean(shared)), "min": float(np.min(shared))},
           "nordland_recall_at_1_by_a": recall}
    Path(args.out).write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
