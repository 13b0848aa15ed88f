"""ResNet + FPN, written here (no torchvision): FocusBEV's image backbone.

:class:`ResNet` is He et al.'s network (basic blocks for depths 18 / 34, bottlenecks for 50 /
101), with a ``width`` multiplier on every stage (64 = the published network) so a CPU-sized
trunk is the same code. :class:`FPN` is Lin et al.'s feature pyramid: 1x1 lateral convolutions,
top-down nearest upsampling, 3x3 output convolutions; levels finer than the trunk's last stage
come from its stages, coarser ones from stride-2 3x3 convolutions on the previous level (as
RetinaNet's and PON's P6 / P7).
"""

from __future__ import annotations

from torch import nn
from torch.nn import functional as F

#: depth -> (block kind, blocks per stage)
RESNET_DEPTHS: dict[int, tuple[str, tuple[int, int, int, int]]] = {
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
    101: ("bottleneck", (3, 4, 23, 3)),
}


class _Basic(nn.Module):
    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(cin, planes, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.down = _shortcut(cin, planes, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        return F.relu(self.bn2(self.conv2(y)) + self.down(x), inplace=True)


class _Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int) -> None:
        super().__init__()
        out = planes * 4
        self.conv1 = nn.Conv2d(cin, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride, 1, bias=False)  # stride on the 3x3 (ResNet v1.5)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, out, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(out)
        self.down = _shortcut(cin, out, stride)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)), inplace=True)
        y = F.relu(self.bn2(self.conv2(y)), inplace=True)
        return F.relu(self.bn3(self.conv3(y)) + self.down(x), inplace=True)


def _shortcut(cin: int, cout: int, stride: int) -> nn.Module:
    if cin == cout and stride == 1:
        return nn.Identity()
    return nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))


class ResNet(nn.Module):
    """ResNet trunk without its classifier: ``forward`` returns the outputs of stages 1-4
    (strides 4, 8, 16, 32), :attr:`out_channels` their widths.

    Args:
        depth: 18, 34, 50 or 101.
        width: channels of the stem and of stage 1's blocks (64 = the published networks).
        in_channels: image channels (3 for RGB, the label count for one-hot label images).
    """

    def __init__(self, depth: int = 50, width: int = 64, in_channels: int = 3) -> None:
        super().__init__()
        kind, counts = RESNET_DEPTHS[depth]
        block = _Basic if kind == "basic" else _Bottleneck
        self.stem = nn.Sequential(nn.Conv2d(in_channels, width, 7, 2, 3, bias=False), nn.BatchNorm2d(width),
                                  nn.ReLU(inplace=True), nn.MaxPool2d(3, 2, 1))
        cin, stages, self.out_channels = width, [], []
        for i, n in enumerate(counts):
            planes = width * 2 ** i
            blocks = []
            for j in range(n):
                blocks.append(block(cin, planes, 2 if (j == 0 and i > 0) else 1))
                cin = planes * block.expansion
            stages.append(nn.Sequential(*blocks))
            self.out_channels.append(cin)
        self.stages = nn.ModuleList(stages)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x):
        """``(B, C_in, h, w)`` -> list of 4 feature maps at strides 4, 8, 16, 32."""
        x = self.stem(x)
        out = []
        for stage in self.stages:
            x = stage(x)
            out.append(x)
        return out


class FPN(nn.Module):
    """Feature pyramid over a trunk's stage outputs: ``levels`` maps of ``channels`` channels at
    strides ``8, 16, 32, ...`` (stage outputs from stride 8 on; extra levels by stride-2 convs).

    Args:
        in_channels: widths of the trunk's stages at strides 4, 8, 16, 32.
        channels: width of every pyramid level.
        levels: number of levels (1..5: strides 8 .. 128).
    """

    def __init__(self, in_channels: list[int], channels: int, levels: int) -> None:
        super().__init__()
        used = in_channels[1:]  # strides 8, 16, 32
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in used)
        # every stage feeds the top-down path; output convs only for the levels returned
        self.output = nn.ModuleList(nn.Conv2d(channels, channels, 3, 1, 1) for _ in range(min(levels, len(used))))
        self.extra = nn.ModuleList(nn.Conv2d(channels, channels, 3, 2, 1) for _ in range(max(levels - len(used), 0)))
        self.levels = levels

    def forward(self, feats):
        """Trunk outputs (strides 4..32) -> ``levels`` maps, finest first."""
        c = feats[1:]
        lat = [conv(f) for conv, f in zip(self.lateral, c)]
        for i in range(len(lat) - 2, -1, -1):  # top-down: coarse into fine
            lat[i] = lat[i] + F.interpolate(lat[i + 1], size=lat[i].shape[-2:], mode="nearest")
        out = [conv(f) for conv, f in zip(self.output, lat)]
        for conv in self.extra:
            out.append(conv(F.relu(out[-1])))
        return out[:self.levels]


__all__ = ["FPN", "RESNET_DEPTHS", "ResNet"]
