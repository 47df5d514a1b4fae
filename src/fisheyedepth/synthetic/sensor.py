"""What a real camera does to the light before it becomes an 8-bit image, each effect a switch.

- ``exposure``: auto-exposure: a gain that pulls the frame's mean brightness towards mid-grey, with a
  slow drift of its own, different for every camera; it changes from frame to frame, so the same
  surface is brighter in one frame than in the next (what breaks brightness constancy on real drives);
- ``white_balance``: per-camera red and blue gains that drift slowly over time;
- ``vignetting``: brightness falling towards the image circle's rim, fixed per camera;
- ``noise``: photon (Poisson-like) and read noise, new in every frame;
- ``motion_blur``: the shutter stays open for :data:`SHUTTER` of a frame interval, centred on the
  frame's instant: the colour is the mean of :data:`BLUR_SAMPLES` renders along the motion of the car
  and the traffic (the ground truth stays that of the frame's instant).

Every draw comes from ``numpy.random.default_rng`` seeded with the world's seed, the camera's index and
(for noise) the frame: the same seed renders the same images.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

EFFECTS = ("exposure", "white_balance", "vignetting", "noise", "motion_blur")
SHUTTER = 0.3  # the open shutter, as a fraction of the frame interval
BLUR_SAMPLES = 5
MID_GREY = 0.42  # the brightness auto-exposure aims at
READ_NOISE, SHOT_NOISE = 0.004, 0.0008  # sigma^2 = READ^2 + SHOT * signal (signal in [0, 1])


def check_effects(effects) -> tuple[str, ...]:
    """``effects`` as a sorted tuple of names of :data:`EFFECTS`; an unknown name (or anything but a
    name: an effect is a switch, it has no level) is an error."""
    effects = [effects] if isinstance(effects, str) else list(effects or ())
    unknown = [e for e in effects if not (isinstance(e, str) and e in EFFECTS)]
    if unknown:
        raise ValueError(f"effects: unknown {unknown}; choose among {', '.join(EFFECTS)}")
    return tuple(sorted(set(effects)))


def blur_times(frame: int) -> np.ndarray:
    """The instants (in trajectory frames) whose renders a motion-blurred ``frame`` averages."""
    return frame + SHUTTER * (np.arange(BLUR_SAMPLES) / (BLUR_SAMPLES - 1) - 0.5)


def _drift(rng: np.random.Generator, n: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A smooth zero-mean process of unit scale: ``n`` sinusoids with random periods and phases."""
    periods = rng.uniform(15.0, 120.0, n)
    phases = rng.uniform(0.0, 2 * math.pi, n)
    weights = rng.uniform(0.5, 1.0, n)
    return periods, phases, weights / np.sqrt((weights**2).sum() / 2)


def _at(process, frame: float) -> float:
    periods, phases, weights = process
    return float((weights * np.sin(2 * math.pi * frame / periods + phases)).sum())


class Sensor:
    """The effects of one camera (``index`` in its rig) of the world ``seed``."""

    def __init__(self, effects, seed: int, index: int, valid: np.ndarray):
        self.effects = check_effects(effects)
        self.seed, self.index = seed, index
        rng = np.random.default_rng([seed, index, 46])
        self.exposure_drift, self.red, self.blue = _drift(rng), _drift(rng), _drift(rng)
        self.valid = torch.as_tensor(valid, dtype=torch.bool)  # [H, W] pixels with a ray
        H, W = valid.shape
        strength = rng.uniform(0.25, 0.45)
        ys, xs = np.nonzero(valid)
        cy, cx = (H - 1) / 2, (W - 1) / 2
        r = np.hypot(np.arange(W)[None, :] - cx, np.arange(H)[:, None] - cy)
        rim = max(float(np.hypot(xs - cx, ys - cy).max()) if len(xs) else 1.0, 1.0)
        u = np.clip(r / rim, 0.0, 1.0)
        self.vignette = torch.as_tensor(1.0 - strength * u**2 - 0.5 * strength * u**4, dtype=torch.float32)

    def gains(self, colour: Tensor, frame: int) -> Tensor:
        """``[3]`` the per-channel gain of ``frame`` (exposure and white balance) for ``colour``."""
        gain = torch.ones(3)
        if "exposure" in self.effects:
            valid = colour[self.valid]
            mean = float(valid.mean()) if valid.numel() else MID_GREY
            auto = (MID_GREY / max(mean, 1e-3)) ** 0.7
            gain = gain * float(np.clip(auto * math.exp(0.2 * _at(self.exposure_drift, frame)), 0.4, 2.5))
        if "white_balance" in self.effects:
            red = math.exp(0.06 * _at(self.red, frame))
            blue = math.exp(0.06 * _at(self.blue, frame))
            gain = gain * torch.tensor([red, 1.0, blue])
        return gain

    def __call__(self, colour: Tensor, frame: int) -> Tensor:
        """``[H, W, 3]`` colour of ``frame`` as the camera records it (before quantisation)."""
        out = colour
        if "vignetting" in self.effects:
            out = out * self.vignette[..., None]
        out = out * self.gains(out, frame)
        if "noise" in self.effects:
            rng = np.random.default_rng([self.seed, self.index, frame, 47])
            sigma = torch.sqrt(READ_NOISE**2 + SHOT_NOISE * out.clamp(0, 1))
            out = out + sigma * torch.from_numpy(rng.standard_normal(out.shape).astype(np.float32))
        return torch.where(self.valid[..., None], out, torch.zeros_like(out))
