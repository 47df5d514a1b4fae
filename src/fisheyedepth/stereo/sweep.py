"""Sweep stereo on the sphere: metric distance from two or more calibrated cameras, untrained.

For a reference pixel p with unit ray r(p) and a distance hypothesis L, the point ``X = L r(p)`` lands at
``p_s = F_s(T_{ref->s} X)`` in source s (any camera model; a rig's extrinsics, odometry, or both). The
source image, warped to the reference grid at every hypothesis, is compared with the reference in a
window around p (ZNCC or census): the cost volume ``C[d, p]``. Hypotheses are uniform in inverse
distance, as parallax is. Nothing is rectified: a pixel beyond 90 degrees of incidence keeps its
estimate wherever a source sees its point.

Then Hirschmueller's semi-global aggregation along paths of the reference image,

    L_r(p, d) = C(p, d) + min(L_r(p-r, d), L_r(p-r, d+-1) + P1, min_k L_r(p-r, k) + P2) - min_k L_r(p-r, k),

winner-take-all over the summed paths with a parabola through the winner and its neighbours
(sub-hypothesis), a confidence (how unique the winner is), and a round trip: the reference's point,
looked up in the source's own estimate and carried back, must land within ``check_px`` of where it
started (left-right consistency for any geometry), and a winner inside the range, not at its ends.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras.base import CameraModel
from ..cameras.rays import RayCache
from ..geometry.se3 import invert_pose, transform_points
from ..geometry.warp import pixels_to_grid, sample, warp_to_source

COSTS = ("zncc", "census")
UNSEEN = 0.5  # the cost of a hypothesis no source sees: neither a match nor a mismatch (costs are in [0, 1])
RAYS = RayCache(max_entries=16)  # each camera's rays, unprojected once (iterative for most fisheye models)


class View(NamedTuple):
    """One image and its camera. ``image``: ``[B, C, H, W]`` (C = 1 or 3, any range: costs are
    normalised per window); ``T_ref_to_view``: ``[B, 4, 4]`` (or ``[4, 4]``) reference camera to this one
    (the identity for the reference itself)."""

    image: Tensor
    camera: CameraModel
    T_ref_to_view: Tensor


class StereoResult(NamedTuple):
    distance: Tensor  # [B, H, W] metres along the ray; 0 where the check rejects, nothing is seen, or the
    # winner is the range's first or last hypothesis
    dense: Tensor  # [B, H, W] the same before the check: every pixel a source sees at some hypothesis
    confidence: Tensor  # [B, H, W] in [0, 1]: 1 - best / second-best aggregated cost (0 where unseen)
    valid: Tensor  # [B, H, W] bool: kept by the round trip (distance > 0)
    seen: Tensor  # [B, H, W] bool: some source sees the pixel at some hypothesis (dense > 0)


@dataclass(frozen=True)
class SweepStereo:
    """The sweep's settings. ``hypotheses`` distances uniform in inverse distance over
    ``[min_distance, max_distance]`` metres; ``cost``: ``zncc`` (``window`` x ``window``) or ``census``
    (``census_window``); ``p1``, ``p2``: the aggregation's penalties for a step of one hypothesis and for a
    jump, in cost units; ``paths``: 0 (none), 4 or 8; ``check_px``: the round trip's tolerance;
    ``chunk``: hypotheses warped at once (memory against speed; the result does not depend on it)."""

    hypotheses: int = 128
    min_distance: float = 0.3
    max_distance: float = 80.0
    cost: str = "zncc"
    window: int = 11
    census_window: int = 7
    p1: float = 0.03
    p2: float = 0.3
    paths: int = 4
    check_px: float = 1.5
    chunk: int = 32

    def __post_init__(self) -> None:
        if self.cost not in COSTS:
            raise ValueError(f"cost: {self.cost!r} is not one of {', '.join(COSTS)}")
        if not 0 < self.min_distance < self.max_distance < float("inf"):
            raise ValueError(
                f"min_distance, max_distance: {self.min_distance}, {self.max_distance}; "
                "need 0 < min_distance < max_distance < inf"
            )
        if self.hypotheses < 3:
            raise ValueError(f"hypotheses: {self.hypotheses}; at least 3 (the refinement fits a parabola)")
        for name in ("window", "census_window"):
            if getattr(self, name) < 3 or getattr(self, name) % 2 == 0:
                raise ValueError(f"{name}: {getattr(self, name)} is not an odd number >= 3")
        if self.chunk < 1:
            raise ValueError(f"chunk: {self.chunk}; at least 1")
        if self.paths not in (0, 4, 8):
            raise ValueError(f"paths: {self.paths} is not 0, 4 or 8")
        if not (0 <= self.p1 <= self.p2) or self.check_px <= 0:
            raise ValueError(
                f"p1, p2, check_px: {self.p1}, {self.p2}, {self.check_px}; need 0 <= p1 <= p2, check_px > 0"
            )

    def inverse_distances(self, device=None) -> Tensor:
        """``[D]`` inverse distances, nearest first, uniform steps."""
        return torch.linspace(1 / self.min_distance, 1 / self.max_distance, self.hypotheses, device=device)

    # ------------------------------------------------------------------ one reference
    def cost_volume(self, reference: View, sources: Sequence[View]) -> tuple[Tensor, Tensor]:
        """``[B, D, H, W]`` matching cost of every hypothesis, averaged over the sources that see it
        (:data:`UNSEEN` where none does), and ``[B, D, H, W]`` how many sources see it. ``chunk``
        hypotheses are warped and compared at once (one batch of ``B * chunk`` images)."""
        ref = gray(reference.image)
        batch, _, height, width = ref.shape
        rays, has_ray = RAYS.get(reference.camera, ref.device)
        if self.cost == "census":
            ref_code = census(ref, self.census_window)
        else:
            ref_stats = window_stats(ref, self.window)
        total = ref.new_zeros(batch, self.hypotheses, height, width)
        count = ref.new_zeros(batch, self.hypotheses, height, width)
        inverse = self.inverse_distances(ref.device)
        for source in sources:
            image = gray(source.image)
            T = _batched(source.T_ref_to_view, batch).to(ref)
            for start in range(0, self.hypotheses, self.chunk):
                k = min(self.chunk, self.hypotheses - start)

                def each(x: Tensor, k=k) -> Tensor:  # [B, ...] -> [B * k, ...], hypotheses inner
                    return x.unsqueeze(1).expand(x.shape[0], k, *x.shape[1:]).reshape(-1, *x.shape[1:])

                distance = (
                    (1 / inverse[start : start + k]).reshape(1, k, 1, 1).expand(batch, k, height, width)
                )
                warp = warp_to_source(
                    rays.expand(batch * k, -1, -1, -1),
                    has_ray.expand(batch * k, -1, -1),
                    distance.reshape(batch * k, height, width),
                    each(T),
                    source.camera,
                )
                warped = sample(each(image), warp.grid, padding_mode="zeros")
                if self.cost == "census":
                    grouped = warped.reshape(batch, k, height, width)
                    cost = census_cost(ref_code, grouped, self.census_window).reshape(
                        batch * k, height, width
                    )
                else:
                    cost = zncc_cost(each(ref), warped, self.window, tuple(each(x) for x in ref_stats))
                seen = warp.valid.to(ref.dtype).reshape(batch, k, height, width)
                total[:, start : start + k] += cost.reshape(batch, k, height, width) * seen
                count[:, start : start + k] += seen
        volume = torch.where(count > 0, total / count.clamp(min=1), torch.full_like(total, UNSEEN))
        return volume, count

    def estimate(self, reference: View, sources: Sequence[View]) -> tuple[Tensor, Tensor, Tensor]:
        """The distance before the check ``[B, H, W]`` (0 where no hypothesis is seen), its confidence,
        and which pixels are seen."""
        volume, count = self.cost_volume(reference, sources)
        seen = (count > 0).any(1)
        aggregated = aggregate(volume, self.p1, self.p2, self.paths)
        index, confidence = winner(aggregated)
        inverse = self.inverse_distances(volume.device)
        step = inverse[1] - inverse[0]
        distance = 1 / (inverse[0] + index * step).clamp(min=float(inverse[-1]) * 0.5)
        distance = torch.where(seen, distance, torch.zeros_like(distance))
        return distance, torch.where(seen, confidence, torch.zeros_like(confidence)), seen

    # ------------------------------------------------------------------ with the round trip
    def __call__(self, reference: View, sources: Sequence[View]) -> StereoResult:
        """Distance for the reference, kept where a round trip through some source's own estimate (that
        source as reference, the reference as its source) comes back within ``check_px``."""
        if not sources:
            raise ValueError("sources: sweep stereo needs at least one source view")
        dense, confidence, seen = self.estimate(reference, sources)
        batch = dense.shape[0]
        kept = torch.zeros_like(seen)
        for source in sources:
            back = invert_pose(_batched(source.T_ref_to_view, batch).to(dense))
            partner = View(source.image, source.camera, torch.eye(4, dtype=dense.dtype))
            partner_distance, _, _ = self.estimate(partner, [View(reference.image, reference.camera, back)])
            kept |= round_trip(dense, reference.camera, partner_distance, source.camera, source.T_ref_to_view,
                               self.check_px)  # fmt: skip
        # a winner at either end of the range is no measurement (the cost may fall further beyond it):
        # low texture matched at the farthest hypothesis in both directions passes the round trip
        inverse = self.inverse_distances(dense.device)
        quarter = (inverse[0] - inverse[1]) / 4  # an inner winner is at most half a step from its index
        reciprocal = 1 / dense.clamp(min=1e-12)
        inside = (reciprocal < inverse[0] - quarter) & (reciprocal > inverse[-1] + quarter)
        kept &= seen & (dense > 0) & inside
        distance = torch.where(kept, dense, torch.zeros_like(dense))
        return StereoResult(distance, dense, confidence, kept, seen)


def _batched(T: Tensor, batch: int) -> Tensor:
    T = torch.as_tensor(T)
    return T.expand(batch, 4, 4) if T.dim() == 2 else T


def gray(image: Tensor) -> Tensor:
    """``[B, 1, H, W]`` float luminance of an RGB or one-channel image."""
    image = image.float()
    if image.shape[1] == 3:
        weights = image.new_tensor((0.299, 0.587, 0.114)).reshape(1, 3, 1, 1)
        return (image * weights).sum(1, keepdim=True)
    if image.shape[1] != 1:
        raise ValueError(f"image: {image.shape[1]} channels; expected 1 or 3")
    return image


# ------------------------------------------------------------------ matching costs
def box_mean(x: Tensor, window: int) -> Tensor:
    """Mean over the ``window`` x ``window`` neighbourhood (the image's inside only, at its border): a row
    mean then a column mean, ``2 window`` additions per pixel instead of ``window**2``."""
    r = window // 2
    rows = F.avg_pool2d(x, (1, window), stride=1, padding=(0, r), count_include_pad=False)
    return F.avg_pool2d(rows, (window, 1), stride=1, padding=(r, 0), count_include_pad=False)


def window_stats(a: Tensor, window: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel mean and variance of ``a`` over the window, and the image's largest variance (the scale
    of :func:`zncc_cost`'s regulariser): computed once for a reference compared with many warps."""
    mean = box_mean(a, window)
    var = (box_mean(a * a, window) - mean**2).clamp(min=0)
    return mean, var, var.amax(dim=(-2, -1), keepdim=True).clamp(min=1e-12)


def zncc_cost(
    a: Tensor, b: Tensor, window: int, stats_a: tuple[Tensor, Tensor, Tensor] | None = None, eps: float = 1e-4
) -> Tensor:
    """``(1 - ZNCC) / 2`` in [0, 1] of ``[B, 1, H, W]`` images over ``window`` x ``window``: 0 for
    windows equal up to gain and offset, 1 for inverted ones; flat windows score 0.5 (no evidence).
    ``stats_a``: :func:`window_stats` of ``a``, when already known."""
    mean_a, var_a, scale = window_stats(a, window) if stats_a is None else stats_a
    mean_b = box_mean(b, window)
    var_b = (box_mean(b * b, window) - mean_b**2).clamp(min=0)
    covariance = box_mean(a * b, window) - mean_a * mean_b
    ncc = covariance / torch.sqrt((var_a + eps * scale) * (var_b + eps * scale))
    return ((1 - ncc.clamp(-1, 1)) / 2)[:, 0]


def census(image: Tensor, window: int) -> Tensor:
    """``[B, window**2 - 1, H, W]`` bool: each neighbour brighter than the centre (the census transform)."""
    r = window // 2
    padded = F.pad(image, (r, r, r, r), mode="replicate")
    height, width = image.shape[-2:]
    bits = [
        padded[:, 0, dy : dy + height, dx : dx + width] > image[:, 0]
        for dy in range(window)
        for dx in range(window)
        if (dy, dx) != (r, r)
    ]
    return torch.stack(bits, 1)


def hamming(a: Tensor, b: Tensor) -> Tensor:
    """The fraction of census bits that differ, ``[B, H, W]`` in [0, 1]."""
    return (a != b).float().mean(1)


def census_cost(reference_bits: Tensor, images: Tensor, window: int) -> Tensor:
    """``hamming(reference_bits, census(image))`` for each of ``images [B, K, H, W]`` (``K`` warps compared
    with one reference's :func:`census` ``[B, window**2 - 1, H, W]``), ``[B, K, H, W]`` in [0, 1], without
    building the images' census: one neighbour at a time, the differing bits counted in uint8 (a tenth of
    the memory traffic of stacking the bits and averaging them as floats)."""
    r = window // 2
    height, width = images.shape[-2:]
    padded = F.pad(images, (r, r, r, r), mode="replicate")
    differ = torch.zeros(images.shape, dtype=torch.uint8, device=images.device)
    bit = 0
    for dy in range(window):
        for dx in range(window):
            if (dy, dx) == (r, r):
                continue
            brighter = padded[:, :, dy : dy + height, dx : dx + width] > images
            differ += brighter != reference_bits[:, bit : bit + 1]
            bit += 1
    return differ.float() / bit


# ------------------------------------------------------------------ semi-global aggregation
STRAIGHT = ((0, 1), (0, -1), (1, 0), (-1, 0))  # (dy, dx): along rows and columns, both ways
DIRECTIONS = {4: STRAIGHT, 8: (*STRAIGHT, (1, 1), (-1, -1), (1, -1), (-1, 1))}


def aggregate(volume: Tensor, p1: float, p2: float, paths: int = 4) -> Tensor:
    """The sum over ``paths`` directions of Hirschmueller's path costs ``L_r`` of ``volume [B, D, H, W]``
    (``paths=0``: the volume itself)."""
    if paths == 0:
        return volume
    return sum(path_cost(volume, dy, dx, p1, p2) for dy, dx in DIRECTIONS[paths])


def path_cost(volume: Tensor, dy: int, dx: int, p1: float, p2: float) -> Tensor:
    """``L_r`` along direction ``r = (dy, dx)``: one image line at a time, every line of the other axis and
    every hypothesis at once. A diagonal path walks the rows and takes its predecessor from the row
    before, shifted by one column. The walked axis is moved to the front, so each line is contiguous."""
    if dy == 0:  # horizontal: walk the columns
        return path_cost(volume.transpose(-1, -2), dx, 0, p1, p2).transpose(-1, -2)
    lines = volume.permute(2, 0, 1, 3).contiguous()  # [H, B, D, W]
    out = torch.empty_like(lines)
    rows = range(lines.shape[0]) if dy > 0 else range(lines.shape[0] - 1, -1, -1)
    previous = None
    for y in rows:
        cost = lines[y]  # [B, D, W]
        if previous is None:
            current = cost.clone()
        else:
            if dx:  # the predecessor of column x is column x - dx of the previous row
                previous = torch.roll(previous, shifts=dx, dims=-1)
                edge = slice(0, 1) if dx > 0 else slice(-1, None)
                previous[..., edge] = cost[..., edge]  # a path starts at the border
            best = previous.amin(1, keepdim=True)
            step = torch.minimum(previous, best + p2)  # stay, or jump anywhere
            step[:, :-1] = torch.minimum(step[:, :-1], previous[:, 1:] + p1)  # one hypothesis nearer
            step[:, 1:] = torch.minimum(step[:, 1:], previous[:, :-1] + p1)  # one farther
            current = cost + step - best
        out[y] = current
        previous = current
    return out.permute(1, 2, 0, 3)


def winner(aggregated: Tensor) -> tuple[Tensor, Tensor]:
    """Winner-take-all with a parabola through the winner and its two neighbours: ``[B, H, W]`` fractional
    hypothesis index, and the confidence ``1 - best / second best`` outside the winner's neighbours."""
    depth = aggregated.shape[1]
    best, index = aggregated.min(1)
    lower = aggregated.gather(1, (index - 1).clamp(min=0)[:, None])[:, 0]
    upper = aggregated.gather(1, (index + 1).clamp(max=depth - 1)[:, None])[:, 0]
    curvature = lower - 2 * best + upper
    offset = torch.where(curvature > 1e-12, (lower - upper) / (2 * curvature.clamp(min=1e-12)), 0 * best)
    inner = (index > 0) & (index < depth - 1)
    refined = index.to(aggregated.dtype) + torch.where(inner, offset.clamp(-0.5, 0.5), 0 * best)
    hypotheses = torch.arange(depth, device=aggregated.device).reshape(1, -1, 1, 1)
    near = (hypotheses - index[:, None]).abs() <= 1
    second = aggregated.masked_fill(near, float("inf")).amin(1)
    confidence = (1 - best / second.clamp(min=1e-12)).clamp(0, 1)
    return refined, confidence


# ------------------------------------------------------------------ the round trip
def round_trip(
    distance: Tensor,
    camera: CameraModel,
    partner_distance: Tensor,
    partner: CameraModel,
    T_ref_to_partner: Tensor,
    check_px: float,
) -> Tensor:
    """``[B, H, W]`` bool: the reference pixel's point, at ``distance``, lands in the partner's image; the
    partner's own distance there (nearest pixel), carried back into the reference, lands within
    ``check_px`` pixels of where it started."""
    batch, height, width = distance.shape
    rays, has_ray = RAYS.get(camera, distance.device)
    T = _batched(T_ref_to_partner, batch).to(distance)
    points = transform_points(T, rays * distance[..., None])
    uv, visible = partner.project(points)
    inside = (uv[..., 0] > -0.5) & (uv[..., 0] < partner.width - 0.5)
    inside &= (uv[..., 1] > -0.5) & (uv[..., 1] < partner.height - 0.5)
    grid = pixels_to_grid(
        torch.where((visible & inside)[..., None], uv, torch.zeros_like(uv)), partner.width, partner.height
    )
    theirs = F.grid_sample(partner_distance[:, None], grid, mode="nearest", align_corners=False)[:, 0]
    # the partner's ray at uv: its cached ray grid interpolated (rays vary smoothly), not unprojected again
    partner_grid, partner_valid = RAYS.get(partner, distance.device)
    sampled = F.grid_sample(
        partner_grid.permute(2, 0, 1)[None].expand(batch, -1, -1, -1), grid, mode="bilinear",
        padding_mode="border", align_corners=False,
    ).permute(0, 2, 3, 1)  # fmt: skip
    partner_rays = sampled / sampled.norm(dim=-1, keepdim=True).clamp(min=1e-12)
    partner_has_ray = F.grid_sample(
        partner_valid[None, None].to(distance).expand(batch, -1, -1, -1), grid, mode="nearest",
        align_corners=False,
    )[:, 0] > 0.5  # fmt: skip
    back = transform_points(invert_pose(T), partner_rays * theirs[..., None])
    returned, returns = camera.project(back)
    pixels = torch.stack(
        torch.meshgrid(
            torch.arange(width, device=distance.device),
            torch.arange(height, device=distance.device),
            indexing="xy",
        ),
        -1,
    ).to(distance)
    error = (returned - pixels).norm(dim=-1)
    return has_ray & visible & inside & partner_has_ray & returns & (theirs > 0) & (error <= check_px)
