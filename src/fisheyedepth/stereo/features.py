"""Feature matches between two calibrated images, as unit bearings: SIFT keypoints found once an image
(:func:`features`) and matched with Lowe's ratio test, kept where mutual (:func:`match_described`); what
the pose refinement (:mod:`.refine`) and the motion check (:mod:`.motion`) start from."""

from __future__ import annotations

from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from ..cameras.base import CameraModel


class Matches(NamedTuple):
    rays_a: Tensor  # [N, 3] float64 unit bearings in camera a
    rays_b: Tensor  # [N, 3] float64 unit bearings in camera b
    uv_a: np.ndarray  # [N, 2] pixels
    uv_b: np.ndarray

    @staticmethod
    def pooled(found: list[Matches]) -> Matches:
        """The matches of several image pairs of the same two cameras, as one set (empty for none)."""
        empty = Matches(torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.float64),
                        np.zeros((0, 2)), np.zeros((0, 2)))  # fmt: skip
        return Matches(
            torch.cat([m.rays_a for m in (empty, *found)]),
            torch.cat([m.rays_b for m in (empty, *found)]),
            np.concatenate([m.uv_a for m in (empty, *found)]),
            np.concatenate([m.uv_b for m in (empty, *found)]),
        )


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """An ``[H, W]``, ``[1|3, H, W]`` or ``[1, 1|3, H, W]`` image in [0, 1] (or 0-255) as 8-bit grey."""
    array = (
        image.detach().cpu().float().numpy() if isinstance(image, Tensor) else np.asarray(image, np.float32)
    )
    array = array.squeeze()
    if array.ndim == 3:
        array = array.mean(0) if array.shape[0] == 3 else array.mean(-1)
    scale = 255.0 if array.max() <= 1.0 else 1.0
    return np.clip(array * scale, 0, 255).astype(np.uint8)


class Features(NamedTuple):
    """An image's SIFT keypoints (``[N, 2]`` pixels) and descriptors (``[N, 128]`` float32)."""

    uv: np.ndarray
    descriptors: np.ndarray | None


def features(image, count: int = 4000) -> Features:
    """The image's SIFT :class:`Features` (at most ``count``), computed once per image and reusable for
    every pair it is in (:func:`match_described`)."""
    keys, descriptors = cv2.SIFT_create(nfeatures=count).detectAndCompute(to_uint8(image), None)
    return Features(np.array([k.pt for k in keys], np.float64).reshape(-1, 2), descriptors)


def match_described(
    found_a: Features, camera_a: CameraModel, found_b: Features, camera_b: CameraModel, ratio: float = 0.8
) -> Matches:
    """The two images' features matched (Lowe's ratio test, kept only when mutual), as unit bearings of
    pixels that have a ray."""
    empty = Matches.pooled([])
    desc_a, desc_b = found_a.descriptors, found_b.descriptors
    if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
        return empty
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = matcher.knnMatch(desc_a, desc_b, k=2)
    backward = {m.queryIdx: m.trainIdx for m, *_ in matcher.knnMatch(desc_b, desc_a, k=1) if m}
    pairs = [
        (m.queryIdx, m.trainIdx)
        for m, n in (p for p in forward if len(p) == 2)
        if m.distance < ratio * n.distance and backward.get(m.trainIdx) == m.queryIdx
    ]
    if not pairs:
        return empty
    uv_a = found_a.uv[[i for i, _ in pairs]]
    uv_b = found_b.uv[[j for _, j in pairs]]
    rays_a, ok_a = camera_a.unproject(torch.from_numpy(uv_a))
    rays_b, ok_b = camera_b.unproject(torch.from_numpy(uv_b))
    ok = (ok_a & ok_b).numpy()
    return Matches(rays_a[ok], rays_b[ok], uv_a[ok], uv_b[ok])


def match_features(
    image_a, camera_a: CameraModel, image_b, camera_b: CameraModel, ratio: float = 0.8, count: int = 4000
) -> Matches:
    """SIFT matches between the two images (:func:`features`, :func:`match_described`)."""
    return match_described(features(image_a, count), camera_a, features(image_b, count), camera_b, ratio)
