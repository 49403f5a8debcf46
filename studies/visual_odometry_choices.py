"""The default's visual odometry, chosen step by step on validation worlds and reported on held-out
ones -> studies/results/visual_odometry_choices.json.

Each synthetic world's route is rendered as an MP4 video (as bench/visual_odometry.py renders the
default route), the default's front end runs once over the video's frames (its templates, cached
under $NEOSLAM_CACHE/visual_odometry_choices), and every variant's visual odometry, computed from
the same frames, is replayed through the default's back end with those templates
(bias_forgetting.replay): APE of the per-frame pose (online) and on the final map, SE(2)-aligned.
The world's wheel odometry replayed with the same templates is the reference (``wheel``).

``STEPS``, each on top of the ones before, from the default before this study (``rotation:
pinhole_centre``, ``scale: platform``; visual_odometry.py says why each):

* ``subpixel``: the rotation's shift refined to a fraction of a column;
* ``rotation_check``: the centre's shift stands only if the whole window bears it out;
* ``normal_flow``: the translation's difference over the profiles' contrast.

``RULE`` (fixed before any held-out world was run): a step stays if it lowers the mean final-map
APE over the validation worlds and raises none of them by more than ``SLACK``. Held out: world 0
(the default route, the one bench/visual_odometry.py and docs/ratslam.md report) and world 2.

Run: ``.venv/bin/python studies/visual_odometry_choices.py [--out FILE]`` (about 6 minutes on 2
cores, 2 with the front ends cached).
"""

from __future__ import annotations

import argparse
import os
import pickle
from pathlib import Path
from typing import Any

import _paths  # the package and bench/ on sys.path
import cv2
import numpy as np
from bench_settings import cache_key
from bias_forgetting import default_back_end, replay, template_input, validate_then_report

from neoslam_stream.algorithms.backend import CameraOdometry
from neoslam_stream.api import NeoSLAM, _image_data
from neoslam_stream.config import load_config
from neoslam_stream.nodes.camera import camera_pixels
from neoslam_stream.sources.files import VideoSource
from neoslam_stream.sources.synthetic import SyntheticWorldSource

CACHE = Path(os.environ.get("NEOSLAM_CACHE", "/tmp/neoslam_generalisation")) / "visual_odometry_choices"
VALIDATION, TEST = ("synthetic:1", "synthetic:3", "synthetic:4"), ("synthetic:0", "synthetic:2")
#: the default's visual odometry before this study, and the steps tried on top of it, in order
BEFORE = {"scale": "platform", "rotation": "pinhole_centre", "camera_fov_deg": 90,
          "subpixel": False, "rotation_check": False, "translation": "difference"}
STEPS = {"subpixel": {"subpixel": True}, "rotation_check": {"rotation_check": True},
         "normal_flow": {"translation": "normal_flow"}}
SLACK = 1.05
RULE = (f"a step stays if it lowers the mean final-map APE over {', '.join(VALIDATION)} and raises none "
        f"by more than {SLACK:g} x")


def variants() -> dict[str, dict[str, Any]]:
    """``before`` and each step with every step before it."""
    out, cur = {"before": dict(BEFORE)}, dict(BEFORE)
    for name, change in STEPS.items():
        cur = {**cur, **change}
        out[name] = dict(cur)
    return out


def world_video(seed: int) -> tuple[Path, list[tuple], np.ndarray]:
    """The world's route as an MP4 file, its wheel odometry per frame and its ground truth (x, y,
    heading)."""
    cfg = load_config("default", {"source": {"params": {"seed": seed}}})
    CACHE.mkdir(parents=True, exist_ok=True)
    video, side = CACHE / f"world{seed}.mp4", CACHE / f"world{seed}_pose_truth.pkl"
    if not (video.exists() and side.exists()):
        src = SyntheticWorldSource(**cfg.source.params)
        writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), src.rate_hz,
                                 (src.world.width, src.world.height))
        wheel, truth = [], []
        for f in src:
            writer.write(np.ascontiguousarray(f.image[:, :, ::-1]))
            wheel.append(tuple(f.odom))
            truth.append(tuple(f.groundtruth[:3]))
        writer.release()
        side.write_bytes(pickle.dumps((wheel, truth)))
    wheel, truth = pickle.loads(side.read_bytes())
    return video, wheel, np.array(truth)


def front_end_on_video(seed: int, video: Path) -> list[tuple[int | None, float, float]]:
    """The default's front end over the video's frames: (template id or None, relative rotation,
    stamp) per frame, cached under a digest of the front end's config."""
    cfg = load_config("default", {"source": {"params": {"seed": seed}}})
    path = CACHE / f"world{seed}_front_{cache_key(cfg.front_end().model_dump())}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    slam = NeoSLAM(cfg, backend=False)
    rows = []
    for f in VideoSource(str(video)):
        t = slam.step(f.image, stamp=f.stamp, frame=f.frame).template
        rows.append((*template_input(t), f.stamp))
    path.write_bytes(pickle.dumps(rows))
    return rows


def visual_odometry(video: Path, settings: dict[str, Any]) -> list[tuple[float, float, float]]:
    """(vtrans, vrot, dt) per frame of the video, by the default's VO with ``settings``."""
    cfg = load_config("default", {"odometry": "visual", "visual_odometry": settings})
    vo = CameraOdometry(cfg.visual_odometry, cfg.platform.speed_mps)
    return [vo.on_frame(camera_pixels(_image_data(f.image, None)), f.stamp) for f in VideoSource(str(video))]


def true_motion(truth: np.ndarray) -> np.ndarray:
    """(distance, turn) of each frame since the one before, from the ground truth."""
    step = np.diff(truth, axis=0, prepend=truth[:1])
    return np.column_stack([np.hypot(step[:, 0], step[:, 1]), np.remainder(step[:, 2] + np.pi, 2 * np.pi) - np.pi])


def distance_spread(vo: np.ndarray, true: np.ndarray, window: int = 10) -> list[float]:
    """VO's distance over the true one in windows of ``window`` frames (one second at 10 Hz) where
    the robot drove: the 5th and 95th percentiles."""
    n = len(true) // window * window
    d_true, d_vo = true[:n].reshape(-1, window).sum(1), vo[:n].reshape(-1, window).sum(1)
    moving = d_true > 0.5 * d_true.max()
    return [round(float(v), 3) for v in np.percentile(d_vo[moving] / d_true[moving], [5, 95])]


def part_rows(part: str) -> dict[str, dict[str, Any]]:
    """Per odometry: APE online and on the final map. For each VO variant also its distance spread
    over one-second windows, and for the chosen-so-far settings (the last step) the same VO with one
    half replaced by the truth (``true_translation``: VO's turns; ``true_rotation``: VO's distances),
    which says which half the remaining error is in."""
    seed = int(part.split(":")[1])
    video, wheel, truth = world_video(seed)
    front = front_end_on_video(seed, video)
    forget = default_back_end().pose_cells.odometry_bias.forget_s
    visual = {name: visual_odometry(video, s) for name, s in variants().items()}
    true = true_motion(truth)
    last = np.array(visual[list(STEPS)[-1]])
    dt = np.where(last[:, 2] > 0, last[:, 2], 1.0)
    halves = {"true_translation": np.column_stack([true[:, 0] / dt, last[:, 1], last[:, 2]]),
              "true_rotation": np.column_stack([last[:, 0], true[:, 1] / dt, last[:, 2]])}
    odometries = {"wheel": wheel, **visual, **{k: [tuple(r) for r in v] for k, v in halves.items()}}
    out: dict[str, dict[str, Any]] = {}
    for name, odo in odometries.items():
        rows = [(tid, rel, o, stamp, tuple(xy[:2])) for (tid, rel, stamp), o, xy in zip(front, odo, truth, strict=True)]
        r = replay(rows, forget)
        out[name] = {"online_m": round(r["online_m"], 4), "final_map_m": round(r["final_map_m"], 4)}
        if name in visual:
            o = np.array(odo)
            out[name]["distance_1s_p5_p95"] = distance_spread(o[:, 0] * o[:, 2], true[:, 0])
        print(part, name, out[name], flush=True)
    return out


def choose(valid: dict[str, dict[str, dict[str, float]]]) -> dict[str, Any]:
    """``RULE`` over the validation worlds' rows: the steps kept and the settings they make."""
    kept, settings, verdicts = "before", dict(BEFORE), {}
    for name, change in STEPS.items():
        trial = {**settings, **change}
        if trial != variants()[name]:  # a step left out changes what the later ones stand on: not replayed
            verdicts[name] = "not tried: it stands on a step left out"
            continue
        ratios = {p: v[name]["final_map_m"] / v[kept]["final_map_m"] for p, v in valid.items()}
        mean_ratio = float(np.mean([v[name]["final_map_m"] for v in valid.values()])
                           / np.mean([v[kept]["final_map_m"] for v in valid.values()]))
        ok = mean_ratio < 1.0 and all(r <= SLACK for r in ratios.values())
        verdicts[name] = {"final_map_vs_" + kept: {p: round(r, 3) for p, r in ratios.items()},
                          "mean_ratio": round(mean_ratio, 3), "kept": ok}
        if ok:
            kept, settings = name, trial
    return {"rule": RULE, "steps": verdicts, "visual_odometry": settings}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(_paths.RESULTS / "visual_odometry_choices.json"))
    args = ap.parse_args()
    validate_then_report({"before": BEFORE, "steps": STEPS}, part_rows, choose, args.out, VALIDATION, TEST)


if __name__ == "__main__":
    main()
