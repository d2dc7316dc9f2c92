"""The learned crater detector's network (PyTorch; only `pipeline.train` imports torch).

An encoder to stride 32 (its last convolution dilated: a receptive field of ~420 px, so rims of
a few hundred pixels are seen whole) and a feature-pyramid decoder (Lin et al. 2017,
"Feature pyramid networks for object detection", CVPR: each level's lateral 1 x 1 projection
added to the upsampled coarser one, then a 3 x 3 convolution) back to stride 4, where
CenterNet-style heads (Zhou, Wang & Krähenbühl 2019, "Objects as points", arXiv:1904.07850) on
a 3 x 3 convolution predict a crater-centre heatmap logit, the log of the rim radius (px) and
the centre's offset from the cell (du, dv in cells). Batch normalisation throughout (folded
into the convolutions at export). 1.04 M parameters (4.2 MB as the exported float32 ONNX).
Input: one channel, the image normalised by
`pipeline.core.vision.detectors.learned.normalise`, turned so that the Sun shines from +u
(`learned.canonical_turns`); height and width multiples of 32.
"""

from __future__ import annotations

import torch
from torch import nn

CHANNELS = (16, 32, 64, 112, 128)  # strides 2, 4, 8, 16, 32
BLOCKS = (1, 2, 2, 2)  # extra 3 x 3 convolutions at strides 4, 8, 16, 32
HEAD_CHANNELS = 64
STRIDE = 4
OUTPUTS = ("heat_logit", "log_radius_px", "offset_u", "offset_v")


def _cbr(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation,
                                   bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def _lateral(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 1, bias=False), nn.BatchNorm2d(c_out))


class CraterNet(nn.Module):
    """Image (B, 1, H, W) -> maps (B, 4, H / 4, W / 4): heat logit, log radius, offsets."""

    def __init__(self, channels: tuple[int, ...] = CHANNELS, blocks: tuple[int, ...] = BLOCKS,
                 head: int = HEAD_CHANNELS) -> None:
        super().__init__()
        c = channels
        self.e1 = _cbr(1, c[0], 2)
        self.e2 = nn.Sequential(_cbr(c[0], c[1], 2), *[_cbr(c[1], c[1]) for _ in range(blocks[0])])
        self.e3 = nn.Sequential(_cbr(c[1], c[2], 2), *[_cbr(c[2], c[2]) for _ in range(blocks[1])])
        self.e4 = nn.Sequential(_cbr(c[2], c[3], 2), *[_cbr(c[3], c[3]) for _ in range(blocks[2])])
        self.e5 = nn.Sequential(_cbr(c[3], c[4], 2), *[_cbr(c[4], c[4], dilation=2 ** (k % 3))
                                                       for k in range(blocks[3])])
        self.lat4, self.lat3, self.lat2 = _lateral(c[3], c[3]), _lateral(c[2], c[2]), \
            _lateral(c[1], c[1])
        self.top4, self.top3, self.top2 = _lateral(c[4], c[3]), _lateral(c[3], c[2]), \
            _lateral(c[2], c[1])
        self.d4, self.d3, self.d2 = _cbr(c[3], c[3]), _cbr(c[2], c[2]), _cbr(c[1], c[1])
        self.neck = _cbr(c[1], head)
        self.head = nn.Conv2d(head, len(OUTPUTS), 1)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        assert self.head.bias is not None
        with torch.no_grad():  # start from a low prior of a crater per cell (CenterNet)
            self.head.bias.copy_(torch.tensor([-4.0, 1.5, 0.0, 0.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x2 = self.e2(self.e1(x))
        x3 = self.e3(x2)
        x4 = self.e4(x3)
        x5 = self.e5(x4)
        y = self.d4(torch.relu(self.up(self.top4(x5)) + self.lat4(x4)))
        y = self.d3(torch.relu(self.up(self.top3(y)) + self.lat3(x3)))
        y = self.d2(torch.relu(self.up(self.top2(y)) + self.lat2(x2)))
        return self.head(self.neck(y))
