"""Distance hints: the plane sweep against rendered ground truth, the hint files, and the hint term."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import RayCache
from fisheyedepth.data import FisheyeDataset, Kitti360Layout, collate, flip_sample, hint_path
from fisheyedepth.losses import candidate_distances, hint_loss, plane_sweep
from fisheyedepth.losses.hints import window_mean
from fisheyedepth.module import FisheyeDepthModule

from conftest import TRAIN_SEQ, load_script, tiny_batch, tiny_samples


def test_candidate_distances_are_log_spaced_between_the_bounds():
    c = candidate_distances(0.5, 80.0, 48)
    assert c.dtype == torch.float64 and c.shape == (48,)
    assert c[0].item() == pytest.approx(0.5, rel=1e-12) and c[-1].item() == pytest.approx(80.0, rel=1e-12)
    steps = c[1:] / c[:-1]
    assert torch.allclose(steps, torch.full_like(steps, 160 ** (1 / 47)), rtol=1e-10)
    for bad in ((0.0, 80.0, 48), (5.0, 1.0, 48), (0.5, 80.0, 1)):
        with pytest.raises(ValueError, match="candidates"):
            candidate_distances(*bad)


def test_window_mean_averages_the_valid_pixels_only():
    error = torch.arange(25, dtype=torch.float64).reshape(1, 5, 5)
    valid = torch.ones(1, 5, 5, dtype=torch.bool)
    valid[0, 2, 1] = False  # 11 leaves the centre's window
    out = window_mean(error, valid, 3)
    centre = [6, 7, 8, 12, 13, 16, 17, 18]
    assert out[0, 2, 2].item() == pytest.approx(sum(centre) / 8, rel=1e-12)
    assert out[0, 1, 1].item() == pytest.approx((0 + 1 + 2 + 5 + 6 + 7 + 10 + 12) / 8, rel=1e-12)
    # a corner's window has 4 of 9 pixels inside the image: below the default 0.6 share
    assert math.isinf(out[0, 0, 0].item())
    assert window_mean(error, valid, 3, min_share=0.4)[0, 0, 0].item() == pytest.approx(3.0, rel=1e-12)


def test_hint_loss_is_the_log_gap_over_the_used_pixels_divided_by_all():
    pred = torch.tensor([[[1.0, 2.0], [4.0, 8.0]]])
    hint = torch.tensor([[[2.0, 2.0], [1.0, 0.0]]])
    use = torch.tensor([[[True, True], [True, False]]])
    loss, share = hint_loss(pred[:, None], hint, use)
    assert loss.item() == pytest.approx((math.log(2) + 0 + math.log(4)) / 4, rel=1e-6)
    assert share.item() == pytest.approx(0.75)
    pred = pred.clone().requires_grad_(True)
    hint_loss(pred, hint, use)[0].backward()
    assert pred.grad[0, 0, 0].item() == pytest.approx(-1 / 4, rel=1e-6)  # d|log L - log 2|/dL at L=1, / 4
    assert pred.grad[0, 1, 1].item() == 0.0  # not used: no gradient, and hint 0 gives no NaN
    assert torch.isfinite(pred.grad).all()


def test_the_plane_sweep_finds_the_rendered_distances(kitti_data):
    """On a rendered world the hints agree with the ground truth where they are valid: the sweep finds
    near and far surfaces from the real poses and fisheye cameras, and refuses the sky."""
    batch = tiny_batch(kitti_data, size=(256, 256))
    rays, rays_valid = RayCache().batch(batch.camera, "cpu", torch.float32)
    candidates = candidate_distances(0.5, 80.0, 48).float()
    hint, valid = plane_sweep(
        batch.image,
        batch.sources,
        batch.poses,
        rays,
        rays_valid & (batch.mask[:, 0] > 0.5),
        batch.source_camera,
        batch.source_mask,
        candidates,
    )
    assert hint.shape == valid.shape == (4, 256, 256)
    assert bool((hint[~valid] == 0).all()) and bool((hint[valid] > 0.5).all())
    gt = batch.distance[:, 0]
    scored = valid & (gt > 0)
    assert scored.float().mean().item() > 0.1  # hints on a tenth of the pixels at least
    ratio = torch.maximum(hint / gt, gt / hint)[scored]
    assert (ratio < 1.25).float().mean().item() > 0.85
    near = scored & (gt < 8)
    assert near.sum().item() > 1000
    assert (torch.maximum(hint / gt, gt / hint)[near] < 1.25).float().mean().item() > 0.9
    # the sky (no ground truth) has no hint at the last candidate, which only bounds the distance
    assert not bool((hint == candidates[-1]).any())
    # the window, the agreement of the sources and the uniqueness are what make a hint: each pixel's
    # own cheapest candidate is right far less often
    raw, raw_valid = plane_sweep(
        batch.image,
        batch.sources,
        batch.poses,
        rays,
        rays_valid & (batch.mask[:, 0] > 0.5),
        batch.source_camera,
        batch.source_mask,
        candidates,
        window=1,
        ratio=1.0,
        agree=len(candidates),
    )
    raw_scored = raw_valid & (gt > 0)
    raw_right = (torch.maximum(raw / gt, gt / raw)[raw_scored] < 1.25).float().mean().item()
    assert raw_right < (ratio < 1.25).float().mean().item() - 0.1
    with pytest.raises(ValueError, match="two sources"):
        plane_sweep(
            batch.image,
            batch.sources[:, :1],
            batch.poses[:, :1],
            rays,
            rays_valid,
            [c[:1] for c in batch.source_camera],
            None,
            candidates,
        )


def test_make_hints_writes_files_the_dataset_reads_and_flips(kitti_data, tmp_path, capsys):
    script = load_script("make_hints")
    out = tmp_path / "hints"
    args = [
        str(kitti_data),
        "--split",
        "all",
        "--size",
        "64",
        "64",
        "--offsets",
        "-1",
        "1",
        "--candidates",
        "24",
        "--out",
        str(out),
    ]
    assert script.main(args) == 0
    assert "image_02 coverage" in capsys.readouterr().out
    layout = Kitti360Layout(kitti_data)
    dataset = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], size=(64, 64), hints=out, ground_truth="none")
    item = dataset.items[3]
    path = hint_path(out, item.sequence, item.camera, layout.frames(item.sequence, item.camera)[item.row].key)
    stored = np.load(path)
    assert stored.dtype == np.float16 and stored.shape == (64, 64)
    sample = dataset[3]
    assert torch.equal(sample["hint"][0], torch.from_numpy(stored.astype(np.float32)))
    assert (sample["hint"] > 0).any()
    assert torch.equal(flip_sample(sample)["hint"], sample["hint"].flip(-1))
    assert collate([sample, dataset[4]]).hint.shape == (2, 1, 64, 64)
    # existing hints are kept; other settings are refused without --overwrite
    mtime = path.stat().st_mtime_ns
    assert script.main(args) == 0 and path.stat().st_mtime_ns == mtime
    with pytest.raises(SystemExit, match="window"):
        script.main([*args, "--window", "5"])
    # a missing or malformed hint names its file
    path.unlink()
    with pytest.raises(FileNotFoundError, match=str(path.name)):
        dataset[3]
    np.save(path, np.zeros((32, 64), np.float16))
    with pytest.raises(ValueError, match=f"{path.name}: hint is 64x32"):
        dataset[3]
    np.save(path, np.full((64, 64), np.nan, np.float16))
    with pytest.raises(ValueError, match="non-finite"):
        dataset[3]
    with pytest.raises(FileNotFoundError, match="is not a folder"):
        FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], size=(64, 64), hints=tmp_path / "none")


def test_the_hint_term_pulls_towards_hints_that_warp_better(kitti_data):
    """With the ground truth as hints, the term acts where the truth warps better than the prediction,
    adds ``hint_weight`` times its value to the loss, and its gradient moves the prediction towards it."""
    samples = tiny_samples(kitti_data)
    for s in samples:
        s["hint"] = s["distance"].clone()
    batch = collate(samples)
    torch.manual_seed(0)
    plain = FisheyeDepthModule(scales=(0,), automask=False)
    hinted = FisheyeDepthModule(scales=(0,), automask=False, hint_weight=0.5)
    hinted.load_state_dict(plain.state_dict())
    plain.train(), hinted.train()
    outputs = plain(batch.image, batch.camera)
    loss_plain, _ = plain.losses(batch, outputs)
    loss_hinted, logs = hinted.losses(batch, outputs)
    assert 0.05 < logs["hint_pixels"].item() < 1.0
    assert logs["hint"].item() > 0
    assert loss_hinted.item() == pytest.approx(loss_plain.item() + 0.5 * logs["hint"].item(), rel=1e-5)
    # the same term by hand: the truth's min-reprojection error against the prediction's
    distance = outputs["distance"][0].detach().requires_grad_(True)
    _, logs = hinted.losses(batch, {**outputs, "distance": {0: distance}})
    logs["hint"].backward()
    gt = batch.distance[:, 0]
    moved = distance.grad[:, 0] != 0
    assert moved.any() and bool((gt[moved] > 0).all())
    towards = torch.sign(distance.detach()[:, 0] - gt)[moved] == torch.sign(distance.grad[:, 0][moved])
    assert towards.all()  # gradient descent moves every used pixel towards its hint
    # evaluation does not need hints; training without them is an error; the weight is checked
    hinted.eval()
    hinted.losses(collate(tiny_samples(kitti_data)), outputs)
    hinted.train()
    with pytest.raises(ValueError, match="data.datamodule.hints"):
        hinted.losses(collate(tiny_samples(kitti_data)), outputs)
    for bad in (0.0, -1.0):
        with pytest.raises(ValueError, match="hint_weight"):
            FisheyeDepthModule(hint_weight=bad)
