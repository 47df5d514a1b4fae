"""The training batch: what a sample holds and how samples are collated.

A sample (and, stacked, a batch) is a dict:

| key | shape (per sample) | meaning |
|---|---|---|
| ``image`` | ``[3, H, W]`` float in [0, 1] | target frame t, un-augmented (the photometric loss sees this) |
| ``image_aug`` | ``[3, H, W]`` | optional: the network's input (colour-jittered); defaults to ``image`` |
| ``sources`` | ``[S, 3, H, W]`` | source frames (t-1, t+1, ...), un-augmented |
| ``sources_aug`` | ``[S, 3, H, W]`` | optional: PoseNet's input; defaults to ``sources`` |
| ``poses`` | ``[S, 4, 4]`` float32 | real-scale ``T_target_to_source`` for each source |
| ``cam_to_body`` | ``[4, 4]`` float | optional: camera-to-body extrinsic ``E`` (``E M`` after a flip) |
| ``mask`` | ``[1, H, W]`` float | target body mask, 1 = usable pixel |
| ``source_mask`` | ``[S, 1, H, W]`` | optional: sources' body masks (default: ``mask``, same camera) |
| ``distance`` | ``[1, H, W]`` float | optional ground-truth distance in metres, 0 = unknown |
| ``camera`` | a ``CameraModel`` | the target camera (a list of cameras in a batch) |
| ``source_camera`` | list of ``S`` cameras | optional: sources' cameras (default: ``camera``) |

Cameras are Python values, not tensors: ``collate`` keeps them as lists, so one batch may mix cameras
and camera models.
"""

from __future__ import annotations

from typing import Any

import torch

CAMERA_KEYS = ("camera", "source_camera")


def collate(samples: list[dict[str, Any]]) -> dict[str, Any]:
    """Stack tensors; keep cameras (and any non-tensor value) as lists.

    Samples the dataset could not build (``{"skipped": reason}``, with ``skip_bad_frames``) are left out
    and their reasons listed under ``skipped_frames``, so the training loop can count and report them.
    """
    skipped = [s["skipped"] for s in samples if "skipped" in s]
    samples = [s for s in samples if "skipped" not in s]
    out: dict[str, Any] = {"skipped_frames": skipped} if skipped else {}
    if not samples:
        return out
    keys = samples[0].keys()
    for i, s in enumerate(samples):
        if s.keys() != keys:
            raise ValueError(f"sample {i} has keys {sorted(s)}, sample 0 has {sorted(keys)}")
    for key in keys:
        values = [s[key] for s in samples]
        out[key] = torch.stack(values) if isinstance(values[0], torch.Tensor) else values
    return out
