"""Distance hints from a plane sweep, and the loss that uses them where they beat the prediction.

Depth Hints (Watson et al., 2019) add ``|log L - log h|`` wherever a precomputed distance ``h`` warps
the sources better than the prediction ``L``: the hint reaches matches that a warp's local gradient
cannot (a pole 2 m away moves tens of pixels between sources), and the photometric test keeps it out
wherever it is worse. Here the hints come from a sweep over candidate distances along each fisheye
ray, as a stereo matcher would find them: every candidate's photometric error, averaged over a window
(so one pixel's chance match does not win), the forward and backward sources agreeing on the minimum,
and the minimum clearly below any candidate away from it (a unique match).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras.base import CameraModel
from ..geometry.warp import sample, warp_to_source
from .photometric import photometric_error


def candidate_distances(min_distance: float, max_distance: float, count: int) -> Tensor:
    """``count`` distances, log-spaced from ``min_distance`` to ``max_distance`` (float64)."""
    if not (0 < min_distance < max_distance) or count < 2:
        raise ValueError(f"candidates: need 0 < {min_distance} < {max_distance} and count {count} >= 2")
    return torch.logspace(
        torch.log10(torch.tensor(min_distance, dtype=torch.float64)),
        torch.log10(torch.tensor(max_distance, dtype=torch.float64)),
        count,
        dtype=torch.float64,
    )


def window_mean(error: Tensor, valid: Tensor, window: int, min_share: float = 0.6) -> Tensor:
    """Mean of ``error [B, H, W]`` over the valid pixels of each ``window x window`` neighbourhood;
    ``inf`` where fewer than ``min_share`` of them are valid."""
    pad = window // 2
    ok = valid.to(error.dtype)[:, None]
    num = F.avg_pool2d((error * ok.squeeze(1))[:, None], window, 1, pad, count_include_pad=True)
    den = F.avg_pool2d(ok, window, 1, pad, count_include_pad=True)
    mean = (num / den.clamp_min(1e-6))[:, 0]
    return torch.where(den[:, 0] >= min_share, mean, torch.full_like(mean, float("inf")))


@torch.no_grad()
def sweep_costs(
    target: Tensor,
    source: Tensor,
    rays: Tensor,
    rays_valid: Tensor,
    T_target_to_source: Tensor,
    source_cameras: CameraModel | Sequence[CameraModel],
    source_mask: Tensor | None,
    candidates: Tensor,
    window: int = 7,
) -> Tensor:
    """``[B, K, H, W]``: for each of the K candidate distances, the photometric error of ``source``
    warped onto ``target`` (``[B, 3, H, W]`` each) as if every pixel were that far along its ray,
    averaged over a window (:func:`window_mean`); ``inf`` where the warp leaves the source."""
    costs = []
    for d in candidates.tolist():
        distance = torch.full(rays.shape[:3], d, dtype=rays.dtype, device=rays.device)
        warp = warp_to_source(rays, rays_valid, distance, T_target_to_source, source_cameras, source_mask)
        error = photometric_error(sample(source, warp.grid), target)
        costs.append(window_mean(error, warp.valid, window))
    return torch.stack(costs, 1)


@torch.no_grad()
def plane_sweep(
    target: Tensor,
    sources: Tensor,
    poses: Tensor,
    rays: Tensor,
    rays_valid: Tensor,
    source_cameras: Sequence[Sequence[CameraModel]],
    source_masks: Tensor | None,
    candidates: Tensor,
    window: int = 7,
    ratio: float = 0.8,
    agree: int = 2,
) -> tuple[Tensor, Tensor]:
    """Distance hints for ``target [B, 3, H, W]`` from its ``sources [B, S, 3, H, W]`` (S >= 2, e.g. the
    frames before and after) at ``poses [B, S, 4, 4]`` (target to source).

    Returns ``(distance [B, H, W], valid [B, H, W])``. The distance is the candidate with the lowest
    summed cost over the sources (:func:`sweep_costs`). A pixel is valid where every source reaches it,
    each source's own minimum lies within ``agree`` candidates of every other's (a left-right check in
    time: an occlusion or a repeated texture rarely fools both), the minimum beats the pixel's unwarped
    error (the same test as auto-masking: a static or textureless pixel is not evidence), it is
    below ``ratio`` times the lowest cost more than ``agree + 1`` candidates away (a unique match), and
    it is not the first or last candidate (which only bound the distance: the sky's is the last).
    """
    B, S = sources.shape[:2]
    if S < 2:
        raise ValueError(f"plane_sweep: needs at least two sources, got {S}")
    total, mins, unwarped = None, [], []
    for j in range(S):
        cams = [c[j] for c in source_cameras]
        mask = None if source_masks is None else source_masks[:, j]
        cost = sweep_costs(
            target, sources[:, j], rays, rays_valid, poses[:, j], cams, mask, candidates, window
        )
        mins.append(cost.argmin(1))
        unwarped.append(window_mean(photometric_error(sources[:, j], target), rays_valid, window))
        total = cost if total is None else total + cost
    best, arg = total.min(1)
    K = total.shape[1]
    index = torch.arange(K, device=total.device).view(1, K, 1, 1)
    away = (index - arg[:, None]).abs() > agree + 1
    second = torch.where(away, total, torch.full_like(total, float("inf"))).min(1).values
    agreeing = torch.ones_like(rays_valid)
    for j in range(1, S):
        agreeing &= (mins[j] - mins[0]).abs() <= agree
    still = torch.stack(unwarped, 1).sum(1)
    inner = (arg > 0) & (arg < K - 1)  # the first or last candidate means "this near or nearer" (or farther)
    valid = rays_valid & torch.isfinite(best) & inner & agreeing & (best < ratio * second) & (best < still)
    distance = candidates.to(total.dtype)[arg]
    return torch.where(valid, distance, torch.zeros_like(distance)), valid


def hint_loss(distance: Tensor, hint: Tensor, use: Tensor) -> tuple[Tensor, Tensor]:
    """Depth Hints' term in log distance: the mean of ``|log L - log h|`` over the pixels in ``use``
    (``[B, H, W]``: a valid hint that warps the sources better than the prediction), divided by all
    pixels of the batch so a batch with few hints weighs little. Returns ``(loss, share of pixels)``."""
    distance = distance[:, 0] if distance.dim() == 4 else distance
    safe = torch.where(use, hint, torch.ones_like(hint))
    gap = (distance.clamp_min(1e-6).log() - safe.log()).abs()
    n = use.numel()
    return torch.where(use, gap, torch.zeros_like(gap)).sum() / n, use.sum() / n
