"""Checkpoint hyper-parameters of older layouts read as today's options.

What a checkpoint stores is what the module took when it was trained. Older checkpoints differ in four
ways, each converted here and nowhere else: options that no longer exist (dropped), options renamed
(renamed), options stored flat before they came in groups (``net``, ``objective``, ``optimizer``,
``scheduler``: moved into them), and options added since (set to the value those checkpoints were
trained with, so that they load and run as they were trained). :func:`current_hparams` does all four.
"""

from __future__ import annotations

from typing import Any

# Options that no longer exist; a checkpoint that stores them loads without them: gradient clipping
# (now the trainer's gradient_clip_val alone), and the training-only distance search, hint search and
# plane-sweep hints (losses measured and removed: none changed held-out accuracy)
RETIRED_HPARAMS = (
    *("grad_clip", "bin_search", "bin_search_scale"),
    *("hints", "hint_candidates", "hint_spread", "hint_margin", "hint_weight"),
)
# Two options that became one: the evaluation cap (min, max), as the protocols and DepthMetrics name it
RENAMED_HPARAMS = {("eval_min", "eval_max"): "eval_cap"}


# Checkpoints written before the options came in groups store them flat: each flat key and where it
# lives now (``lr_schedule`` picks the scheduler: "step" StepLR, "cosine" CosineAnnealingLR)
NET_KEYS = ("resnet", "weights", "multi_channel", "n_bins", "attention", "min_distance", "max_distance")
NET_KEYS += ("base_focal", "scales", "channels_last", "upsample", "decoder_width")
OBJECTIVE_KEYS = ("fisheye_projection", "pinhole_focal", "real_scale", "pose_translation_scale")
OBJECTIVE_KEYS += ("source_offsets", "rig_offsets", "automask", "rim_margin", "smoothness", "loss_resolution")
FLAT_KEYS = {
    **{k: f"net.{k}" for k in NET_KEYS},
    **{k: f"objective.{k}" for k in OBJECTIVE_KEYS},
    **{"lr": "optimizer.lr", "weight_decay": "optimizer.weight_decay"},
    **{"lr_step": "scheduler.step_size", "lr_gamma": "scheduler.gamma"},
}
# Options added after checkpoints had been written, each with the value that those checkpoints were trained
# with: a checkpoint without one loads as it was trained (net.encoder: every encoder was a ResNet)
# (objective.truth_weight and photometric_weight: every checkpoint before them was self-supervised)
ADDED_HPARAMS = {"net.encoder": "resnet", "objective.brightness": "none", "objective.outliers": 0.0}
ADDED_HPARAMS |= {"objective.truth_weight": 0.0, "objective.photometric_weight": 1.0}
# (net.cost_volume 0: every checkpoint before the multi-view network was monocular; its other options
# do nothing without a cost volume)
ADDED_HPARAMS |= {"net.cost_volume": 0, "net.cost_volume_max": 80.0, "net.cost_volume_stride": 4}
ADDED_HPARAMS |= {"net.cost_volume_min": 0.5, "net.source_dropout": 0.2}
# (the first multi-view checkpoints passed the fused map on in place of the encoder's)
ADDED_HPARAMS |= {"net.cost_volume_fusion": "replace"}
ADAM = {"_target_": "torch.optim.Adam", "_partial_": True}
STEP_LR = {"_target_": "torch.optim.lr_scheduler.StepLR", "_partial_": True}
COSINE_LR = {"_target_": "torch.optim.lr_scheduler.CosineAnnealingLR", "_partial_": True}


def nested_hparams(hparams: dict[str, Any]) -> dict[str, Any]:
    """Hyper-parameters in groups (``net``, ``objective``, ``optimizer``, ``scheduler``): flat ones (a
    checkpoint written before the groups) moved by :data:`FLAT_KEYS`, grouped ones as they are; the
    options of :data:`ADDED_HPARAMS` a checkpoint predates set to the value it was trained with. The
    flat cosine schedule annealed to ``lr * lr_gamma`` over the run's epochs, which the checkpoint does
    not record: its scheduler keeps ``eta_min`` alone (evaluation builds none)."""
    out = dict(hparams) if "net" in hparams else _grouped(hparams)
    for name, value in ADDED_HPARAMS.items():
        group, key = name.split(".")
        if key not in (out.get(group) or {}):
            out[group] = {**(out.get(group) or {}), key: value}
    return out


def _grouped(hparams: dict[str, Any]) -> dict[str, Any]:
    """Flat hyper-parameters in their groups (see :func:`nested_hparams`)."""
    out: dict[str, Any] = {"net": {}, "objective": {}, "optimizer": dict(ADAM), "scheduler": {}}
    for key, value in hparams.items():
        if key in FLAT_KEYS:
            group, name = FLAT_KEYS[key].split(".")
            out[group][name] = value
        elif key != "lr_schedule":
            out[key] = value
    schedule = out.pop("scheduler")
    if hparams.get("lr_schedule") == "cosine":
        eta_min = out["optimizer"].get("lr", 1e-4) * schedule.get("gamma", 0.1)
        out["scheduler"] = COSINE_LR | {"eta_min": eta_min}
    else:
        out["scheduler"] = STEP_LR | schedule
    return out


def current_hparams(hparams: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's stored hyper-parameters as today's grouped options: retired ones dropped, renamed
    ones renamed, flat ones grouped and added ones filled (:func:`nested_hparams`)."""
    hparams = dict(hparams)
    for key in RETIRED_HPARAMS:
        hparams.pop(key, None)
    for old, new in RENAMED_HPARAMS.items():
        if all(k in hparams for k in old):
            hparams[new] = tuple(hparams.pop(k) for k in old)
    return nested_hparams(hparams)


__all__ = [
    "ADDED_HPARAMS",
    "FLAT_KEYS",
    "RENAMED_HPARAMS",
    "RETIRED_HPARAMS",
    "current_hparams",
    "nested_hparams",
]
