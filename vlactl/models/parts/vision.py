"""A small convolutional image tokenizer trained from scratch, and the random-shift augmentation it is trained with."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def _conv(c_in: int, c_out: int, kernel: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=(kernel - 1) // 2 if stride < kernel else 0),
        nn.GroupNorm(8, c_out),
        nn.GELU(),
    )


class ImageTokenizer(nn.Module):
    """[B, cams, 3, H, W] floats in [0, 1] -> [B, cams * tokens_side**2, width] tokens.

    A 4x4 patch stem then stride-2 convolutions down to a tokens_side x tokens_side grid: the stem keeps the cost of
    the 128x128 input low (most of a CPU training step is here), the grid gives the transformer spatial tokens.
    The cameras share weights and are told apart by their own learned position embeddings.
    """

    def __init__(self, cameras: int, channels: tuple[int, ...], width: int, image_size: int, tokens_side: int):
        super().__init__()
        layers = [_conv(3, channels[0], 4, 4)]
        side = image_size // 4
        for c_in, c_out in zip(channels, channels[1:]):
            layers.append(_conv(c_in, c_out, 3, 2))
            side //= 2
        while side > tokens_side:
            layers.append(_conv(channels[-1], channels[-1], 3, 2))
            side //= 2
        if side != tokens_side:
            raise ValueError(f"image_size {image_size} does not reduce to a {tokens_side}x{tokens_side} grid")
        self.convs = nn.Sequential(*layers)
        self.proj = nn.Linear(channels[-1], width)
        self.pos = nn.Parameter(torch.randn(cameras, tokens_side * tokens_side, width) * 0.02)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        b, cams = images.shape[:2]
        x = self.convs((images.flatten(0, 1) - 0.5) / 0.25)
        x = self.proj(x.flatten(2).transpose(1, 2))  # [B*cams, tokens, width]
        return (x.unflatten(0, (b, cams)) + self.pos).flatten(1, 2)


def random_shift(images: torch.Tensor, pad: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """DrQ-style augmentation: pad each image by `pad` pixels (edge replicate) and crop it back at a random offset.

    images: float [B, cams, 3, H, W]; every image gets its own integer shift.
    """
    if pad <= 0:
        return images
    b, cams, c, h, w = images.shape
    x = F.pad(images.flatten(0, 1), (pad, pad, pad, pad), mode="replicate")
    shift = torch.randint(0, 2 * pad + 1, (b * cams, 2), generator=generator)
    rows = (shift[:, 0, None] + torch.arange(h))[:, :, None].expand(-1, -1, w)
    cols = (shift[:, 1, None] + torch.arange(w))[:, None, :].expand(-1, h, -1)
    flat = (rows * (w + 2 * pad) + cols).flatten(1)  # [B*cams, H*W] indices into the padded image
    out = x.flatten(2).gather(2, flat[:, None, :].expand(-1, c, -1))
    return out.view(b, cams, c, h, w)
