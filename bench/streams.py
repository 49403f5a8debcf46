"""The camera streams of bench/generalisation.py, and how a closure is scored on each.

A stream knows its frames (re-read or re-rendered on demand), its stamps, the physical quantities
a user of that robot would state (``platform``), A's features (computed once, cached) and its
ground truth. ``score`` turns the (frame, matched frame) pairs of a run's loop closures into
precision and recall: a two-traversal stream (Nordland summer then winter, Gardens Point's
reference walk then its query walk) counts a closure of the second traversal correct when it lands
within the protocol's tolerance of the same place in the first, recall over the second traversal's
frames that have a place there; the synthetic worlds judge the pairs as ``neoslam evaluate`` does
(``evaluation.closure_figures``): a pair is a loop closure only when the robot travelled more than
5 m (five 1-m radii) since the matched frame, else a re-recognition counted apart; a closure is
correct when the matched frame was within 1 m, recall over the frames that revisit a place seen at
least 5 m of travel earlier (facing the same way). ``recognition_truth`` gives bench/stages.py each
query's candidates and which of them are right. A stream whose data is absent raises
:class:`MissingData` with a one-line reason.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from bench_settings import datasets_cache, load_settings

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
IMAGES = (".jpg", ".jpeg", ".png", ".bmp")


class MissingData(RuntimeError):
    """A stream's data set is not on this machine (the message says where it was looked for)."""


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

    def sdrs(self, fe: FrontEnd) -> list[Any]:
        """C's result of every frame (its cells, and B's descriptor when ``fe`` keeps one) through
        ``fe``'s B (8 frames a batch, as its node) and C, from A's features as in :meth:`cells`."""
        feats = self.features(fe.config.features.photometric, fe.config.features.input_size)
        return [fe.winner_cells(c) for k in range(0, len(feats), 8) for c in fe.codes(feats[k:k + 8])]

    def pixels(self) -> Iterator[np.ndarray]:
        return self.frames()

    def score(self, pairs: list[tuple[int, int]]) -> dict[str, Any]:
        if self.truth["kind"] == "traversals":
            return _score_traversals(pairs, self.truth)
        return _score_world(pairs, self.truth)

    def recognition_truth(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(queries, candidates, allowed, right): the frames that query and the frames they may
        match (stream indices), and per query and candidate whether it may be matched and whether
        that match is right. Two traversals: the second's frames against the first's, right within
        the tolerance; one route: every frame against those at least REVISIT_TRAVEL_M of travel
        earlier, right within RADIUS_M with the same facing (a query with a right candidate is a
        revisit)."""
        tr = self.truth
        if tr["kind"] == "traversals":
            n = tr["n"]
            queries, candidates = np.arange(n, len(self.stamps)), np.arange(n)
            q_ids = np.asarray(tr["query_ids"])[:, None]
            right = (q_ids >= 0) & (np.abs(np.asarray(tr["ref_ids"])[None, :] - q_ids) <= tr["tolerance"])
            return queries, candidates, np.ones_like(right), right
        gt, path = tr["gt"], tr["path"]
        idx = np.arange(len(gt))
        allowed = path[None, :] <= path[:, None] - REVISIT_TRAVEL_M
        d = np.hypot(gt[:, None, 0] - gt[None, :, 0], gt[:, None, 1] - gt[None, :, 1])
        dh = np.abs(np.angle(np.exp(1j * (gt[:, None, 2] - gt[None, :, 2]))))
        return idx, idx, allowed, allowed & (d <= RADIUS_M) & (dh < 0.8)


def _score_traversals(pairs: list[tuple[int, int]], tr: dict[str, Any]) -> dict[str, Any]:
    """Closures of the second traversal (frames n on): right when the matched frame is a frame of the
    first whose place is within the tolerance of the query's; recall over the queries with a place."""
    n, ref, qry, tol = tr["n"], tr["ref_ids"], tr["query_ids"], tr["tolerance"]
    second = [(t, m) for t, m in pairs if t >= n]
    correct = sum(1 for t, m in second if m < n and qry[t - n] >= 0 and abs(ref[m] - qry[t - n]) <= tol)
    positives = sum(1 for q in qry if q >= 0)
    return {"closures": len(second), "correct": correct,
            "precision": correct / len(second) if second else None, "recall": correct / positives,
            "first_traversal_closures": len(pairs) - len(second)}


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
    truth = {"kind": "traversals", "n": len(summer), "ref_ids": ids, "query_ids": ids, "tolerance": p["tolerance"]}
    return Stream(f"nordland{offset}", stamps, s["platform"], lambda: iter(frames), cache, truth)


def traversals_stream(settings: str, pair: str, half: str, cache: Path) -> Stream:
    """Two walks of one route, the reference streamed first, then the query (bench/settings/
    ``settings``.yaml: the data set's folder under :func:`bench_settings.datasets_cache`, which
    traversals each ``pair`` names and which frames each ``half`` takes), without stamps (frame
    numbers) and with the platform a user would state. The images are read in sorted order from
    ``<cache>/<set>/<traversal>/``; ``gt.json`` says they are frame-aligned (``aligned``: frame i of
    one walk is frame i's place in the other) or gives ``pairs`` [query frame, reference frame], and
    the ``tolerance_frames``. Raises :class:`MissingData` when the folder is absent."""
    import json

    import cv2

    s = load_settings(settings)
    p = s["protocol"]
    root = datasets_cache() / p["set"]
    ref_name, query_name = p["pairs"][pair]
    lo, hi = p["halves"][half]
    folders = [root / ref_name, root / query_name]
    if not (root / "gt.json").exists() or not all(f.is_dir() for f in folders):
        raise MissingData(f"{p['set']} not found in {root} (set $NEOSLAM_DATASETS; bench/settings/{settings}.yaml "
                          "says what it is)")
    gt = json.loads((root / "gt.json").read_text())
    files = [sorted(f for f in d.iterdir() if f.suffix.lower() in IMAGES)[lo:hi] for d in folders]
    ref_ids = np.arange(lo, lo + len(files[0]))
    if gt.get("aligned"):
        query_ids = np.arange(lo, lo + len(files[1]))
    else:  # [query frame, reference frame] pairs, numbered in the whole walks
        pairs = dict((int(q), int(r)) for q, r in gt["pairs"])
        query_ids = np.array([pairs.get(i, -1) for i in range(lo, lo + len(files[1]))])
    paths = files[0] + files[1]

    def frames() -> Iterator[np.ndarray]:
        return (cv2.imread(str(f))[:, :, ::-1].copy() for f in paths)

    truth = {"kind": "traversals", "n": len(files[0]), "ref_ids": ref_ids, "query_ids": query_ids,
             "tolerance": int(gt.get("tolerance_frames", p["tolerance"]))}
    return Stream(f"{settings}_{pair}_{half}", np.arange(len(paths), dtype=np.float64), s["platform"], frames,
                  cache, truth)


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
