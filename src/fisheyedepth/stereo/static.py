"""Pixels that do not move with the scene, found from a camera's own images: a constant border, a burnt-in
overlay, the robot's own body. Matched against another instant they sit still and match at no parallax
(a hand-held camera's white border was read as a "too far" band at an abs_rel of 1.3-10); matched
against another camera they match whatever lies on the same row. So they are never matched.

Between two images of the camera, a pixel is judged only where the scene there must move: where a point
at the farthest distance searched (nearly the rotation alone) moves by :data:`MIN_SHIFT` pixels or more,
so that nothing far and nothing at the focus of expansion is ever taken for static. A judged pixel is
static in the pair where it keeps its value (within :data:`CLOSE` of the image's range, over a 3x3
average) although moving with the scene would have changed it by four times that (the second image's
value where its far point lands, or the first image's value where what lands on it comes from): a flat
wall keeps its value too, but so would it moving, and it is not taken. A judged pixel whose value
changes moved. A pixel is static once :data:`MIN_PAIRS` pairs found it static and none saw it move;
lone pixels (no 3x3 block of static pixels) are dropped (a border, an overlay and a body are areas), and
the rest widened by a matching window (:data:`WINDOW`), so that no window reaches into them.
"""

from __future__ import annotations

import cv2
import numpy as np
import torch

from ..cameras.base import CameraModel
from .rectify import RAYS

MIN_SHIFT = 3.0  # pixels the scene must move under a pixel for the pair to judge it
CLOSE = 0.02  # of the image's range: a value kept (a real camera's noise, averaged over 3x3, is under it)
MIN_PAIRS = 2  # pairs that must find a pixel static (and none moving) before it is left out
WINDOW = 7  # pixels: how far the static pixels are widened (the matcher's window and a margin)


def far_flow(camera: CameraModel, T_a_to_b: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of ``camera`` in pose a lands in pose b (``T_a_to_b``: a's frame to b's) for a
    point ``distance`` metres along its ray (``[H, W, 2]`` float32 pixels), and by how many pixels it
    moves (``[H, W]``; ``inf`` where it leaves the image or has no projection, 0 where it has no ray)."""
    rays, has_ray = RAYS.get(camera)
    T = torch.as_tensor(np.asarray(T_a_to_b), dtype=rays.dtype)
    points = rays * distance @ T[:3, :3].T + T[:3, 3]
    uv, ok = camera.project(points)
    h, w = has_ray.shape
    grid = torch.stack(torch.meshgrid(torch.arange(w, dtype=uv.dtype), torch.arange(h, dtype=uv.dtype),
                                      indexing="xy"), -1)  # fmt: skip
    shift = (uv - grid).norm(dim=-1)
    inside = ok & (uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
    shift = torch.where(inside, shift, torch.full_like(shift, float("inf")))
    shift = torch.where(has_ray, shift, torch.zeros_like(shift))
    return uv.float().numpy(), shift.numpy()


class StaticFinder:
    """The static pixels of one camera (module docstring), from pairs of its images as they come:
    :meth:`add` each pair (two images and the pose between them), :attr:`mask` the pixels found."""

    def __init__(self, camera: CameraModel, max_distance: float = 80.0):
        self.camera, self.max_distance = camera, float(max_distance)
        shape = (camera.height, camera.width)
        self.static = np.zeros(shape, np.int32)  # pairs that found the pixel static
        self.moved = np.zeros(shape, bool)  # some pair saw it move
        self.pairs = 0  # pairs that judged some pixel

    def add(self, image_a: np.ndarray, image_b: np.ndarray, T_a_to_b: np.ndarray) -> None:
        """Two images of the camera (``H x W`` or ``H x W x 3``) and ``T_a_to_b`` from the first's pose to
        the second's."""
        a, b = (np.asarray(x, np.float32) for x in (image_a, image_b))
        a, b = (cv2.blur(x.mean(2) if x.ndim == 3 else x, (3, 3)) for x in (a, b))
        uv, shift = far_flow(self.camera, T_a_to_b, self.max_distance)
        seen = RAYS.get(self.camera).valid.numpy()
        judged = seen & (shift >= MIN_SHIFT)
        if not judged.any():
            return
        values = a[seen]
        tol = CLOSE * max(float(np.percentile(values, 99) - np.percentile(values, 1)), 1e-6)
        h, w = a.shape
        here = np.stack(np.meshgrid(np.arange(w), np.arange(h), indexing="xy"), -1).astype(np.float32)
        back = 2 * here - uv  # where, to first order, what moves onto the pixel comes from
        constant = {"interpolation": cv2.INTER_LINEAR, "borderMode": cv2.BORDER_REPLICATE}
        went = cv2.remap(b, np.ascontiguousarray(uv[..., 0]), np.ascontiguousarray(uv[..., 1]), **constant)
        came = cv2.remap(
            a, np.ascontiguousarray(back[..., 0]), np.ascontiguousarray(back[..., 1]), **constant
        )
        kept = np.abs(b - a) <= tol
        distinct = (np.abs(went - a) > 4 * tol) | (np.abs(came - b) > 4 * tol)
        self.static += judged & kept & distinct
        self.moved |= judged & ~kept
        self.pairs += 1

    @property
    def mask(self) -> np.ndarray:
        """``[H, W]`` bool: the pixels found static, widened by :data:`WINDOW`."""
        found = ((self.static >= MIN_PAIRS) & ~self.moved).astype(np.uint8)
        found = cv2.morphologyEx(found, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))  # no lone pixels
        return cv2.dilate(found, np.ones((WINDOW, WINDOW), np.uint8)) > 0


def usable(mask: np.ndarray | None, static: np.ndarray) -> np.ndarray | None:
    """A camera's pixels to match: its ``mask``'s (nonzero: the scene; None: every pixel) less its
    ``static`` ones; None where that is every pixel."""
    if not static.any():
        return mask
    return ~static if mask is None else (np.asarray(mask) > 0) & ~static
