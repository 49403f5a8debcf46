"""The in-process API: NeoSLAM / RatSLAM hosting the run's nodes in the caller's process."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from neoslam_stream import NeoSLAM, RatSLAM, load_config
from neoslam_stream.runtime.messages import MessageError
from neoslam_stream.runtime.node import StageInputError
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
    assert list(slam.nodes) == ["A", "B", "C", "D"]
    ids = [slam.step(sf.image).template_id for sf in frames]
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
    out = slam.finish()
    assert [t for t, _ in out][-1] == "experience_map/map"


def test_frames_must_advance_and_bad_input_is_refused_without_breaking_the_chain(frames):
    slam = NeoSLAM(_cfg(), backend=False)
    slam.step(frames[0].image, frame=5)
    with pytest.raises(ValueError, match="not after"):
        slam.step(frames[1].image, frame=5)
    with pytest.raises(MessageError):  # validated like a message from the bus: uint8 images only
        slam.step(frames[1].image.astype(np.float32))
    with pytest.raises(StageInputError, match="corrupt|truncated|decode"):
        slam.step(b"\xff\xd8not a jpeg")
    ok, jpeg = cv2.imencode(".jpg", frames[2].image[:, :, ::-1])
    assert ok and slam.step(jpeg.tobytes()).template_id is not None


def test_non_finite_odometry_is_refused(frames):
    slam = NeoSLAM(_cfg())
    with pytest.raises(MessageError, match="not finite"):
        slam.step(frames[0].image, odometry=(float("nan"), 0.0, 0.1))


def test_run_dir_gets_the_files_of_a_run(tmp_path, frames):
    with NeoSLAM(_cfg(), run_dir=tmp_path) as slam:
        for sf in frames[:5]:
            slam.step(sf.image, odometry=sf.odom, stamp=sf.stamp)
    assert len((tmp_path / "templates.csv").read_text().splitlines()) == 1 + 5
    assert len((tmp_path / "trajectory.tum").read_text().splitlines()) == 5
    assert (tmp_path / "map.json").is_file()
