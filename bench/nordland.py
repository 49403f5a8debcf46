"""Nordland summer -> winter through A, B, (C) and D: loop-closure precision and recall.

Shared by bench/frontend.py and tests/test_frontend_nordland.py. Summer frames are streamed first,
then winter frames; the seasons are frame-aligned, so winter frame i shows the place of summer frame
i. A winter frame's loop closure is correct when the template it matched was created within
+-``tolerance`` source frames of that place during the summer pass. Recall = correct closures /
winter frames.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "nordland_64x32"


def load_frames(step: int, limit: int | None = None) -> tuple[list[np.ndarray], list[np.ndarray], list[int]]:
    names = sorted(p.name for p in (DATA / "summer").glob("images-*.png"))[::step]
    if limit:
        names = names[:limit]
    summer = [cv2.imread(str(DATA / "summer" / n))[:, :, ::-1] for n in names]
    winter = [cv2.imread(str(DATA / "winter" / n))[:, :, ::-1] for n in names]
    ids = [int(n[7:12]) for n in names]
    return summer, winter, ids


def passthrough_neocortex(bits: np.ndarray, cells_per_column: int = 32) -> np.ndarray:
    """What htm.core's TM effectively emits with NeoSLAM's parameters: cell 0 of each active column."""
    return bits.astype(np.uint32) * cells_per_column


def evaluate(template_ids: list[int], loops: list[bool], source_ids: list[int], n_summer: int,
             tolerance: int) -> dict:
    """Precision/recall of winter closures against the template creation place in summer."""
    created: dict[int, int] = {}
    for i, t in enumerate(template_ids[:n_summer]):
        created.setdefault(t, source_ids[i])
    closures = correct = 0
    for j in range(n_summer, len(template_ids)):
        if not loops[j]:
            continue
        closures += 1
        place = source_ids[j - n_summer]
        origin = created.get(template_ids[j])
        if origin is not None and abs(origin - place) <= tolerance:
            correct += 1
    n_winter = len(template_ids) - n_summer
    return {"closures": closures, "correct": correct,
            "precision": correct / closures if closures else None,
            "recall": correct / n_winter if n_winter else 0.0}


def run_frontend(backbone: str, step: int, svc_params: list[dict], tolerance: int = 150,
                 limit: int | None = None, neocortex=None, projection: str = "gaussian", seed: int = 42) -> list[dict]:
    """Extract and project once, then run the spatial-view cells once per parameter set."""
    from stages.features import VisualFeatureExtractor
    from stages.projector import BinaryProjector
    from stages.spatial_view import SpatialViewCells

    summer, winter, ids = load_frames(step, limit)
    fx = VisualFeatureExtractor(backbone=backbone, seed=seed)
    proj = BinaryProjector(input_dim=fx.output_dim, projection=projection, seed=seed)
    frames = summer + winter
    sdrs = []
    for k in range(0, len(frames), 8):
        for bits in proj.bits_batch(fx.extract_batch(frames[k:k + 8])):
            sdrs.append(neocortex(bits) if neocortex is not None else passthrough_neocortex(bits))
    results = []
    for params in svc_params:
        svc = SpatialViewCells(**params)
        out = [svc.compute(c) for c in sdrs]
        res = evaluate([r["id"] for r in out], [r["is_loop_closure"] for r in out], ids, len(summer), tolerance)
        res.update({"backbone": fx.backbone, "frames": len(frames), "step": step, "tolerance": tolerance,
                    "templates": svc.n_templates, "svc": params,
                    "chance_precision": min(1.0, (2 * tolerance + 1) / (ids[-1] - ids[0] + 10))})
        results.append(res)
    return results
