"""The camera streams of bench/generalisation.py, and how a closure is scored on each.

A stream knows its frames (re-read or re-rendered on demand), its stamps, the physical quantities
a user of that robot would state (``platform``), A's features (computed once, cached) and its
ground truth. ``score`` turns the (frame, matched frame) pairs of a run's loop closures into
precision and recall: Nordland (summer then winter) counts a winter closure correct when it lands
within the protocol's tolerance of the same place in summer, recall over the winter frames; the
synthetic worlds judge the pairs as ``neoslam evaluate`` does (``evaluation.closure_figures``): a
pair is a loop closure only when the robot travelled more than 5 m (five 1-m radii) since the
matched frame, else a re-recognition counted apart; a closure is correct when the matched frame
was within 1 m, recall over the frames that revisit a place seen at least 5 m of travel earlier
(facing the same way).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from bench_settings import load_settings

from neoslam_stream.algorithms.frontend import FrontEnd
from neoslam_stream.config import load_config
from neoslam_stream.evaluation import closure_figures, left_distance, travelled

RADIUS_M = 1.0
#: the travel after which the robot has left a place: a later match is a loop closure, a later
#: frame there a revisit (evaluation.left_distance: 5 m at 1 m)
REVISIT_TRAVEL_M = left_distance(RADIUS_M)
#: frames 800-2400 of each pass of the default's looped synthetic route: the stretch every pass
#: revisits (the closures per pass of bench/soak.py and studies/passes.py)
STRETCH = (800, 2400)


@dataclass
class Stream:
    name: str
    stamps: np.ndarray
    platform: dict[str, Any]
    frames: Callable[[], Iterator[np.ndarray]]
    cache: Path
    truth: dict[str, Any] = field(default_factory=dict)

    def features(self, photometric: str = "none", input_size: int = 224) -> np.ndarray:
        """A's features (the default's backbone: EfficientNet-Lite0 unless AlexNet's weights are
        found; ``photometric`` and ``input_size`` as given), 8 frames at a time."""
        tag = ("" if photometric == "none" else f"_{photometric}") + ("" if input_size == 224 else f"_{input_size}")
        path = self.cache / f"{self.name}{tag}_features.npy"
        if path.exists():
            return np.load(path)
        over = {"features": {"photometric": photometric, "input_size": input_size}}
        fe = FrontEnd(load_config("default", over).front_end())
        batch, out = [], []
        for img in self.frames():
            batch.append(img)
            if len(batch) == 8:
                out.append(fe.features(batch))
                batch = []
        if batch:
            out.append(fe.features(batch))
        feats = np.concatenate(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        np.save(path, feats)
        return feats

    def cells(self, fe: FrontEnd) -> list[np.ndarray]:
        """C's cells of every frame through ``fe``'s B (8 frames a batch, as its node) and C, from
        A's features with ``fe``'s photometric setting and input size."""
        feats = self.features(fe.config.features.photometric, fe.config.features.input_size)
        return [fe.cells(b) for k in range(0, len(feats), 8) for b in fe.bits(feats[k:k + 8])]

    def pixels(self) -> Iterator[np.ndarray]:
        return self.frames()

    def score(self, pairs: list[tuple[int, int]]) -> dict[str, Any]:
        if self.truth["kind"] == "nordland":
            return _score_nordland(pairs, self.truth)
        return _score_world(pairs, self.truth)


def _score_nordland(pairs: list[tuple[int, int]], tr: dict[str, Any]) -> dict[str, Any]:
    n, ids, tol = tr["n"], tr["ids"], tr["tolerance"]
    winter = [(t, m) for t, m in pairs if t >= n]
    correct = sum(1 for t, m in winter if m < n and abs(ids[m] - ids[t - n]) <= tol)
    return {"closures": len(winter), "correct": correct,
            "precision": correct / len(winter) if winter else None, "recall": correct / (len(ids)),
            "first_traversal_closures": len(pairs) - len(winter)}


def _score_world(pairs: list[tuple[int, int]], tr: dict[str, Any]) -> dict[str, Any]:
    """The pairs judged by ``evaluation.closure_figures``: loop closures (more than
    ``REVISIT_TRAVEL_M`` travelled since the matched frame) with their precision and recall, and
    the re-recognitions beside them."""
    gt, path, revisit = tr["gt"], tr["path"], tr["revisit"]
    t, m = (np.array([p[k] for p in pairs], dtype=np.int64) for k in (0, 1))
    res = closure_figures(gt[t, :2], gt[m, :2], path[t] - path[m], revisit[t], int(revisit.sum()), RADIUS_M,
                          REVISIT_TRAVEL_M)
    if res["recall"] is None:  # no revisiting frame: nothing to find
        res["recall"] = 0.0
    return res


def _world_truth(gt: np.ndarray) -> dict[str, Any]:
    path = travelled(gt[:, :2])
    revisit = np.zeros(len(gt), bool)
    for j in range(len(gt)):
        old = path <= path[j] - REVISIT_TRAVEL_M
        if old.any():
            d = np.hypot(gt[old, 0] - gt[j, 0], gt[old, 1] - gt[j, 1])
            dh = np.abs(np.angle(np.exp(1j * (gt[old, 2] - gt[j, 2]))))
            revisit[j] = bool(np.any((d <= RADIUS_M) & (dh < 0.8)))  # a forward camera: the same facing
    return {"kind": "world", "gt": gt, "path": path, "revisit": revisit}


def nordland_stream(offset: int, cache: Path) -> Stream:
    """Summer then winter thumbnails of the protocol (bench/settings/nordland.yaml), a frame every
    ``frame_s`` seconds of the source, with the train's physical quantities."""
    from nordland import load_frames

    s = load_settings("nordland")
    p = s["protocol"]
    summer, winter, ids = load_frames(p["step"], None, p["min_std"], offset)
    frames = summer + winter
    stamps = np.arange(len(frames), dtype=np.float64) * p["frame_s"]
    truth = {"kind": "nordland", "n": len(summer), "ids": ids, "tolerance": p["tolerance"]}
    return Stream(f"nordland{offset}", stamps, s["platform"], lambda: iter(frames), cache, truth)


def _synthetic(name: str, params: dict[str, Any], stamps_from_source: bool, cache: Path) -> Stream:
    from neoslam_stream.sources.synthetic import SyntheticWorldSource

    tiny = [(f.groundtruth, f.stamp) for f in SyntheticWorldSource(**{**params, "width": 8, "height": 8})]
    gt = np.array([g for g, _ in tiny])
    src_stamps = np.array([s for _, s in tiny])
    stamps = src_stamps if stamps_from_source else np.arange(len(gt), dtype=np.float64)
    platform = load_config("default").platform.model_dump()

    def frames() -> Iterator[np.ndarray]:
        return (f.image for f in SyntheticWorldSource(**params))

    return Stream(name, stamps, platform, frames, cache, _world_truth(gt))


def synthetic_stream(seed: int, cache: Path) -> Stream:
    """The embedded world's default route (2445 frames at 10 Hz) with the default's platform."""
    return _synthetic(f"synthetic{seed}", {"seed": seed}, True, cache)


def proxy_stream(seed: int, cache: Path, hard: bool = False) -> Stream:
    """The held-out protocol on a sparse stand-in: two laps at one frame per 0.3 m of a
    160x120 wide-angle camera, fed without stamps to the default as it ships (as the issue's
    corridor is). ``hard``: the second lap under other light (gain, gamma), with a drifting
    lateral offset, blur and noise."""
    params = {"seed": seed, "speed": 3.0, "laps_cw": 2, "laps_ccw": 0, "width": 160, "height": 120,
              "fov_deg": 120}
    s = _synthetic(f"{'hard' if hard else 'sparse'}{seed}", params, False, cache)
    if hard:
        plain = s.frames
        n = len(s.stamps) // 2

        def frames() -> Iterator[np.ndarray]:
            change = Perturbation(np.random.default_rng(100 + seed))
            for i, img in enumerate(plain()):
                yield img if i < n else change(img)

        s.frames = frames
    return s


class Perturbation:
    """Another visit's conditions: gain and gamma fixed for the visit, a lateral offset that drifts
    (image shift), blur, and sensor noise per frame."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.gain = 1 + 0.35 * rng.choice([-1, 1])
        self.gamma = 1 + 0.3 * rng.choice([-1, 1])
        self.dx = 0.0

    def __call__(self, img: np.ndarray) -> np.ndarray:
        import cv2

        f = np.clip(img.astype(np.float32) / 255 * self.gain, 0, 1) ** self.gamma
        self.dx = float(np.clip(self.dx + self.rng.normal(0, 2), -12, 12))
        f = np.roll(f, int(round(self.dx)), axis=1)
        f = cv2.GaussianBlur(f, (3, 3), 0.8)
        f = f + self.rng.normal(0, 0.04, f.shape)
        return (np.clip(f, 0, 1) * 255).astype(np.uint8)
