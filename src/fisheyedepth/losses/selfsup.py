"""Minimum reprojection with auto-masking (Monodepth2), over fisheye warps, and edge-aware smoothness."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .photometric import photometric_error


def min_reprojection(
    reprojection: Tensor, valid: Tensor, identity: Tensor | None = None, noise: float = 1e-5
) -> tuple[Tensor, Tensor]:
    """Per-pixel minimum over sources, and where it is used.

    Args:
        reprojection: ``[B, S, H, W]`` photometric error of each warped source.
        valid: ``[B, S, H, W]`` the warp of that source is meaningful (see ``warp_to_source``).
        identity: ``[B, S, H, W]`` error of the *unwarped* sources (auto-masking), or None.
    Returns:
        ``(loss [B, H, W], used [B, H, W] bool)``: a pixel is used when at least one source warps validly
        to it and (with auto-masking) the best warp explains it better than every unwarped source; a small
        noise breaks ties as in Monodepth2.
    """
    inf = torch.full_like(reprojection, float("inf"))
    best, _ = torch.where(valid, reprojection, inf).min(1)
    used = torch.isfinite(best)
    if identity is not None:
        identity = identity + noise * torch.randn_like(identity)
        used = used & (best < identity.min(1).values)
    return torch.where(used, best, torch.zeros_like(best)), used


def edge_aware_smoothness(disp: Tensor, image: Tensor) -> Tensor:
    """Mean of ``|d disp*| exp(-|d I|)`` over x and y, with ``disp* = disp / mean(disp)`` per sample."""
    disp = disp / (disp.mean((2, 3), keepdim=True) + 1e-7)
    dx = (disp[..., :, :-1] - disp[..., :, 1:]).abs()
    dy = (disp[..., :-1, :] - disp[..., 1:, :]).abs()
    ix = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    iy = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()


@dataclass
class ReprojectionLoss:
    """Combines the pieces for one scale; ``__call__`` returns (loss, used-pixel fraction)."""

    automask: bool = True
    alpha: float = 0.85

    def __call__(
        self, target: Tensor, warped: Tensor, valid: Tensor, sources: Tensor, mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """
        Args:
            target: ``[B, 3, H, W]`` un-augmented target image.
            warped: ``[B, S, 3, H, W]`` sources sampled at the warp.
            valid: ``[B, S, H, W]`` warp validity (includes the source body masks).
            sources: ``[B, S, 3, H, W]`` unwarped sources (for auto-masking).
            mask: ``[B, H, W]`` target pixels that may contribute (body mask and pixels with a ray).
        The loss is normalised by the number of used pixels, never by a count including masked ones.
        """
        B, S = warped.shape[:2]
        flat = lambda x: x.reshape(B * S, *x.shape[2:])  # noqa: E731
        rep = lambda x: x[:, None].expand(B, S, *x.shape[1:]).reshape(B * S, *x.shape[1:])  # noqa: E731
        reproj = photometric_error(flat(warped), rep(target), self.alpha).reshape(B, S, *target.shape[2:])
        identity = None
        if self.automask:
            identity = photometric_error(flat(sources), rep(target), self.alpha).reshape(
                B, S, *target.shape[2:]
            )
        loss, used = min_reprojection(reproj, valid & mask[:, None], identity)
        used = used & mask
        n = used.sum()
        return (loss * used).sum() / n.clamp_min(1), n / used.numel()
