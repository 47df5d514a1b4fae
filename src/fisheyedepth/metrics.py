"""Depth metrics as torchmetrics ``Metric``s, averaged per image over an epoch (KITTI / Monodepth2 style)."""

from __future__ import annotations

import torch
from torch import Tensor
from torchmetrics import Metric

NAMES = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")


def image_metrics(pred: Tensor, gt: Tensor) -> Tensor:
    """The seven metrics of one image's valid pixels (1-D tensors of equal length) as a ``[7]`` tensor."""
    thresh = torch.maximum(gt / pred, pred / gt)
    return torch.stack(
        (
            ((gt - pred).abs() / gt).mean(),
            ((gt - pred) ** 2 / gt).mean(),
            torch.sqrt(((gt - pred) ** 2).mean()),
            torch.sqrt(((torch.log(gt) - torch.log(pred)) ** 2).mean()),
            (thresh < 1.25).float().mean(),
            (thresh < 1.25**2).float().mean(),
            (thresh < 1.25**3).float().mean(),
        )
    )


class DepthMetrics(Metric):
    """abs_rel, sq_rel, rmse, rmse_log, a1, a2, a3, each averaged over images.

    A pixel counts when its ground truth lies in the open interval ``cap`` (metres) and the optional mask
    is set; predictions are clamped to ``cap`` after optional per-image median scaling
    (``median_scaling=True``: prediction * median(gt) / median(pred), for scale-less methods).
    Images without a valid pixel are skipped and counted in ``skipped``. Over zero images the metrics
    are undefined: ``compute`` raises rather than report a perfect 0.
    """

    full_state_update = False

    def __init__(self, cap: tuple[float, float] = (1e-3, 80.0), median_scaling: bool = False, **kwargs):
        super().__init__(**kwargs)
        self.cap, self.median_scaling = (float(cap[0]), float(cap[1])), median_scaling
        self.add_state("sums", default=torch.zeros(len(NAMES), dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("images", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("skipped", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("ratio_sum", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, gt: Tensor, mask: Tensor | None = None) -> None:
        """``pred``, ``gt``: ``[B, 1, H, W]`` (or ``[B, H, W]``); ``mask``: same shape, True = evaluate."""
        pred, gt = pred.reshape(pred.shape[0], -1).double(), gt.reshape(gt.shape[0], -1).double()
        valid = (gt > self.cap[0]) & (gt < self.cap[1])
        if mask is not None:
            valid &= mask.reshape(mask.shape[0], -1).bool()
        for p, g, v in zip(pred, gt, valid, strict=True):
            if not bool(v.any()):
                self.skipped += 1
                continue
            p, g = p[v], g[v]
            ratio = torch.ones((), dtype=p.dtype, device=p.device)
            if self.median_scaling:
                ratio = g.median() / p.median().clamp_min(1e-12)
                p = p * ratio
            self.sums += image_metrics(p.clamp(*self.cap), g)
            self.ratio_sum += ratio
            self.images += 1

    def compute(self) -> dict[str, Tensor]:
        if int(self.images) == 0:
            raise ValueError(
                f"no image had a pixel to score (ground truth in {self.cap[0]:g}-{self.cap[1]:g} m, "
                f"{int(self.skipped)} image(s) without one): the metrics of zero pixels are undefined"
            )
        n = self.images.double()
        out = {name: self.sums[i] / n for i, name in enumerate(NAMES)}
        if self.median_scaling:
            out["scale_ratio"] = self.ratio_sum / n
        return out
