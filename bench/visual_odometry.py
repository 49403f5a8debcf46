"""Visual odometry on the default route rendered as a video -> bench/results/visual_odometry.json.

The default synthetic route (world 0, 2445 frames at 10 Hz) is written to an MP4 file (OpenCV's
mp4v), read back by the ``video`` source (no odometry, no ground truth), and mapped by the default
NeoSLAM in-process (the same templates and poses as a lossless ``neoslam run``) with visual
odometry; the same route with the source's wheel odometry is the reference. Per variant: the
trajectory APE online and on the final map (SE(2)-aligned, against the route's ground truth), the
loop closures, and the path length VO integrated against the true one. Variants:

* ``wheel``: the synthetic world's wheel odometry (3 % scale, 0.01 rad/s yaw bias, noise);
* ``visual_openratslam``: OpenRatSLAM's VO as it ships (``scale: fixed``, ``vtrans_scaling`` 100,
  ``rotation: openratslam``, ``camera_fov_deg`` 50): what ``odometry: visual`` gave before;
* ``visual_openratslam_fov90``: the same with the camera's field of view (90 degrees);
* ``visual_platform_scale``: and the translation scaled by the platform's typical speed;
* ``visual_pinhole_centre``: and the rotation read from the image's centre as a pinhole camera's
  (``rotation: pinhole_centre``);
* ``visual_default``: the default's VO, which adds a fraction of a column to the rotation's shift
  (``subpixel``), checks the centre's turn against the whole window (``rotation_check``) and reads
  the translation as normal flow (``translation: normal_flow``).

Run: ``.venv/bin/python bench/visual_odometry.py [--frames N] [--variants a,b] [--out FILE]``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from neoslam_stream.api import NeoSLAM  # noqa: E402
from neoslam_stream.config import load_config  # noqa: E402
from neoslam_stream.evaluation import evaluate_run  # noqa: E402
from neoslam_stream.sources.files import VideoSource  # noqa: E402
from neoslam_stream.sources.synthetic import SyntheticWorldSource  # noqa: E402
from neoslam_stream.tum import write_tum  # noqa: E402

#: the reference code's VO (what ``odometry: visual`` gave before the default's VO section)
OPENRATSLAM = {"scale": "fixed", "rotation": "openratslam", "camera_fov_deg": 50, "subpixel": False,
               "rotation_check": False, "translation": "difference"}
VARIANTS = {
    "wheel": {},
    "visual_openratslam": {"odometry": "visual", "visual_odometry": OPENRATSLAM},
    "visual_openratslam_fov90": {"odometry": "visual", "visual_odometry": {**OPENRATSLAM, "camera_fov_deg": 90}},
    "visual_platform_scale": {"odometry": "visual", "visual_odometry": {**OPENRATSLAM, "scale": "platform",
                                                                       "camera_fov_deg": 90}},
    "visual_pinhole_centre": {"odometry": "visual", "visual_odometry": {
        **OPENRATSLAM, "scale": "platform", "rotation": "pinhole_centre", "camera_fov_deg": 90}},
    "visual_default": {"odometry": "visual"},
}

def render_video(path: Path, frames: int | None) -> np.ndarray:
    """The default route into an MP4 file at 10 Hz; returns its ground truth (stamp, x, y, theta)."""
    src = SyntheticWorldSource(**{**load_config("default").source.params, "frames": frames})
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), src.rate_hz,
                             (src.world.width, src.world.height))
    gt = []
    for sf in src:
        writer.write(np.ascontiguousarray(sf.image[:, :, ::-1]))
        gt.append((sf.stamp, *sf.groundtruth))
    writer.release()
    return np.array(gt)


def run_variant(name: str, video: Path, gt: np.ndarray, out: Path, frames: int | None) -> dict:
    cfg = load_config("default", VARIANTS[name])
    run_dir = out / name
    run_dir.mkdir(parents=True, exist_ok=True)
    slam = NeoSLAM(cfg, run_dir=run_dir)
    t0 = time.perf_counter()
    path = 0.0
    if cfg.odometry == "wheel":
        for f in SyntheticWorldSource(**{**cfg.source.params, "frames": frames}):
            slam.step(f.image, odometry=f.odom, stamp=f.stamp, frame=f.frame)
            path += f.odom[0] * f.odom[2]
    else:
        for f in VideoSource(str(video)):
            vtrans, _, dt = slam.step(f.image, stamp=f.stamp, frame=f.frame).odometry
            path += vtrans * dt
    slam.finish()
    secs = time.perf_counter() - t0
    write_tum(run_dir / "groundtruth.tum", gt)
    ev = evaluate_run(run_dir, plot=True, walls=SyntheticWorldSource(frames=1).world.segments)
    true_path = float(np.hypot(*np.diff(gt[:, 1:3], axis=0).T).sum())
    lc = ev.get("loop_closures", {})
    return {"ape_online_mean_m": round(ev["trajectory_ape"]["mean_m"], 3),
            "ape_map_mean_m": round(ev["map_trajectory_ape"]["mean_m"], 3),
            "closures": lc.get("closures"), "precision": lc.get("precision"), "recall": lc.get("recall"),
            "path_m": round(path, 2), "true_path_m": round(true_path, 2), "path_ratio": round(path / true_path, 3),
            "frames": len(gt), "seconds": round(secs, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=None, help="frames of the route (default: all 2445)")
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated: " + ", ".join(VARIANTS))
    ap.add_argument("--out", default="bench/results/visual_odometry.json")
    ap.add_argument("--keep", help="keep the video and the run folders in this folder")
    args = ap.parse_args()
    names = [v for v in args.variants.split(",") if v]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.keep or tmp)
        work.mkdir(parents=True, exist_ok=True)
        video = work / "route.mp4"
        gt = render_video(video, args.frames)
        results = {}
        for name in names:
            results[name] = run_variant(name, video, gt, work, args.frames)
            print(name, results[name], flush=True)
    wheel = results.get("wheel")
    out = {"route": "synthetic world 0, the default route", "video": "mp4v via OpenCV, 416x240, 10 Hz",
           "variants": {k: VARIANTS[k] for k in names}, "results": results}
    if wheel:
        out["ratio_to_wheel_online"] = {k: round(r["ape_online_mean_m"] / wheel["ape_online_mean_m"], 2)
                                        for k, r in results.items()}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
