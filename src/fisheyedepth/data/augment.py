"""Training augmentation: colour jitter for the network input only, and a geometrically consistent flip."""

from __future__ import annotations

import dataclasses
import hashlib
import math
from typing import Any

import torch
from torch import Tensor

from ..geometry import axis_angle_to_matrix, mirror_pose_x


@dataclasses.dataclass
class Augment:
    """Training augmentation: flip probability and colour-jitter ranges (Monodepth2's defaults)."""

    flip: float = 0.5
    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.1

    def __call__(self, sample: dict[str, Any]) -> dict[str, Any]:
        """A training sample, flipped with probability ``flip`` (images, masks, ground truth, camera and
        poses together, :func:`flip_sample`), with ``image_aug``/``sources_aug`` colour-jittered alike
        for the networks' input; the un-jittered frames stay for the photometric loss."""
        if torch.rand(()).item() < self.flip:
            sample = flip_sample(sample)
        frames = torch.cat((sample["image"][None], sample["sources"]))
        jittered = colour_jitter(frames, self.brightness, self.contrast, self.saturation, self.hue)
        return {**sample, "image_aug": jittered[0], "sources_aug": jittered[1:]}


_GREY = torch.tensor([0.299, 0.587, 0.114], dtype=torch.float64)
_YIQ = torch.tensor(
    [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64
)


def colour_jitter(
    images: Tensor,
    brightness: float,
    contrast: float,
    saturation: float,
    hue: float,
    generator: torch.Generator | None = None,
) -> Tensor:
    """One random jitter applied alike to every image of ``[..., 3, H, W]`` (Monodepth2's ranges:
    0.2, 0.2, 0.2, 0.1), clamped to [0, 1] once at the end:

    - brightness ``x -> b x``;
    - contrast about each image's mean grey ``m``: ``x -> m + c (x - m)``;
    - saturation about each pixel's grey ``g = w . x``: ``x -> g + s (x - g)``, i.e.
      ``S = s I + (1 - s) 1 w^T``;
    - hue: a rotation by up to ``hue`` turns of the chroma plane of YIQ, ``H = YIQ^-1 R YIQ``.

    The chain is affine, so it is applied as one map, ``x -> A x + t`` with ``A = c b H S`` and
    ``t = (1 - c) b m 1`` (``S 1 = H 1 = 1``): one pass over the pixels instead of eight."""

    def draw(spread: float) -> float:
        return 1.0 + (2 * torch.rand((), generator=generator).item() - 1) * spread

    b, c, s = draw(brightness), draw(contrast), draw(saturation)
    A = s * torch.eye(3, dtype=torch.float64) + (1 - s) * torch.ones(3, 1, dtype=torch.float64) * _GREY
    if hue:
        angle = (2 * torch.rand((), generator=generator).item() - 1) * hue * 2 * math.pi
        cos, sin = math.cos(angle), math.sin(angle)
        rot = torch.tensor([[1.0, 0, 0], [0, cos, -sin], [0, sin, cos]], dtype=torch.float64)
        A = torch.linalg.inv(_YIQ) @ rot @ _YIQ @ A
    A = (c * b * A).to(images)
    pixels = images.shape[-1] * images.shape[-2]
    grey_mean = torch.einsum("j,...jhw->...", _GREY.to(images), images) / pixels
    shift = ((1 - c) * b) * grey_mean
    out = torch.einsum("ij,...jhw->...ihw", A, images) + shift[..., None, None, None]
    return out.clamp_(0, 1)


def flip_sample(sample: dict[str, Any]) -> dict[str, Any]:
    """Mirror a sample left-right: images, masks and ground truth flip, the camera model flips
    (``u0 -> W - 1 - u0``, and what the model needs), relative poses mirror (``M T M``) and the
    camera-to-body extrinsic becomes ``E M``, so ``(E M)^-1 T_body (E M)`` is the mirrored pose."""
    out = dict(sample)
    for key in ("image", "image_aug", "sources", "sources_aug", "mask", "source_mask", "distance", "moving"):
        if key in out:
            out[key] = out[key].flip(-1)
    out["camera"] = sample["camera"].flip()
    if "source_camera" in out:
        out["source_camera"] = [c.flip() for c in sample["source_camera"]]
    out["poses"] = mirror_pose_x(sample["poses"])
    if "cam_to_body" in out:  # the mirrored camera: X_body = E X = (E M)(M X), so E' = E M
        out["cam_to_body"] = sample["cam_to_body"] * _MIRROR_COLUMNS.to(sample["cam_to_body"])
    return out


_MIRROR_COLUMNS = torch.tensor([-1.0, 1.0, 1.0, 1.0])  # right-multiplying by diag(-1, 1, 1, 1)


@dataclasses.dataclass(frozen=True)
class PoseNoise:
    """Seeded odometry error applied to the relative poses at load time (any layout, every split):
    a rotation by an angle drawn from N(0, ``rotation_deg``) about a random axis, and a translation error
    of N(0, ``translation``) times the translation's length along each axis. The noise of a given
    (sequence, camera, frame, neighbour) is the same every epoch, like a real odometry's error."""

    rotation_deg: float = 0.0
    translation: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.rotation_deg < 0 or self.translation < 0:
            raise ValueError(f"pose noise must be non-negative, got {self}")

    @property
    def active(self) -> bool:
        return self.rotation_deg > 0 or self.translation > 0

    def __call__(self, T: Tensor, key: str) -> Tensor:
        """``T`` ``[4, 4]`` (float64) with this noise; ``key`` names the pose (stable across epochs)."""
        if not self.active:
            return T
        digest = hashlib.blake2b(f"{self.seed}|{key}".encode(), digest_size=8).digest()
        gen = torch.Generator().manual_seed(int.from_bytes(digest, "little") >> 1)
        axis = torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
        angle = math.radians(self.rotation_deg) * torch.randn((), generator=gen, dtype=torch.float64)
        noisy = T.clone()
        noisy[:3, :3] = axis_angle_to_matrix(axis * angle) @ T[:3, :3]
        error = torch.randn(3, generator=gen, dtype=torch.float64) * self.translation * T[:3, 3].norm()
        noisy[:3, 3] = T[:3, 3] + error
        return noisy
