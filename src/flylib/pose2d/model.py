"""The DeepFly2D stacked-hourglass network (Newell et al., ECCV 2016) in PyTorch.

A faithful rebuild of the network DeepFly3D/DeepFly2D trained (the pytorch-pose ``hg`` model): a
7x7 stride-2 stem, pre-activation bottlenecks with expansion 2, depth-4 hourglasses, and
intermediate supervision whose score maps are merged back into the features. Module names, and so
``state_dict`` keys and shapes, are those of the published checkpoints (``conv1``, ``bn1``,
``layer1..3``, ``hg.N.hg.L.R.B``, ``res``, ``fc``, ``score``, ``fc_``, ``score_``), which
therefore load strictly without any renaming. With the ``sh8`` hyper-parameters the stem is
``layer1`` 64 planes (64 -> 128, projected skip), ``layer2`` 128 planes (128 -> 256, projected
skip) and ``layer3`` 128 planes on 256 channels (identity skip); ``state_dict()`` then has exactly
the 2,526 entries of the released file (``../shared/spec/deepfly2d-sh8-state-dict.tsv``, checked
in ``tests/pose2d/test_deepfly2d_compat.py``): 25,606,168 parameters, 112.6 GFLOP (56.3 G
multiply-adds) per 256x512 image.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


class Bottleneck(nn.Module):
    """Pre-activation residual block: (BN, ReLU, conv) x3 with ``planes -> 2 * planes`` output."""

    expansion = 2

    def __init__(
        self, inplanes: int, planes: int, stride: int = 1, downsample: nn.Module | None = None
    ):
        super().__init__()
        self.bn1 = nn.BatchNorm2d(inplanes)
        self.conv1 = nn.Conv2d(inplanes, planes, kernel_size=1, bias=True)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, kernel_size=3, stride=stride, padding=1, bias=True)
        self.bn3 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * self.expansion, kernel_size=1, bias=True)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.conv1(self.relu(self.bn1(x)))
        out = self.conv2(self.relu(self.bn2(out)))
        out = self.conv3(self.relu(self.bn3(out)))
        residual = x if self.downsample is None else self.downsample(x)
        return out + residual


class Hourglass(nn.Module):
    """One hourglass of ``depth`` levels. ``hg[level]`` holds the level's residual branches: ``[0]``
    the skip branch, ``[1]`` after pooling, ``[2]`` before upsampling, and, at the innermost level
    only, ``[3]`` the bottom of the hourglass (the pytorch-pose layout)."""

    def __init__(self, num_blocks: int, planes: int, depth: int):
        super().__init__()
        self.depth = depth
        channels = planes * Bottleneck.expansion

        def branch() -> nn.Sequential:
            return nn.Sequential(*[Bottleneck(channels, planes) for _ in range(num_blocks)])

        self.hg = nn.ModuleList(
            nn.ModuleList([branch() for _ in range(4 if level == 0 else 3)])
            for level in range(depth)
        )

    def _level(self, n: int, x: torch.Tensor) -> torch.Tensor:
        branches = self.hg[n - 1]
        up1 = branches[0](x)
        low1 = branches[1](F.max_pool2d(x, 2, stride=2))
        low2 = self._level(n - 1, low1) if n > 1 else branches[3](low1)
        low3 = branches[2](low2)
        return up1 + F.interpolate(low3, scale_factor=2, mode="nearest")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._level(self.depth, x)


class HourglassNet(nn.Module):
    """The DeepFly2D stacked hourglass: ``(N, 3, H, W)`` images -> per-stack heatmaps.

    The heatmaps are at a quarter of the input resolution (``H/4 x W/4``); input sides must be
    multiples of 64 (the stem's /4 and four hourglass poolings). ``num_stacks`` hourglasses (the
    published ``sh8`` checkpoint has 8) of ``depth`` levels, ``num_blocks`` residual blocks per
    branch, ``num_classes`` heatmap channels (19 for DeepFly2D), stem width ``inplanes``, stem
    convolution stride ``init_stride``, ``2 * num_feats`` channels between hourglass blocks.
    """

    def __init__(
        self,
        num_stacks: int = 8,
        num_blocks: int = 1,
        num_classes: int = 19,
        inplanes: int = 64,
        num_feats: int = 128,
        init_stride: int = 2,
        depth: int = 4,
    ):
        super().__init__()
        self.num_stacks = num_stacks
        self.num_classes = num_classes
        self.config = dict(
            num_stacks=num_stacks,
            num_blocks=num_blocks,
            num_classes=num_classes,
            inplanes=inplanes,
            num_feats=num_feats,
            init_stride=init_stride,
            depth=depth,
        )
        self.inplanes = inplanes
        self.conv1 = nn.Conv2d(3, inplanes, kernel_size=7, stride=init_stride, padding=3, bias=True)
        self.bn1 = nn.BatchNorm2d(inplanes)
        self.relu = nn.ReLU(inplace=True)
        # DeepFly2D (pytorch-pose ``hg``) passes the *running* width to layer2: after layer1
        # (inplanes -> 2 inplanes) it is a 2*inplanes-plane bottleneck (2 inplanes -> 4 inplanes,
        # with a projection), and layer3 (num_feats planes) then needs a projection only when
        # 4 inplanes != 2 num_feats (not for sh8).
        self.layer1 = self._make_residual(self.inplanes, 1)
        self.layer2 = self._make_residual(self.inplanes, 1)
        self.layer3 = self._make_residual(num_feats, 1)
        self.maxpool = nn.MaxPool2d(2, stride=2)

        ch = num_feats * Bottleneck.expansion
        self.hg = nn.ModuleList(Hourglass(num_blocks, num_feats, depth) for _ in range(num_stacks))
        self.res = nn.ModuleList(
            self._make_residual(num_feats, num_blocks) for _ in range(num_stacks)
        )
        self.fc = nn.ModuleList(
            nn.Sequential(
                nn.Conv2d(ch, ch, kernel_size=1, bias=True),
                nn.BatchNorm2d(ch),
                nn.ReLU(inplace=True),
            )
            for _ in range(num_stacks)
        )
        self.score = nn.ModuleList(
            nn.Conv2d(ch, num_classes, kernel_size=1, bias=True) for _ in range(num_stacks)
        )
        self.fc_ = nn.ModuleList(
            nn.Conv2d(ch, ch, kernel_size=1, bias=True) for _ in range(num_stacks - 1)
        )
        self.score_ = nn.ModuleList(
            nn.Conv2d(num_classes, ch, kernel_size=1, bias=True) for _ in range(num_stacks - 1)
        )

    def _make_residual(self, planes: int, blocks: int) -> nn.Sequential:
        # The first block changes the width (with a 1x1 projection on the skip path) when the
        # running width differs from its output; `self.inplanes` tracks it.
        out_channels = planes * Bottleneck.expansion
        downsample = None
        if self.inplanes != out_channels:
            downsample = nn.Sequential(
                nn.Conv2d(self.inplanes, out_channels, kernel_size=1, bias=True)
            )
        layers = [Bottleneck(self.inplanes, planes, 1, downsample)]
        self.inplanes = out_channels
        layers += [Bottleneck(out_channels, planes) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> list[torch.Tensor]:
        """Heatmaps of every stack, ``num_stacks`` tensors of ``(N, num_classes, H/4, W/4)``."""
        x = self.relu(self.bn1(self.conv1(x)))
        x = self.layer1(x)
        x = self.maxpool(x)
        x = self.layer3(self.layer2(x))
        outputs = []
        for i in range(self.num_stacks):
            y = self.fc[i](self.res[i](self.hg[i](x)))
            score = self.score[i](y)
            outputs.append(score)
            if i < self.num_stacks - 1:
                x = x + self.fc_[i](y) + self.score_[i](score)
        return outputs

    def heatmaps(self, x: torch.Tensor) -> torch.Tensor:
        """The last stack's heatmaps, ``(N, num_classes, H/4, W/4)`` (what inference uses)."""
        return self.forward(x)[-1]

    @staticmethod
    def output_stride() -> int:
        """Input pixels per heatmap pixel."""
        return 4
