"""The in-process API: NeoSLAM / RatSLAM calling the front-end and back-end cores in the caller's process."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from neoslam_stream import NeoSLAM, RatSLAM, load_config
from neoslam_stream.algorithms.errors import InvalidInput
from neoslam_stream.sources.synthetic import SyntheticWorldSource


def _cfg(**over):
    # random AlexNet weights: the real backbone's shapes, no weight file needed
    return load_config("default", {"features": {"backbone": "random_alexnet"}, **over})


def _frames(n):
    return [sf for sf, _ in zip(SyntheticWorldSource(seed=0, width=160, height=96), range(n), strict=False)]


@pytest.fixture(scope="module")
def frames():
    return _frames(12)


def test_front_end_alone_needs_no_odometry(frames):
    slam = NeoSLAM(_cfg(), backend=False)
    assert slam.back_end is None
    results = [slam.step(sf.image) for sf in frames]
    ids = [r.template_id for r in results]
    assert all(r.pose is None and len(r.front.bits) == 512 for r in results)
    # the first frame opens interval 0 and template 0; ids are consecutive from 0 (paper, step 4)
    assert ids[0] == 0 and all(0 <= t <= max(ids) for t in ids)
    assert sorted(set(ids)) == list(range(max(ids) + 1))
    with pytest.raises(ValueError, match="backend=False"):
        slam.map()


def test_back_end_wants_odometry_and_says_how(frames):
    slam = NeoSLAM(_cfg())
    with pytest.raises(ValueError, match="odometry=\\(vtrans, vrot, dt\\)"):
        slam.step(frames[0].image)


def test_poses_follow_the_odometry_and_the_map_grows(frames):
    slam = RatSLAM(_cfg())
    xs = []
    for sf in frames:
        r = slam.step(sf.image, odometry=(1.0, 0.0, 0.1))  # 0.1 m straight ahead per frame
        xs.append(r.pose[0])
    # dead reckoning of 0.1 m per frame along the start heading (0 rad in the default config)
    assert np.diff(xs) == pytest.approx(0.1)
    assert len(slam.map()["nodes"]) >= 1
    assert slam.finish() == slam.map()
    with pytest.raises(RuntimeError, match="finished"):
        slam.step(frames[0].image, odometry=(1.0, 0.0, 0.1))


def test_frames_must_advance_and_bad_input_is_refused_without_breaking_the_chain(frames):
    slam = NeoSLAM(_cfg(), backend=False)
    slam.step(frames[0].image, frame=5)
    with pytest.raises(ValueError, match="not after"):
        slam.step(frames[1].image, frame=5)
    with pytest.raises(InvalidInput, match="uint8"):  # uint8 images only
        slam.step(frames[1].image.astype(np.float32))
    with pytest.raises(InvalidInput, match="channels"):
        slam.step(frames[1].image[:, :, :2])
    with pytest.raises(InvalidInput, match="corrupt|truncated|decode"):
        slam.step(b"\xff\xd8not a jpeg")
    ok, jpeg = cv2.imencode(".jpg", frames[2].image[:, :, ::-1])
    assert ok and slam.step(jpeg.tobytes()).template_id is not None


def test_non_finite_odometry_is_refused(frames):
    slam = NeoSLAM(_cfg())
    with pytest.raises(InvalidInput, match="not finite"):
        slam.step(frames[0].image, odometry=(float("nan"), 0.0, 0.1))


def test_run_dir_gets_the_files_of_a_run(tmp_path, frames):
    with NeoSLAM(_cfg(), run_dir=tmp_path) as slam:
        for sf in frames[:5]:
            slam.step(sf.image, odometry=sf.odom, stamp=sf.stamp)
    assert len((tmp_path / "templates.csv").read_text().splitlines()) == 1 + 5
    assert len((tmp_path / "trajectory.tum").read_text().splitlines()) == 5
    assert (tmp_path / "map.json").is_file()


def test_a_refused_image_still_moves_the_robot(frames):
    """The frame's odometry happened whatever its image was: a corrupt frame's motion is integrated
    (without a template), so the next pose is where the wheels say."""
    slam = RatSLAM(_cfg())
    first = slam.step(frames[0].image, odometry=(1.0, 0.0, 0.1))
    with pytest.raises(InvalidInput):
        slam.step(b"\xff\xd8not a jpeg", odometry=(1.0, 0.0, 0.1))
    r = slam.step(frames[1].image, odometry=(1.0, 0.0, 0.1))
    assert r.frame == 2 and r.pose[0] - first.pose[0] == pytest.approx(0.2)  # 0.1 m per sample, both counted
