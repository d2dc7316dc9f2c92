"""The learned crater detector's network (PyTorch; only `pipeline.train` imports torch).

A small U-Net-like encoder-decoder (Ronneberger, Fischer & Brox 2015, "U-Net", MICCAI) with
CenterNet-style heads (Zhou, Wang & Krähenbühl 2019, "Objects as points", arXiv:1904.07850): at
stride 4 it predicts a crater-centre heatmap logit, the log of the rim radius (px) and the
sub-cell offset of the centre (du, dv in cells). The encoder goes to stride 32 with dilated
convolutions (receptive field ~700 px), so rims up to ~400 px across are seen whole; skip
connections at strides 4-16 keep the small ones. ~0.23 M parameters (~0.9 MB as float32).
Input: one channel, the image normalised by `pipeline.core.vision.detectors.learned.normalise`;
height and width multiples of 32.
"""

from __future__ import annotations

import torch
from torch import nn

CHANNELS = (8, 16, 32, 48, 64)
STRIDE = 4
OUTPUTS = ("heat_logit", "log_radius_px", "offset_u", "offset_v")


def _cbr(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation,
                                   bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class CraterNet(nn.Module):
    """Image (B, 1, H, W) -> maps (B, 4, H / 4, W / 4): heat logit, log radius, offsets."""

    def __init__(self, channels: tuple[int, ...] = CHANNELS) -> None:
        super().__init__()
        c = channels
        self.e1 = _cbr(1, c[0], 2)
        self.e2 = nn.Sequential(_cbr(c[0], c[1], 2), _cbr(c[1], c[1]))
        self.e3 = nn.Sequential(_cbr(c[1], c[2], 2), _cbr(c[2], c[2]))
        self.e4 = nn.Sequential(_cbr(c[2], c[3], 2), _cbr(c[3], c[3]))
        self.e5 = nn.Sequential(_cbr(c[3], c[4], 2), _cbr(c[4], c[4], dilation=2),
                                _cbr(c[4], c[4], dilation=4))
        self.d4 = _cbr(c[4] + c[3], c[3])
        self.d3 = _cbr(c[3] + c[2], c[2])
        self.d2 = _cbr(c[2] + c[1], c[1])
        self.head = nn.Conv2d(c[1], len(OUTPUTS), 1)
        self.up = nn.Upsample(scale_factor=2, mode="nearest")
        assert self.head.bias is not None
        with torch.no_grad():  # start from a low prior of a crater per cell (CenterNet)
            self.head.bias.copy_(torch.tensor([-4.0, 1.5, 0.0, 0.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x2 = self.e2(self.e1(x))
        x3 = self.e3(x2)
        x4 = self.e4(x3)
        x5 = self.e5(x4)
        y = self.d4(torch.cat([self.up(x5), x4], 1))
        y = self.d3(torch.cat([self.up(y), x3], 1))
        y = self.d2(torch.cat([self.up(y), x2], 1))
        return self.head(y)
