"""What a distance map from geometry is worth against ground truth, and how it looks."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from ..viz import colourise


def score(
    distance: Tensor | np.ndarray, truth: Tensor | np.ndarray, among: Tensor | np.ndarray
) -> dict[str, Any]:
    """abs_rel, a1 and coverage of ``distance`` (0: no estimate) on ``among`` (pixels with truth), and the
    constant map at the truth's median on the same scored pixels: a score of nothing is ``None``, never 0."""
    distance, truth, among = (torch.as_tensor(np.asarray(x)) if isinstance(x, np.ndarray) else x
                              for x in (distance, truth, among))  # fmt: skip
    among = among & (truth > 0)
    kept = among & (distance > 0)
    if not kept.any():
        return {"abs_rel": None, "a1": None, "coverage": 0.0, "pixels": 0, "constant_abs_rel": None}
    d, t = distance[kept].double(), truth[kept].double()
    ratio = d / t
    constant = t.median()
    return {
        "abs_rel": round(float((ratio - 1).abs().mean()), 4),
        "a1": round(float((torch.maximum(ratio, 1 / ratio) < 1.25).double().mean()), 4),
        "coverage": round(float(kept.sum() / among.sum().clamp(min=1)), 4),
        "pixels": int(kept.sum()),
        "constant_abs_rel": round(float(((constant - t).abs() / t).mean()), 4),
    }


def panel(
    image: np.ndarray, checked: np.ndarray, dense: np.ndarray, truth: np.ndarray | None = None
) -> np.ndarray:
    """image | checked | dense [| ground truth], ``H x (3|4)W x 3`` BGR uint8 for cv2, on one colour scale
    (the dense map's range). ``image``: ``H x W`` or ``H x W x 3`` RGB, uint8 or floats in [0, 1]."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = np.clip(image * 255, 0, 255).astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    seen = dense[dense > 0]
    vmin, vmax = (0.3, 20.0) if seen.size == 0 else (float(seen.min()), float(seen.max()))
    vmin, vmax = max(vmin, 0.05), max(vmax, vmin * 1.5)
    tiles = [image, colourise(checked, vmin, vmax), colourise(dense, vmin, vmax)]
    if truth is not None:
        tiles.append(colourise(truth, vmin, vmax))
    return np.ascontiguousarray(np.concatenate(tiles, axis=1)[..., ::-1])
