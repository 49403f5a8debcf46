"""The CNN backbones of stage A (torch modules): AlexNet up to conv3 and EfficientNet-Lite0.

Only the process that runs stage A imports this module (and so torch).
"""

from __future__ import annotations

import torch
from torch import nn


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
