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


def automasked_error(reprojection: Tensor, valid: Tensor, identity: Tensor | None, mask: Tensor) -> Tensor:
    """Monodepth2's photometric loss as a measurement: the mean over the target's usable pixels of the
    per-pixel minimum over every validly warped source *and* every unwarped source (no tie-breaking
    noise). A better warp can only lower it, so it compares epochs and checkpoints (the training loss,
    normalised by the pixels the warps win, does not: it rises as harder pixels start to count).

    ``reprojection``, ``valid``, ``identity``: ``[B, S, H, W]``; ``mask``: ``[B, H, W]``."""
    best = torch.where(valid, reprojection, torch.full_like(reprojection, float("inf"))).min(1).values
    if identity is not None:
        best = torch.minimum(best, identity.min(1).values)
    keep = mask & torch.isfinite(best)
    return best[keep].mean() if bool(keep.any()) else best.new_zeros(())


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

    def photometric(self, images: Tensor, target: Tensor) -> Tensor:
        """``[B, S, 3, H, W]`` images against the ``[B, 3, H, W]`` target: ``[B, S, H, W]`` errors."""
        B, S = images.shape[:2]
        flat = images.reshape(B * S, *images.shape[2:])
        rep = target[:, None].expand(B, S, *target.shape[1:]).reshape(B * S, *target.shape[1:])
        return photometric_error(flat, rep, self.alpha).reshape(B, S, *target.shape[2:])

    def identity(self, sources: Tensor, target: Tensor) -> Tensor | None:
        """Errors of the unwarped sources for auto-masking (None when it is off); the same at every scale,
        so compute it once per step."""
        return self.photometric(sources, target) if self.automask else None

    def __call__(
        self,
        target: Tensor,
        warped: Tensor,
        valid: Tensor,
        identity: Tensor | None,
        mask: Tensor,
        measure: bool = True,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """
        Args:
            target: ``[B, 3, H, W]`` un-augmented target image.
            warped: ``[B, S, 3, H, W]`` sources sampled at the warp.
            valid: ``[B, S, H, W]`` warp validity (includes the source body masks).
            identity: ``[B, S, H, W]`` from :meth:`identity`, or None.
            mask: ``[B, H, W]`` target pixels that may contribute (body mask and pixels with a ray).
        Returns ``(loss, used fraction, automasked error)``: the loss is normalised by the number of used
        pixels, never by a count including masked ones; the automasked error (:func:`automasked_error`,
        no gradient needed) is what validation compares across epochs; None without ``measure`` (the
        training step does not need it).
        """
        errors = self.photometric(warped, target)
        loss, used = min_reprojection(errors, valid & mask[:, None], identity)
        used = used & mask
        n = used.sum()
        measured = None
        if measure:
            with torch.no_grad():
                measured = automasked_error(errors, valid & mask[:, None], identity, mask)
        return (loss * used).sum() / n.clamp_min(1), n / used.numel(), measured
