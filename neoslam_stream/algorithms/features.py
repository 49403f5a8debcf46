"""Stage A: visual features (NeoSLAM's visual feature extractor).

Per camera frame: ``frame_stride`` selection, optional crop, colour mode, the ImageNet
preprocessing of the reference (shorter side to 256, centre crop 224, mean/std; ``input_size``
scales both; with
``photometric: log_standardise`` each frame's log intensity standardised before the mean/std),
and a CNN layer (:mod:`.backbones`): ``alexnet`` (the paper's: conv3 before its ReLU, 384x13x13 =
64896 float32), ``efficientnet_lite0`` (block 10, 112x14x14 = 21952 at 224, the map closest to conv3's 13x13; what
``backbone: auto`` runs without AlexNet's weights) or ``random_alexnet`` (seeded random weights,
for tests and throughput benches only). Weight files and what "auto" means: :mod:`.weights`.
On a CPU the backbone runs frozen (``inference``): the same features to float rounding, faster.

Differences from the ROS 2 NeoSLAM, on purpose: ``frame_stride`` works (frames 0, s, 2s, ...
pass; the ROS 2 counter lets every frame pass); the crop takes [x_min, x_max) as columns and
[y_min, y_max) as rows, as in the paper's equation, and only when enabled; resizing is OpenCV's
bilinear interpolation, not PIL's (which antialiases when downscaling).
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Sequence
from typing import Any, Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from ._config import make_config
from .errors import InvalidInput
from .weights import (
    ALEXNET_URL,
    alexnet_missing_message,
    efficientnet_lite0_weights,
    find_alexnet_weights,
    resolve_device,
)

log = logging.getLogger(__name__)

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def feature_dim(backbone: str, input_size: int = 224) -> int:
    """Length of A's feature vector for a square input of ``input_size`` pixels: AlexNet's conv3
    (384 channels; conv1 of kernel 11, stride 4, padding 2, then two 3x3 max pools of stride 2:
    13x13 at 224) or EfficientNet-Lite0's block 10 (112 channels; four stride-2 convolutions
    padded to keep ceil(n/2): 14x14 at 224)."""
    if backbone in ("alexnet", "random_alexnet"):
        n = (input_size + 4 - 11) // 4 + 1
        for _ in range(2):
            n = (n - 3) // 2 + 1
        return 384 * n * n
    if backbone == "efficientnet_lite0":
        n = input_size
        for _ in range(4):
            n = -(-n // 2)
        return 112 * n * n
    raise ValueError(f"unknown backbone {backbone!r}")


#: the log intensity a frame is brought to by ``photometric: log_standardise``: mean ln 0.5 (mid
#: grey) and spread 0.25 (a pixel one spread away is 0.39 or 0.64; up to 2.8 spreads above the
#: mean stay below 1, brighter pixels clip); set once, not tuned (docs/mapping.md)
LOG_MEAN, LOG_SPREAD = float(np.log(0.5)), 0.25


def log_standardised(img: np.ndarray) -> np.ndarray:
    """HxW or HxWxC float32 in [0, 1] -> the same with each channel's log intensity at mean
    ``LOG_MEAN`` and standard deviation ``LOG_SPREAD`` (values above 1 clipped). A gain g and
    gamma y map log I to y log I + y log g, an affine map that the standardisation removes (up to
    clipping, and the floor of 1/255 that keeps the log of a black pixel finite)."""
    lg = np.log(np.maximum(img, np.float32(1 / 255)))
    mean = lg.mean(axis=(0, 1), dtype=np.float64)
    sd = lg.std(axis=(0, 1), dtype=np.float64)
    scale = (LOG_SPREAD / np.maximum(sd, 1e-6)).astype(np.float32)
    out = np.exp((lg - mean.astype(np.float32)) * scale + np.float32(LOG_MEAN))
    return np.minimum(out, np.float32(1.0), out=out)


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
    #: side of the square the backbone sees: the frame's shorter side is resized to
    #: round(input_size * 256 / 224) and the centre square of ``input_size`` cropped (the
    #: reference's 256 and 224 at the default). A's cost grows with its square, and so does B's
    #: input (:func:`feature_dim`)
    input_size: int = Field(224, ge=64, le=512)
    #: ``log_standardise``: each frame's log intensity (per channel) brought to one mean and
    #: spread before the backbone (:func:`log_standardised`): a change of exposure (a gain) or of
    #: the camera's response curve (a gamma) is an affine change of log intensity, which this
    #: undoes, so a place seen again under other light gives the backbone the same image
    photometric: Literal["none", "log_standardise"] = "none"
    #: torch device of the backbone: auto (cuda when torch sees a GPU), cpu, cuda or cuda:N
    device: str = Field("auto", pattern=r"^(cpu|auto|cuda(:[0-9]+)?)$")
    threads: int = Field(1, ge=1)
    #: on a CPU, ``frozen`` runs the backbone traced, frozen and optimised for inference (torch.jit:
    #: batch norm folded into the convolutions, oneDNN layouts), the same features to float
    #: rounding in two thirds of the time; ``eager`` runs the module as written (the paper profile's
    #: features bit for bit). A GPU always runs it eager
    inference: Literal["eager", "frozen"] = "frozen"
    seed: int = 42


def resolve_backbone(config: FeatureConfig) -> str:
    """The backbone stage A runs: ``config.backbone``, with ``auto`` decided as AlexNet when its
    weights are found (or ``download_weights``), else EfficientNet-Lite0; a configured
    ``weights_path`` that does not exist also means EfficientNet-Lite0 here."""
    if config.backbone != "auto":
        return config.backbone
    try:
        found = find_alexnet_weights(config.weights_path) is not None or config.download_weights
    except FileNotFoundError:
        found = False
    return "alexnet" if found else "efficientnet_lite0"


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

        self.config = make_config(FeatureConfig, config, overrides)
        #: the torch device the backbone runs on (``device: auto`` decided)
        self.device = torch.device(resolve_device(self.config.device))
        torch.set_num_threads(self.config.threads)
        #: the backbone that runs (``backbone: auto`` decided), where its weights came from, the
        #: torch module with those weights
        self.backbone, self.weights_source, self.module = self._build(resolve_backbone(self.config))
        self.module.eval().to(self.device)
        #: what runs: the module, or (``inference: frozen`` on a CPU) its frozen, optimised trace
        self.net = self.module
        if self.config.inference == "frozen" and self.device.type == "cpu":
            self.net = self._frozen(self.module, self.config.input_size)
        self.output_dim = feature_dim(self.backbone, self.config.input_size)

    @staticmethod
    def _frozen(net: Any, size: int) -> Any:
        """``net`` traced on one size x size frame, frozen and optimised for inference (any batch size).
        torch marks torch.jit deprecated in favour of torch.compile, which needs a C++ compiler on
        the robot; where a torch cannot trace, the module runs as written (said once)."""
        import torch

        try:
            with warnings.catch_warnings(), torch.inference_mode(False), torch.no_grad():
                warnings.simplefilter("ignore", DeprecationWarning)
                traced = torch.jit.trace(net, torch.zeros(1, 3, size, size), check_trace=False)
                return torch.jit.optimize_for_inference(torch.jit.freeze(traced))
        except (AttributeError, RuntimeError) as exc:
            log.warning("features: inference: frozen is not available with this torch (%s); "
                        "the backbone runs as written", exc)
            return net

    def _build(self, backbone: str) -> tuple[str, str, Any]:
        import torch

        from .backbones import AlexNetConv3, EfficientNetLite0

        cfg = self.config
        if backbone == "alexnet":
            path = find_alexnet_weights(cfg.weights_path)
            if path is None and cfg.download_weights:
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
            raise FileNotFoundError(alexnet_missing_message())
        if backbone == "efficientnet_lite0":
            net = EfficientNetLite0()
            path = efficientnet_lite0_weights()
            net.load_state_dict(torch.load(path, map_location="cpu", weights_only=True), strict=True)
            return "efficientnet_lite0", str(path), net
        if backbone == "random_alexnet":
            gen = torch.Generator().manual_seed(cfg.seed)
            net = AlexNetConv3()
            with torch.no_grad():
                for p in net.parameters():
                    # Kaiming-like scale so activations have a realistic spread
                    fan_in = p[0].numel() if p.dim() > 1 else 1
                    p.copy_(torch.randn(p.shape, generator=gen) * (2.0 / fan_in) ** 0.5 if p.dim() > 1
                            else torch.randn(p.shape, generator=gen) * 0.01)
            return "random_alexnet", f"random (seed {cfg.seed})", net
        raise ValueError(f"unknown backbone {backbone!r}")

    # ---------------------------------------------------------------- steps
    def crop_array(self, img: np.ndarray) -> np.ndarray:
        """Crop columns [x_min, x_max) and rows [y_min, y_max) (paper's convention) when enabled."""
        cfg = self.config
        if not cfg.crop_image:
            return img
        h, w = img.shape[:2]
        x0, x1, y0, y1 = cfg.x_min, cfg.x_max, cfg.y_min, cfg.y_max
        x1 = w if x1 is None else x1
        y1 = h if y1 is None else y1
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise InvalidImage(f"crop x[{x0},{x1}) y[{y0},{y1}) does not fit a {w}x{h} (WxH) image")
        return img[y0:y1, x0:x1]

    def preprocess(self, rgb: np.ndarray) -> np.ndarray:
        """HxWx3 uint8 RGB -> 3xSxS float32 normalised, S = ``input_size`` (shorter side to
        round(S * 256 / 224), centre crop S: 256 and 224 at the default).

        ``colour: grey`` gives the backbone the grey image in all three channels. The grey image is
        resized and scaled once, and each channel normalised from it: the same numbers as resizing
        the three equal channels (the resize treats channels alike) in a third of the work."""
        img = self.crop_array(rgb)
        grey = self.config.colour == "grey"
        if grey:
            img = cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_RGB2GRAY)
        size = self.config.input_size
        side = round(size * 256 / 224)
        h, w = img.shape[:2]
        scale = side / min(h, w)
        nh, nw = max(side, round(h * scale)), max(side, round(w * scale))
        img = cv2.resize(np.ascontiguousarray(img), (nw, nh), interpolation=cv2.INTER_LINEAR)
        top, left = (nh - size) // 2, (nw - size) // 2
        img = img[top:top + size, left:left + size].astype(np.float32) / 255.0
        if self.config.photometric == "log_standardise":
            img = log_standardised(img)
        if grey:
            out = np.empty((3, size, size), np.float32)
            for c in range(3):
                np.subtract(img, IMAGENET_MEAN[c], out=out[c])
                np.divide(out[c], IMAGENET_STD[c], out=out[c])
            return out
        img = (img - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(img.transpose(2, 0, 1))

    def warm_up(self, max_batch: int) -> None:
        """Run the frozen backbone on blank batches of every size up to ``max_batch``, twice each:
        torch.jit specialises a frozen graph to each input shape on its first calls, which take up
        to twice as long (bench/stage_a.py ``by_batch``), long enough for a live camera's frames to
        be evicted while A waits. The module as written (eager, a GPU) has no such cost and is
        left alone."""
        if self.net is self.module:
            return
        import torch

        s = self.config.input_size
        with torch.inference_mode():
            for n in range(1, max_batch + 1):
                for _ in range(2):
                    self.net(torch.zeros(n, 3, s, s, device=self.device))

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
