"""Scores on the real frames with metric ground truth (:mod:`fisheyedepth.realworld.frames`).

A projected LiDAR scan is scored under the ``full`` protocol (every point up to 80 m that the camera can
see, the occlusion filter on), then the ``kitti360`` protocol (under 8 m); a dense map on every pixel
with depth, capped at the frame's range. Each frame is scored unscaled and median-scaled over its
ground-truth pixels inside the camera's valid domain, beside a constant map at the ground truth's median
distance (:func:`constant_map`): the score that knows nothing of the image, which any real-world score
must beat. A runtime runs at its own input size on the image and camera resized alike, its distance
upsampled to the frame's size (:mod:`fisheyedepth.runtimes`).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from ..evaluation import PROTOCOLS, Evaluator, Protocol
from ..metrics import DepthMetrics
from .frames import RAYS, RealFrame


def protocols(frame: RealFrame) -> tuple[Protocol, ...]:
    """The protocols that score ``frame``, the first the one a table shows."""
    if frame.source == "lidar":
        return (PROTOCOLS["full"], PROTOCOLS["kitti360"])
    return (Protocol(frame.name, "distance", None, None, cap=(1e-3, frame.cap)),)


def scored_pixels(frame: RealFrame) -> Tensor:
    """``[H, W]`` bool: the pixels the frame's first protocol scores."""
    evaluator = Evaluator(protocols(frame)[0], rays=RAYS)
    return evaluator.scored(frame.distance, frame.mask, frame.camera, frame.source)


def median_distance(frame: RealFrame, scored: Tensor) -> float:
    """The median of the ground truth on the ``scored`` pixels (:func:`scored_pixels`; the mean of the
    middle two for an even count)."""
    return float(torch.quantile(frame.distance[scored].double(), 0.5))


def constant_map(frame: RealFrame, scored: Tensor | None = None) -> dict[str, Any]:
    """The baseline: every pixel at the ground truth's median distance, scored like a prediction on the
    pixels the frame scores (its median scaling would change nothing); ``{"distance": m, "pixels": n,
    "none": metrics}``. ``scored``: :func:`scored_pixels`, when known already."""
    scored = scored_pixels(frame) if scored is None else scored
    value = median_distance(frame, scored)
    metrics = DepthMetrics(protocols(frame)[0].cap)
    metrics.update(torch.full_like(frame.distance, value)[None], frame.distance[None], scored[None])
    summary = {k: float(v) for k, v in metrics.compute().items()}
    return {"distance": value, "pixels": int(scored.sum()), "none": summary | {"images": 1}}


def predict(runtime, frame: RealFrame) -> Tensor:
    """``runtime`` (anything with ``distance(images, cameras)``) on the frame: distance ``[H, W]``."""
    return runtime.distance(frame.image, [frame.camera]).float()[0, 0]


def score(runtime, frame: RealFrame) -> tuple[dict[str, Any], Tensor]:
    """The frame scored under each of its protocols, unscaled and median-scaled
    (``{protocol: Evaluator.compute()}``), and the predicted distance ``[H, W]``."""
    pred = predict(runtime, frame)
    results = {}
    for protocol in protocols(frame):
        evaluator = Evaluator(protocol, ("none", "median"), rays=RAYS)
        evaluator.update(
            pred,
            frame.distance.to(pred),
            frame.mask.to(pred.device),
            frame.camera,
            source=frame.source,
            frame=frame.name,
        )
        results[protocol.name] = evaluator.compute(frame.name)
    return results, pred
