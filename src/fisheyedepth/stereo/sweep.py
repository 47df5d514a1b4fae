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
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..cameras.base import CameraModel
from ..cameras.rays import RayCache
from ..geometry.se3 import invert_pose, transform_points
from ..geometry.warp import pixels_to_grid, sample, warp_to_source
from ..options.memory import check_memory
from .costs import COSTS, aggregate, census, census_cost, window_stats, winner, zncc_cost
from .fuse import Fused
from .matchers import ImageMaps
from .pairing import MIN_BASELINE, Pairing, pair_pose

if TYPE_CHECKING:
    from ..data.layouts import RigLayout
    from .pipeline import Timer

UNSEEN = 0.5  # the cost of a hypothesis no source sees: neither a match nor a mismatch (costs are in [0, 1])
MEMORY_PER_VOXEL = 20  # bytes: the sweep's cost sums, counts and volume (float32) and a chunk's warps
RAYS = RayCache(max_entries=16)  # each camera's rays, unprojected once (iterative for most fisheye models)


class View(NamedTuple):
    """One image and its camera. ``image``: ``[B, C, H, W]`` (C = 1 or 3, any range: costs are
    normalised per window); ``T_ref_to_view``: ``[B, 4, 4]`` (or ``[4, 4]``) reference camera to this one
    (the identity for the reference itself)."""

    image: Tensor
    camera: CameraModel
    T_ref_to_view: Tensor


class SweepResult(NamedTuple):
    """What :meth:`SweepMatcher.__call__` finds for a reference image."""

    distance: Tensor  # [B, H, W] metres along the ray; 0 where the check rejects, nothing is seen, or the
    # winner is the range's first or last hypothesis
    dense: Tensor  # [B, H, W] the same before the check: every pixel a source sees at some hypothesis
    confidence: Tensor  # [B, H, W] in [0, 1]: 1 - best / second-best aggregated cost (0 where unseen)
    valid: Tensor  # [B, H, W] bool: kept by the round trip (distance > 0)
    seen: Tensor  # [B, H, W] bool: some source sees the pixel at some hypothesis (dense > 0)


@dataclass(frozen=True)
class SweepSettings:
    """The sweep's parameters (:class:`SweepMatcher`). ``hypotheses`` distances uniform in inverse
    distance over ``[min_distance, max_distance]`` metres; ``cost``: ``zncc`` (``window`` x ``window``)
    or ``census`` (``census_window``); ``p1``, ``p2``: the aggregation's penalties for a step of one
    hypothesis and for a jump, in cost units; ``paths``: 0 (none), 4 or 8; ``check_px``: the round
    trip's tolerance; ``chunk``: hypotheses warped at once (memory against speed; the result does not
    depend on it)."""

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


@dataclass(frozen=True)
class SweepMatcher:
    """Sweep stereo (module docstring) with its :class:`SweepSettings`: one reference image against its
    sources (:meth:`__call__`), and the :class:`~.matchers.Matcher` interface the multi-view command and
    the real-world scores call (:meth:`maps`, :meth:`recording`, :meth:`memory`)."""

    settings: SweepSettings = field(default_factory=SweepSettings)
    name: ClassVar[str] = "sweep"
    min_baseline: ClassVar[float] = MIN_BASELINE

    def __post_init__(self) -> None:
        if not isinstance(self.settings, SweepSettings):
            raise ValueError(f"settings: {type(self.settings).__name__}; a SweepSettings expected")

    # ------------------------------------------------------------------ one reference
    def cost_volume(self, reference: View, sources: Sequence[View]) -> tuple[Tensor, Tensor]:
        """``[B, D, H, W]`` matching cost of every hypothesis, averaged over the sources that see it
        (:data:`UNSEEN` where none does), and ``[B, D, H, W]`` how many sources see it. ``chunk``
        hypotheses are warped and compared at once (one batch of ``B * chunk`` images)."""
        ref = gray(reference.image)
        batch, _, height, width = ref.shape
        rays, has_ray = RAYS.get(reference.camera, ref.device)
        if self.settings.cost == "census":
            ref_code = census(ref, self.settings.census_window)
        else:
            ref_stats = window_stats(ref, self.settings.window)
        total = ref.new_zeros(batch, self.settings.hypotheses, height, width)
        count = ref.new_zeros(batch, self.settings.hypotheses, height, width)
        inverse = self.settings.inverse_distances(ref.device)
        for source in sources:
            image = gray(source.image)
            T = _batched(source.T_ref_to_view, batch).to(ref)
            for start in range(0, self.settings.hypotheses, self.settings.chunk):
                k = min(self.settings.chunk, self.settings.hypotheses - start)

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
                if self.settings.cost == "census":
                    grouped = warped.reshape(batch, k, height, width)
                    cost = census_cost(ref_code, grouped, self.settings.census_window).reshape(
                        batch * k, height, width
                    )
                else:
                    stats = tuple(each(x) for x in ref_stats)
                    cost = zncc_cost(each(ref), warped, self.settings.window, stats)
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
        aggregated = aggregate(volume, self.settings.p1, self.settings.p2, self.settings.paths)
        index, confidence = winner(aggregated)
        inverse = self.settings.inverse_distances(volume.device)
        step = inverse[1] - inverse[0]
        distance = 1 / (inverse[0] + index * step).clamp(min=float(inverse[-1]) * 0.5)
        distance = torch.where(seen, distance, torch.zeros_like(distance))
        return distance, torch.where(seen, confidence, torch.zeros_like(confidence)), seen

    # ------------------------------------------------------------------ with the round trip
    def __call__(self, reference: View, sources: Sequence[View]) -> SweepResult:
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
                               self.settings.check_px)  # fmt: skip
        # a winner at either end of the range is no measurement (the cost may fall further beyond it):
        # low texture matched at the farthest hypothesis in both directions passes the round trip
        inverse = self.settings.inverse_distances(dense.device)
        quarter = (inverse[0] - inverse[1]) / 4  # an inner winner is at most half a step from its index
        reciprocal = 1 / dense.clamp(min=1e-12)
        inside = (reciprocal < inverse[0] - quarter) & (reciprocal > inverse[-1] + quarter)
        kept &= seen & (dense > 0) & inside
        distance = torch.where(kept, dense, torch.zeros_like(dense))
        return SweepResult(distance, dense, confidence, kept, seen)

    # ------------------------------------------------------------------ as a Matcher
    def maps(
        self, image, partner_image, camera, partner_camera, T_ref_to_partner
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`__call__` with one source: the reference's checked and filled distance."""
        T = torch.as_tensor(T_ref_to_partner).float()
        reference, partner = View(as_batch(image), camera, torch.eye(4)), as_batch(partner_image)
        found = self(reference, [View(partner, partner_camera, T)])
        return found.distance[0].cpu().numpy(), found.dense[0].cpu().numpy()

    def recording(self, layout: RigLayout, pairings: list[Pairing], timer: Timer) -> SweepRecording:
        return SweepRecording(layout, self)

    def memory(self, camera: CameraModel) -> float:
        return MEMORY_PER_VOXEL * self.settings.hypotheses * camera.width * camera.height

    def check_memory(self, name: str, camera: CameraModel, where: str) -> None:
        size = f"{camera.width}x{camera.height}"
        what = f"{MEMORY_PER_VOXEL} bytes x hypotheses x camera {name!r}'s {size} pixels"
        check_memory("--hypotheses", self.settings.hypotheses, self.memory(camera), what)

    def record(self) -> dict[str, Any]:
        return {"matcher": self.name, **asdict(self.settings)}


class SweepRecording:
    """:class:`SweepMatcher`'s run over a recording (:class:`~.matchers.RecordingMatches`): each image the
    reference, all its partners the sources at once (on the GPU where there is one)."""

    def __init__(self, layout: RigLayout, sweep: SweepMatcher):
        self.layout, self.sweep = layout, sweep
        self.device = "cuda" if torch.cuda.is_available() else "cpu"

    def _tensor(self, bgr: np.ndarray) -> Tensor:
        return as_batch(bgr[..., ::-1]).to(self.device) / 255

    def image(self, pairing: Pairing, image: np.ndarray) -> ImageMaps:
        layout, device = self.layout, self.device
        own = layout.cameras[pairing.camera].camera
        reference = View(self._tensor(image), own, torch.eye(4, device=device))
        sources = []
        for partner in pairing.partners:
            T = pair_pose(layout, pairing.camera, pairing.frame, partner.camera, partner.frame)
            partner_image = layout.read_image(pairing.sequence, partner.camera, partner.frame)
            sources.append(View(self._tensor(partner_image), layout.cameras[partner.camera].camera,
                                torch.from_numpy(T).float().to(device)))  # fmt: skip
        result = self.sweep(reference, sources)
        distance, dense, confidence = (
            x[0].cpu().numpy() for x in (result.distance, result.dense, result.confidence)
        )
        fused = Fused(distance, dense, np.where(distance > 0, confidence, 0).astype(np.float32),
                      (distance > 0).astype(np.uint8))  # fmt: skip
        return ImageMaps(fused, list(pairing.partners), {})

    def record(self) -> dict[str, Any]:
        return {"static": {}, "pairs": {}, "pairs_left_out": {}}


def as_batch(image: np.ndarray | Tensor) -> Tensor:
    """An ``H x W (x C)`` array or a ``[C, H, W]`` / ``[1, C, H, W]`` tensor as ``[1, C, H, W]`` float."""
    if isinstance(image, Tensor):
        return (image if image.dim() == 4 else image[None]).float()
    array = np.asarray(image, dtype=np.float32)
    array = array[..., None] if array.ndim == 2 else array
    return torch.from_numpy(np.ascontiguousarray(array)).permute(2, 0, 1)[None]


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
