"""PyTorch versions of MiDaS v2.1 small and VGG16 with the original checkpoints' module layout and key names.

Outside the library on purpose (placejax never imports torch): used as the speed baseline by
``benchmarks.models_speed`` and to write reference outputs in ``tests/torch_refs/``. The layouts
follow isl-org/MiDaS ``MidasNet_small`` (encoder: geffnet ``tf_efficientnet_lite3``) and
``torchvision.models.vgg16``, so ``load_state_dict`` of the official files works with ``strict=True``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

# (kind, repeats, kernel, stride, out channels) of tf_efficientnet_lite3, as in placejax.models.MidasSmall.
_LITE3 = (
    ("ds", 1, 3, 1, 24),
    ("ir", 3, 3, 2, 32),
    ("ir", 3, 5, 2, 48),
    ("ir", 5, 3, 2, 96),
    ("ir", 5, 5, 1, 136),
    ("ir", 6, 5, 2, 232),
    ("ir", 1, 3, 1, 384),
)


class Conv2dSame(nn.Conv2d):
    """TF 'SAME' padding (extra row/column at bottom/right), as geffnet's tf_ models use for stride 2."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pads = []
        for size, k, s in zip(x.shape[-2:], self.kernel_size, self.stride, strict=True):
            total = max((math.ceil(size / s) - 1) * s + k - size, 0)
            pads.append((total // 2, total - total // 2))
        x = F.pad(x, (*pads[1], *pads[0]))
        return F.conv2d(x, self.weight, self.bias, self.stride, 0, self.dilation, self.groups)


def _conv(cin: int, cout: int, k: int, stride: int = 1, groups: int = 1) -> nn.Conv2d:
    if stride > 1:
        return Conv2dSame(cin, cout, k, stride, 0, groups=groups, bias=False)
    return nn.Conv2d(cin, cout, k, stride, k // 2, groups=groups, bias=False)


def _bn(c: int) -> nn.BatchNorm2d:
    return nn.BatchNorm2d(c, eps=1e-3)


class DepthwiseSeparable(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.conv_dw, self.bn1, self.act = _conv(cin, cin, 3, groups=cin), _bn(cin), nn.ReLU6()
        self.conv_pw, self.bn2 = _conv(cin, cout, 1), _bn(cout)

    def forward(self, x):
        return self.bn2(self.conv_pw(self.act(self.bn1(self.conv_dw(x)))))


class InvertedResidual(nn.Module):
    def __init__(self, cin: int, cout: int, k: int, stride: int):
        super().__init__()
        mid = cin * 6
        self.conv_pw, self.bn1 = _conv(cin, mid, 1), _bn(mid)
        self.conv_dw, self.bn2 = _conv(mid, mid, k, stride, groups=mid), _bn(mid)
        self.conv_pwl, self.bn3 = _conv(mid, cout, 1), _bn(cout)
        self.act = nn.ReLU6()
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        y = self.act(self.bn1(self.conv_pw(x)))
        y = self.act(self.bn2(self.conv_dw(y)))
        y = self.bn3(self.conv_pwl(y))
        return y + x if self.residual else y


class ResidualConvUnit(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c, c, 3, 1, 1)
        self.conv2 = nn.Conv2d(c, c, 3, 1, 1)

    def forward(self, x):
        return self.conv2(F.relu(self.conv1(F.relu(x)))) + x


class FeatureFusionBlock(nn.Module):
    def __init__(self, c: int, out: int):
        super().__init__()
        self.resConfUnit1 = ResidualConvUnit(c)
        self.resConfUnit2 = ResidualConvUnit(c)
        self.out_conv = nn.Conv2d(c, out, 1)

    def forward(self, x0, x1=None):
        out = x0 if x1 is None else x0 + self.resConfUnit1(x1)
        out = F.interpolate(self.resConfUnit2(out), scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(out)


class Interpolate(nn.Module):
    def forward(self, x):
        return F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)


class TorchMidasSmall(nn.Module):
    """``MidasNet_small`` (features 64, expand): NCHW normalised RGB → (N, H, W) inverse depth."""

    def __init__(self):
        super().__init__()
        blocks, cin = [], 32
        for kind, repeats, k, stride, cout in _LITE3:
            stage = []
            for i in range(repeats):
                if kind == "ds":
                    stage.append(DepthwiseSeparable(cin, cout))
                else:
                    stage.append(InvertedResidual(cin, cout, k, stride if i == 0 else 1))
                cin = cout
            blocks.append(nn.Sequential(*stage))
        self.pretrained = nn.Module()
        self.pretrained.layer1 = nn.Sequential(_conv(3, 32, 3, 2), _bn(32), nn.ReLU6(), *blocks[0:2])
        self.pretrained.layer2 = nn.Sequential(*blocks[2:3])
        self.pretrained.layer3 = nn.Sequential(*blocks[3:5])
        self.pretrained.layer4 = nn.Sequential(*blocks[5:7])
        s = self.scratch = nn.Module()
        s.layer1_rn = nn.Conv2d(32, 64, 3, 1, 1, bias=False)
        s.layer2_rn = nn.Conv2d(48, 128, 3, 1, 1, bias=False)
        s.layer3_rn = nn.Conv2d(136, 256, 3, 1, 1, bias=False)
        s.layer4_rn = nn.Conv2d(384, 512, 3, 1, 1, bias=False)
        s.refinenet4 = FeatureFusionBlock(512, 256)
        s.refinenet3 = FeatureFusionBlock(256, 128)
        s.refinenet2 = FeatureFusionBlock(128, 64)
        s.refinenet1 = FeatureFusionBlock(64, 64)
        s.output_conv = nn.Sequential(
            nn.Conv2d(64, 32, 3, 1, 1),
            Interpolate(),
            nn.Conv2d(32, 32, 3, 1, 1),
            nn.ReLU(),
            nn.Conv2d(32, 1, 1),
            nn.ReLU(),
        )

    def forward(self, x):
        p, s = self.pretrained, self.scratch
        l1 = p.layer1(x)
        l2 = p.layer2(l1)
        l3 = p.layer3(l2)
        l4 = p.layer4(l3)
        path = s.refinenet4(s.layer4_rn(l4))
        path = s.refinenet3(path, s.layer3_rn(l3))
        path = s.refinenet2(path, s.layer2_rn(l2))
        path = s.refinenet1(path, s.layer1_rn(l1))
        return s.output_conv(path)[:, 0]


class TorchVGG16(nn.Module):
    """``torchvision.models.vgg16`` module layout: ``features``, ``avgpool``, ``classifier``.

    ``width`` scales every conv and fc6/fc7 as ``placejax.models.VGG16(width=...)`` does (1.0 = torchvision)."""

    def __init__(self, num_classes: int = 1000, width: float = 1.0):
        super().__init__()

        def scaled(c: int) -> int:
            return max(1, round(c * width))

        layers, cin = [], 3
        for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
            if v == "M":
                layers.append(nn.MaxPool2d(2, 2))
            else:
                layers += [nn.Conv2d(cin, scaled(v), 3, padding=1), nn.ReLU(inplace=True)]
                cin = scaled(v)
        self.features = nn.Sequential(*layers)
        self.avgpool = nn.AdaptiveAvgPool2d((7, 7))
        hidden = scaled(4096)
        self.classifier = nn.Sequential(
            nn.Linear(cin * 7 * 7, hidden),
            nn.ReLU(True),
            nn.Dropout(0.5),
            nn.Linear(hidden, hidden),
            nn.ReLU(True),
            nn.Dropout(0.5),
            nn.Linear(hidden, num_classes),
        )

    def forward(self, x):
        x = torch.flatten(self.avgpool(self.features(x)), 1)
        return self.classifier(x)

    def fc7(self, x):
        """The post-ReLU fc7 embedding (eval mode: dropout is the identity)."""
        x = torch.flatten(self.avgpool(self.features(x)), 1)
        return self.classifier[:5](x)
