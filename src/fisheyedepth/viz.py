"""Pictures people read faster than numbers: colourised distance, error maps and panels."""

from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import Tensor


def colourise(
    value: Tensor | np.ndarray,
    vmin: float,
    vmax: float,
    invalid: np.ndarray | None = None,
    log: bool = True,
    cmap: int = cv2.COLORMAP_TURBO,
) -> np.ndarray:
    """``[H, W]`` values to ``[H, W, 3]`` uint8 RGB (near = warm, far = cool on a log scale by default);
    ``invalid`` pixels (or non-positive values) are black."""
    v = (
        value.detach().float().cpu().numpy()
        if isinstance(value, Tensor)
        else np.asarray(value, dtype=np.float32)
    )
    bad = ~np.isfinite(v) | (v <= 0)
    if invalid is not None:
        bad |= invalid
    v = np.clip(np.where(bad, vmin, v), vmin, vmax)
    t = (np.log(v) - np.log(vmin)) / (np.log(vmax) - np.log(vmin)) if log else (v - vmin) / (vmax - vmin)
    rgb = cv2.applyColorMap(((1 - t) * 255).astype(np.uint8), cmap)[..., ::-1].copy()
    rgb[bad] = 0
    return rgb


def to_uint8(image: Tensor) -> np.ndarray:
    """``[3, H, W]`` float in [0, 1] to ``[H, W, 3]`` uint8."""
    return (image.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255 + 0.5).astype(np.uint8)


def panel(
    image: Tensor, distance: Tensor, gt: Tensor | None = None, vmin: float = 0.5, vmax: float = 80.0
) -> np.ndarray:
    """Input | predicted distance | [ground truth | relative error (0..50 %)] side by side, uint8 RGB."""
    tiles = [to_uint8(image), colourise(distance[0], vmin, vmax)]
    if gt is not None:
        g, d = gt[0].detach().float().cpu(), distance[0].detach().float().cpu()
        tiles.append(colourise(g, vmin, vmax))
        err = torch.where(g > 0, (d - g).abs() / g.clamp_min(1e-6), torch.zeros_like(g)).numpy()
        heat = cv2.applyColorMap((np.clip(err / 0.5, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)[
            ..., ::-1
        ]
        heat = heat.copy()
        heat[(g <= 0).numpy()] = 0
        tiles.append(heat)
    return np.concatenate(tiles, axis=1)
