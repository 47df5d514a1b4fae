"""Training augmentation: colour jitter for the network input only, and a geometrically consistent flip."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch
from torch import Tensor

from ..geometry import mirror_pose_x


@dataclasses.dataclass
class Augment:
    """Training augmentation: flip probability and colour-jitter ranges (Monodepth2's defaults)."""

    flip: float = 0.5
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.1


_GREY = torch.tensor([0.299, 0.587, 0.114])


def colour_jitter(
    images: Tensor,
    brightness: float,
    contrast: float,
    saturation: float,
    hue: float,
    generator: torch.Generator | None = None,
) -> Tensor:
    """One random jitter applied alike to every image of ``[..., 3, H, W]`` (Monodepth2's ranges:
    0.2, 0.2, 0.2, 0.1). Hue rotates the chroma plane (YIQ) by up to ``hue`` turns."""

    def draw(spread: float) -> float:
        return 1.0 + (2 * torch.rand((), generator=generator).item() - 1) * spread

    out = images * draw(brightness)
    grey = (out * _GREY.to(out)[:, None, None]).sum(-3, keepdim=True)
    out = grey.mean((-2, -1), keepdim=True) + draw(contrast) * (out - grey.mean((-2, -1), keepdim=True))
    grey = (out * _GREY.to(out)[:, None, None]).sum(-3, keepdim=True)
    out = grey + draw(saturation) * (out - grey)
    if hue:
        angle = (2 * torch.rand((), generator=generator).item() - 1) * hue * 2 * math.pi
        yiq = torch.tensor([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]]).to(out)
        c, s = math.cos(angle), math.sin(angle)
        rot = torch.tensor([[1.0, 0, 0], [0, c, -s], [0, s, c]]).to(out)
        m = torch.linalg.inv(yiq) @ rot @ yiq
        out = torch.einsum("ij,...jhw->...ihw", m, out)
    return out.clamp(0, 1)


def flip_sample(sample: dict[str, Any]) -> dict[str, Any]:
    """Mirror a sample left-right: images, masks and ground truth flip, the camera model flips
    (``u0 -> W - 1 - u0``, and what the model needs), and relative poses mirror (``M T M``)."""
    out = dict(sample)
    for key in ("image", "image_aug", "sources", "sources_aug", "mask", "source_mask", "distance"):
        if key in out:
            out[key] = out[key].flip(-1)
    out["camera"] = sample["camera"].flip()
    if "source_camera" in out:
        out["source_camera"] = [c.flip() for c in sample["source_camera"]]
    out["poses"] = mirror_pose_x(sample["poses"])
    return out
