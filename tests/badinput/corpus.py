"""The bad-input corpus: every kind of broken input a robot meets, generated on demand.

Two parts:

* :func:`write_image_folder` writes an image-folder data set (``images/`` + ``odometry.tum``) of
  good frames from the synthetic world with broken files and broken odometry rows among them;
  its manifest says which frames are good and what each bad item is.
* :func:`bus_items` returns ``(topic, payload, stage, cause)`` for messages injected straight into
  a running pipeline's topics: malformed, oversized and wrong-version msgpack, wrong types,
  wrong dtype/shape arrays, NaN/inf and out-of-order odometry, out-of-order templates...

Each item names the stage that must count it and a piece of the cause it must report.
"""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import msgpack
import numpy as np

from neoslam_stream.evaluation import write_tum
from neoslam_stream.runtime.messages import MAX_MESSAGE_BYTES, Message, encode
from neoslam_stream.sources.synthetic import SyntheticWorldSource

#: frame numbers of injected messages: far from the real ones, so none can pass for a real frame,
#: but within a stage's ``max_frame_jump`` (100 000), so that each is refused for its own fault
INJECTED_FRAME = 50_000


@dataclass
class FolderManifest:
    root: Path
    files: list[str] = field(default_factory=list)
    #: indices (frame numbers) of the files that hold a usable image
    good: list[int] = field(default_factory=list)
    #: frame -> (what is wrong, piece of the cause stage A reports)
    bad: dict[int, tuple[str, str]] = field(default_factory=dict)
    #: odometry rows that are broken (NaN/inf, stamp out of order) -> piece of the source's cause
    bad_odometry: dict[int, str] = field(default_factory=dict)


def _png_header_only(width: int, height: int) -> bytes:
    """A PNG signature and IHDR claiming width x height, and no image data."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", len(ihdr)) + b"IHDR" + ihdr
    crc = struct.pack(">I", zlib.crc32(b"IHDR" + ihdr) & 0xFFFFFFFF)
    return b"\x89PNG\r\n\x1a\n" + chunk + crc


def write_image_folder(root: Path, n_good: int = 16, seed: int = 0) -> FolderManifest:
    """Good synthetic frames (PNG and JPEG, colour and grey, one duplicate) with broken files in
    between, and an odometry.tum with a NaN row, an inf row, a stamp going backwards and a stamp
    equal to the previous one."""
    root = Path(root)
    img_dir = root / "images"
    img_dir.mkdir(parents=True, exist_ok=True)
    src = SyntheticWorldSource(seed=seed, width=160, height=96, frames=n_good)
    frames = list(src)
    rng = np.random.default_rng(seed)
    good_png = cv2.imencode(".png", frames[0].image[:, :, ::-1])[1].tobytes()
    good_jpg = cv2.imencode(".jpg", frames[1].image[:, :, ::-1])[1].tobytes()
    bad_items: list[tuple[str, bytes, str, str]] = [
        ("corrupt.jpg", b"\xff\xd8\xff\xe0" + rng.integers(0, 256, 2000, dtype=np.uint8).tobytes() + b"\xff\xd9",
         "corrupt JPEG (random bytes between valid markers)", "cannot decode"),
        ("truncated.jpg", good_jpg[: len(good_jpg) // 2], "JPEG cut in half", "truncated"),
        ("truncated.png", good_png[: len(good_png) // 2], "PNG cut in half", "truncated"),
        ("empty.png", b"", "zero-size file", "empty"),
        ("huge.png", _png_header_only(60000, 60000) + b"IEND", "header claiming 60000x60000 pixels",
         "beyond the limit"),
        ("text.png", b"this is not an image\n", "text file named .png", "cannot decode"),
    ]
    man = FolderManifest(root)
    names: list[tuple[str, bytes]] = []
    # good frames, with a bad item after every second one
    bad_iter = iter(bad_items)
    for k, sf in enumerate(frames):
        img_bgr = sf.image[:, :, ::-1]
        if k == 3:  # a grey frame among colour ones: fine, converted like any other
            data = cv2.imencode(".png", cv2.cvtColor(img_bgr, cv2.COLOR_BGR2GRAY))[1].tobytes()
        elif k % 2:
            data = cv2.imencode(".jpg", img_bgr)[1].tobytes()
        else:
            data = cv2.imencode(".png", img_bgr)[1].tobytes()
        names.append((f"good{k}", data))
        if k == 5:  # a duplicate frame: processed again
            names.append((f"dup{k}", data))
        if k % 2 and (item := next(bad_iter, None)) is not None:
            names.append(("bad", item))  # type: ignore[arg-type]
    stamps, poses = [], []
    x = y = th = 0.0
    for i, (kind, payload) in enumerate(names):
        if kind == "bad":
            fname, data, what, cause = payload  # type: ignore[misc]
            name = f"{i:04d}_{fname}"
            man.bad[i] = (what, cause)
        else:
            ext = ".png" if payload[:4] == b"\x89PNG" else ".jpg"  # type: ignore[index]
            name, data = f"{i:04d}_{kind}{ext}", payload
            man.good.append(i)
        (img_dir / name).write_bytes(data)  # type: ignore[arg-type]
        man.files.append(name)
        x += 0.1 * math.cos(th)
        y += 0.1 * math.sin(th)
        th += 0.05
        stamps.append(0.1 * i)
        poses.append((x, y, th))
    rows = [(t, *p) for t, p in zip(stamps, poses, strict=True)]
    # broken odometry rows on good frames (their image is still processed; their motion is not)
    nan_row, inf_row, back_row = man.good[2], man.good[6], man.good[9]
    rows[nan_row] = (rows[nan_row][0], float("nan"), rows[nan_row][2], rows[nan_row][3])
    man.bad_odometry[nan_row] = "NaN or infinite"
    rows[inf_row] = (rows[inf_row][0], rows[inf_row][1], float("inf"), rows[inf_row][3])
    man.bad_odometry[inf_row] = "NaN or infinite"
    rows[back_row] = (rows[back_row - 2][0] - 0.05, *rows[back_row][1:])
    man.bad_odometry[back_row] = "is not after the previous"
    # a row with the stamp of the row before it: motion in no time (dt = 0)
    same_row = man.good[12]
    rows[same_row] = (rows[same_row - 1][0], *rows[same_row][1:])
    man.bad_odometry[same_row] = "is not after the previous"
    with open(root / "odometry.tum", "w") as fh:  # write_tum would format NaN the same way
        for t, px, py, pth in rows:
            fh.write(f"{t:.6f} {px} {py} 0 0 0 {math.sin(pth / 2):.9f} {math.cos(pth / 2):.9f}\n")
    write_tum(root / "groundtruth.tum", np.array([(t, *p) for t, p in zip(stamps, poses, strict=True)]))
    return man


def _raw(body: dict) -> bytes:
    return msgpack.packb(body, use_bin_type=True)


def _msg(mtype: str, data: dict, frame: int = INJECTED_FRAME) -> bytes:
    return encode(Message(mtype, frame, 1.0, data), validate=False)


def bus_items() -> list[tuple[str, bytes, str, str]]:
    """(topic, payload, stage that must count it, piece of its cause)."""
    f32 = np.float32
    img = np.zeros((96, 160, 3), np.uint8)
    return [
        # --- message codec: everything the decoder must refuse
        ("image", b"\x00garbage", "A", "MessageError"),
        ("image", b"\x93\x01\x02", "A", "MessageError"),  # msgpack, but an array, not a message
        ("image", bytes(MAX_MESSAGE_BYTES + 1), "A", "exceeds MAX_MESSAGE_BYTES"),
        ("image", _raw({"v": 99, "type": "image", "frame": INJECTED_FRAME, "stamp": 0.0, "trace": [],
                        "data": {}}), "A", "schema version"),
        ("image", _msg("odom", {"vtrans": 0.0, "vrot": 0.0, "dt": 0.1}), "A", "on topic 'image'"),
        # --- images: dtype, shape, channels, encodings
        ("image", _msg("image", {"image": img.astype(np.float64), "encoding": "rgb8"}), "A", "dtype"),
        ("image", _msg("image", {"image": np.zeros((96, 160, 5), np.uint8), "encoding": "rgb8"}), "A",
         "channels"),
        ("image", _msg("image", {"image": np.zeros((96, 160, 2), np.uint8), "encoding": "rgb8"}), "A",
         "channels"),
        ("image", _msg("image", {"image": np.zeros((0, 0, 3), np.uint8), "encoding": "rgb8"}), "A", "empty"),
        ("image", _msg("image", {"image": img, "encoding": "mono8"}), "A", "mono8"),
        ("image", _msg("image", {"image": img, "encoding": "yuv422"}), "A", "yuv422"),
        ("image", _msg("image", {"image": np.full((96, 160, 3), np.nan, f32), "encoding": "rgb8"}), "A", ""),
        # --- odometry: NaN / inf, out of order
        ("odom", _msg("odom", {"vtrans": float("nan"), "vrot": 0.0, "dt": 0.1}), "pose_cells", "finite"),
        ("odom", _msg("odom", {"vtrans": 0.1, "vrot": 0.0, "dt": float("inf")}), "pose_cells", "finite"),
        ("odom", _msg("odom", {"vtrans": 0.1, "vrot": 0.0, "dt": 0.1}, frame=0), "pose_cells", "out of order"),
        # --- frame numbers: beyond int64, and far ahead of every frame seen (one message must not
        #     move a stage's frame counter, buffers and checkpoint cuts to the end of time)
        ("odom", _raw({"v": 1, "type": "odom", "frame": 2**64 - 1, "stamp": 1.0, "trace": [],
                       "data": {"vtrans": 0.1, "vrot": 0.0, "dt": 0.1}}), "pose_cells", "int64"),
        ("odom", _msg("odom", {"vtrans": 0.1, "vrot": 0.0, "dt": 0.1}, frame=10**9), "pose_cells",
         "max_frame_jump"),
        # --- template ids: negative, out of order (frame 0 was applied long ago)
        ("visual_template", _msg("visual_template", {"id": -3, "is_loop_closure": False, "relative_rad": 0.0}),
         "pose_cells", "negative"),
        ("visual_template", _msg("visual_template", {"id": 0, "is_loop_closure": False, "relative_rad": 0.0},
                                 frame=0), "pose_cells", "out of order"),
        # --- arrays of the wrong dtype / shape / range between stages
        ("visual_features", _msg("visual_features", {"features": np.full(64896, np.nan, f32)}), "B", ""),
        ("visual_features", _msg("visual_features", {"features": np.zeros(100, f32)}), "B", "shape"),
        ("bin_features", _msg("bin_features", {"bits": np.array([1, 5000], np.int64), "size": 2048}), "C", ""),
        ("bin_features", _msg("bin_features", {"bits": np.array([0.5, 1.5]), "size": 2048}), "C", ""),
        ("sdr", _msg("sdr", {"cells": np.array([70000], np.int64), "size": 65536}), "D", ""),
        ("pose_cells/action", _msg("pose_cells/action", {"action": 0, "src_id": 0, "dst_id": 0,
                                                         "relative_rad": 0.0, "vtrans": float("nan"),
                                                         "vrot": 0.0, "dt": 0.1}), "experience_map", ""),
    ]
