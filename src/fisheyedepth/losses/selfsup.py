"""Minimum reprojection with auto-masking (Monodepth2), over fisheye warps, and edge-aware smoothness;
two levers for what a still world under fixed light does not have: a per-image brightness correction
(auto-exposure, white balance) and trimming of the pixels no warp explains (moving objects)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .photometric import photometric_error

BRIGHTNESS = ("none", "affine")
INVALID_WARP_ERROR = 1.0
"""What a source costs at a pixel its warp cannot reach (outside the source image, no ray, body) when
its unwarped error is not given: the largest photometric error (0.85 + 0.15 for images in [0, 1])."""


def min_reprojection(
    reprojection: Tensor,
    valid: Tensor,
    unwarped: Tensor | None = None,
    automask: bool = True,
    noise: float = 1e-5,
) -> tuple[Tensor, Tensor]:
    """Monodepth2's per-pixel minimum over the warped sources and, with auto-masking, the unwarped ones.

    Args:
        reprojection: ``[B, S, H, W]`` photometric error of each warped source.
        valid: ``[B, S, H, W]`` the warp of that source is meaningful (see ``warp_to_source``). A pixel
            that no source's warp reaches costs the best unwarped error there (what it costs not to warp;
            :data:`INVALID_WARP_ERROR` without ``unwarped``), never zero: every pixel counts, so a network
            cannot lower its loss by pushing warps out of the image.
        unwarped: ``[B, S, H, W]`` error of the *unwarped* sources, or None.
        automask: also take the minimum over the unwarped sources (needs ``unwarped``).
        noise: tie-breaking noise added to the unwarped errors for auto-masking (0 to measure).
    Returns:
        ``(error [B, H, W], used [B, H, W] bool)``: every pixel has an error; it depends on the distance
        only where it is used, i.e. where a valid warp gives the minimum.
    """
    best = torch.where(valid, reprojection, torch.full_like(reprojection, float("inf"))).min(1).values
    used = torch.isfinite(best)
    fallback = unwarped.min(1).values if unwarped is not None else torch.full_like(best, INVALID_WARP_ERROR)
    best = torch.where(used, best, fallback)
    if automask and unwarped is not None:
        still = (unwarped + noise * torch.randn_like(unwarped) if noise else unwarped).min(1).values
        used = used & (best < still)
        best = torch.minimum(best, still)
    return best, used


def automasked_error(reprojection: Tensor, valid: Tensor, unwarped: Tensor | None, mask: Tensor) -> Tensor:
    """Monodepth2's auto-masked photometric loss as a measurement: :func:`min_reprojection` without
    tie-breaking noise, averaged over the target's usable pixels (``mask``). A better warp can only
    lower it, so it compares epochs and checkpoints.

    ``reprojection``, ``valid``, ``unwarped``: ``[B, S, H, W]``; ``mask``: ``[B, H, W]``."""
    best, _ = min_reprojection(reprojection, valid, unwarped, automask=True, noise=0.0)
    return best[mask].mean() if bool(mask.any()) else best.new_zeros(())


def match_brightness(images: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
    """``images [B, S, 3, H, W]`` with each channel of each image mapped affinely onto the ``target
    [B, 3, H, W]``'s brightness: mean and standard deviation matched over the pixels of ``valid [B, S,
    H, W]`` (all without it). An exposure or white-balance change between two frames is such a map; the
    gain and offset carry no gradient (constants of the step, as a camera's exposure is), and the gain is
    kept within [0.5, 2] (a warp that shows something else must not be rescaled into agreement)."""
    w = torch.ones_like(images[:, :, :1]) if valid is None else valid[:, :, None].to(images.dtype)
    n = w.sum((-2, -1), keepdim=True).clamp_min(1.0)
    t = target[:, None]
    with torch.no_grad():
        mean_i, mean_t = (images * w).sum((-2, -1), keepdim=True) / n, (t * w).sum((-2, -1), keepdim=True) / n
        std_i = (((images - mean_i) ** 2 * w).sum((-2, -1), keepdim=True) / n).sqrt()
        std_t = (((t - mean_t) ** 2 * w).sum((-2, -1), keepdim=True) / n).sqrt()
        gain = (std_t / std_i.clamp_min(1e-4)).clamp(0.5, 2.0)
        offset = mean_t - gain * mean_i
    return images * gain + offset


def trimmed(error: Tensor, mask: Tensor, fraction: float) -> Tensor:
    """``[B, H, W]`` bool: the pixels of ``mask`` whose ``error`` is not among the worst ``fraction`` of
    their image's (a trimmed mean's pixels; pixels no warp explains, like a moving car's, are the worst)."""
    if fraction <= 0:
        return mask
    keep = mask.clone()
    for b in range(error.shape[0]):
        values = error[b][mask[b]].detach()
        if values.numel() > 1:
            keep[b] &= error[b].detach() <= torch.quantile(values.float(), 1.0 - fraction).to(error.dtype)
    return keep


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
    brightness: str = "none"  # "affine": match_brightness before the error (warped and unwarped sources)
    trim: float = 0.0  # the worst fraction of each image's pixels left out of the loss (trimmed)
    # (images, targets, alpha) -> per-pixel error; training may swap in a torch.compile'd one
    error_fn: Callable[[Tensor, Tensor, float], Tensor] = photometric_error

    def __post_init__(self) -> None:
        if self.brightness not in BRIGHTNESS:
            raise ValueError(f"brightness: {self.brightness!r} is not one of {', '.join(BRIGHTNESS)}")
        if not 0.0 <= self.trim < 1.0:
            raise ValueError(f"outliers: {self.trim!r} is not a fraction in [0, 1)")

    def photometric(self, images: Tensor, target: Tensor, valid: Tensor | None = None) -> Tensor:
        """``[B, S, 3, H, W]`` images against the ``[B, 3, H, W]`` target: ``[B, S, H, W]`` errors
        (``valid [B, S, H, W]``: the pixels a brightness correction is fitted on)."""
        if self.brightness == "affine":
            images = match_brightness(images, target, valid)
        B, S = images.shape[:2]
        flat = images.reshape(B * S, *images.shape[2:])
        rep = target[:, None].expand(B, S, *target.shape[1:]).reshape(B * S, *target.shape[1:])
        return self.error_fn(flat, rep, self.alpha).reshape(B, S, *target.shape[2:])

    def identity(self, sources: Tensor, target: Tensor) -> Tensor:
        """Errors of the unwarped sources (auto-masking, and the cost of a warp that cannot reach a
        pixel); the same at every scale, so compute it once per step."""
        return self.photometric(sources, target)

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
            identity: ``[B, S, H, W]`` from :meth:`identity` (or None: unreachable pixels cost
                :data:`INVALID_WARP_ERROR`).
            mask: ``[B, H, W]`` target pixels that may contribute (body mask and pixels with a ray).
        Returns ``(loss, used fraction, automasked error)``: the loss is the mean of
        :func:`min_reprojection` over the usable pixels (``mask``): a pixel the warps do not win costs
        its unwarped error and still counts, as in Monodepth2's mean
        over all pixels, so discarding pixels never pays. The used fraction is of the usable pixels;
        the automasked error (:func:`automasked_error`, no gradient) is what validation compares
        across epochs; None without ``measure`` (the training step does not need it).
        """
        valid = valid & mask[:, None]
        errors = self.photometric(warped, target, valid)
        best, used = min_reprojection(errors, valid, identity, self.automask)
        used = used & mask
        n = mask.sum().clamp_min(1)
        measured = None
        if measure:
            with torch.no_grad():
                measured = automasked_error(errors, valid, identity, mask)
        if self.trim > 0:  # the worst pixels leave the mean, and the used fraction
            scored = trimmed(best, mask, self.trim)
            return (best * scored).sum() / scored.sum().clamp_min(1), (used & scored).sum() / n, measured
        return (best * mask).sum() / n, used.sum() / n, measured
