"""The LightningModule: it learns, it measures geometry, each ablation switch does one thing."""

from __future__ import annotations

import copy
import dataclasses
import re
import warnings

import lightning as L
import pytest
import torch
from torch.nn import functional as F
from torch.utils.data import DataLoader

from fisheyedepth.cameras import MeiCamera, PinholeCamera, erode_field_of_view, pinhole_like
from fisheyedepth.data.batch import collate
from fisheyedepth.models import MultiChannelHead, PoseNet, SigmoidHead
from fisheyedepth.module import FisheyeDepthModule, count_parameters

from conftest import ROOT, bare_module, bare_objective, tiny_batch, tiny_samples


def photometric_after(module, batch, steps, lr):
    opt = torch.optim.Adam(module.parameters(), lr, fused=True)
    history = []
    for _ in range(steps):
        loss, logs = module.objective(batch, module(batch.image, batch.camera))
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(logs["photometric/0"].item())
    return history


# the PoseNet row also has to learn the motion: its pose errors are the test below
@pytest.mark.parametrize("real_scale,lr,factor", [(True, 3e-4, 0.8), (False, 3e-4, 0.8)])
def test_overfitting_a_batch_cuts_the_photometric_loss(kitti_data, real_scale, lr, factor):
    torch.manual_seed(0)
    module = bare_module(objective={"real_scale": real_scale, "automask": False}, log_images_every=0)
    # 25 steps: the ratio is 0.58-0.73 over seeds 0-2 for both rows (40 steps: 0.50-0.54)
    history = photometric_after(module, tiny_batch(kitti_data), 25, lr)
    assert history[-1] < factor * history[0], history[::5]


def test_channels_last_changes_the_memory_order_not_the_numbers(kitti_data):
    """The NHWC path (the default, for speed) gives the NCHW path's loss and gradients from the same
    weights, and its state dict loads into either."""
    batch = tiny_batch(kitti_data)
    results = {}
    for channels_last in (False, True):
        torch.manual_seed(0)
        module = bare_module(net={"channels_last": channels_last}, log_images_every=0)
        conv = module.depth_net.encoder.conv1.weight
        assert conv.is_contiguous(memory_format=torch.channels_last) == channels_last
        loss, _ = module.objective(batch, module(batch.image, batch.camera))
        loss.backward()
        grads = {n: p.grad.clone() for n, p in module.named_parameters() if p.grad is not None}
        results[channels_last] = (loss.item(), grads, module.state_dict())
    (loss_a, grads_a, _), (loss_b, grads_b, state_b) = results[False], results[True]
    assert loss_b == pytest.approx(loss_a, rel=1e-5)
    assert grads_a.keys() == grads_b.keys() and len(grads_a) >= 90
    # float32 rounding only: NHWC and NCHW kernels sum in other orders. The whole gradient agrees to
    # about 2e-4; the deepest layers' own gradients (norms near 1e-5, through BatchNorm over 2x2 maps)
    # differ by up to 2e-3 on an AMX Xeon's oneDNN kernels, and a wrong memory order would differ by O(1)
    total = torch.cat([(grads_b[n] - g).flatten() for n, g in grads_a.items()]).norm()
    assert float(total / torch.cat([g.flatten() for g in grads_a.values()]).norm()) < 1e-3
    worst = max(float((grads_b[n] - g).norm() / g.norm().clamp_min(1e-12)) for n, g in grads_a.items())
    assert worst < 1e-2, worst
    bare_module(net={"channels_last": False}).load_state_dict(state_b)


def test_channels_last_posenet_gives_the_same_poses_and_gradients():
    """The PoseNet alone (in the full loss, a pose that differs in the 7th digit can flip a pixel's
    minimum-reprojection choice, which says nothing about the network)."""
    nets = []
    for channels_last in (False, True):
        torch.manual_seed(0)
        nets.append(PoseNet(18, None, 1.3, channels_last).eval())
    gen = torch.Generator().manual_seed(1)
    target, source = torch.rand(2, 3, 64, 96, generator=gen), torch.rand(2, 3, 64, 96, generator=gen)
    weights = torch.randn(2, 4, 4, generator=gen)
    outs, grads = [], []
    for net in nets:
        T = net(target, source, True)
        (T * weights).sum().backward()
        outs.append(T.detach())
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
    assert torch.allclose(outs[1], outs[0], atol=1e-6)
    assert float((grads[1] - grads[0]).norm() / grads[0].norm()) < 1e-4


def test_the_loss_measures_geometry(kitti_data):
    """Ground-truth distance as the prediction beats a wrong constant distance, for every camera."""
    module = bare_module(net={"scales": (0,)}, objective={"automask": False})
    batch = tiny_batch(kitti_data, size=None)  # at 256 px: at 64 px mixed pixels swamp the parallax
    gt = batch.distance

    def loss_with(distance):
        disp = torch.full_like(distance, 0.5)
        return module.objective(batch, {"distance": {0: distance}, "disp": {0: disp}})[1][
            "photometric/0"
        ].item()

    # the sky (GT 0) sits at 10 km in every case: its warps stay valid and nearly parallax-free
    surface = gt > 0
    far = torch.full_like(gt, 1e4)
    truth = loss_with(torch.where(surface, gt, far))
    for wrong in (3.0, 10.0, 40.0):
        assert truth < 0.8 * loss_with(torch.where(surface, torch.full_like(gt, wrong), far)), wrong
    assert truth < 0.95 * loss_with(torch.where(surface, gt * 1.3, far))
    assert truth < 0.95 * loss_with(torch.where(surface, gt * 0.8, far))


def test_the_pinhole_stand_in_prefers_no_motion_to_the_truth(kitti_data):
    """Why the Monodepth2 baseline cannot learn the truth on a fisheye rig: with true distance and true
    poses, its pinhole warp reconstructs the target worse than no motion at all, while the fisheye warp
    does far better than no motion (``scripts/research/diagnose_warp.py`` measures the same on whole
    worlds)."""
    batch = tiny_batch(kitti_data, size=None)
    gt = torch.where(batch.distance > 0, batch.distance, torch.full_like(batch.distance, 1e4))
    outputs = {"distance": {0: gt}, "disp": {0: torch.full_like(gt, 0.5)}}
    still = dataclasses.replace(batch, poses=torch.eye(4).expand_as(batch.poses).clone())
    errors = {}
    for fisheye in (True, False):
        module = bare_module(
            net={"scales": (0,)}, objective={"fisheye_projection": fisheye, "automask": False}
        )
        with torch.no_grad():
            errors[fisheye] = [
                module.objective(b, outputs)[1]["photometric/0"].item() for b in (batch, still)
            ]
    (fish_truth, fish_still), (pin_truth, pin_still) = errors[True], errors[False]
    assert fish_truth < 0.6 * fish_still, errors
    assert pin_truth > pin_still, errors


def test_fisheye_projection_switch_replaces_only_the_warp_camera(kitti_data):
    full = bare_module()
    pin = bare_module(objective={"fisheye_projection": False})
    pin.load_state_dict(full.state_dict())
    batch = tiny_batch(kitti_data)
    cam = batch.camera[0]
    assert isinstance(cam, MeiCamera) and full.objective.warp_model(cam) is cam
    assert pin.objective.warp_model(cam) == pinhole_like(cam) and isinstance(
        pin.objective.warp_model(cam), PinholeCamera
    )
    gamma = bare_module(
        objective={"fisheye_projection": False, "pinhole_focal": "calibration"}
    ).objective.warp_model(cam)
    assert (gamma.fx, gamma.fy, gamma.cx, gamma.cy) == (cam.gamma1, cam.gamma2, cam.u0, cam.v0)
    assert pin.objective.warp_model(cam).fx == pytest.approx(cam.gamma1 / (1 + cam.xi))  # paraxial
    with pytest.raises(ValueError, match="pinhole_focal: 'fov' is not one of paraxial, calibration"):
        bare_module(objective={"fisheye_projection": False, "pinhole_focal": "fov"})
    with torch.no_grad():
        out = full(batch.image, batch.camera)
        assert torch.equal(out["distance"][0], pin(batch.image, batch.camera)["distance"][0])
        assert full.objective(batch, out)[0] != pin.objective(batch, out)[0]


def test_multi_channel_switch_replaces_only_the_heads():
    mc, single = bare_module(), bare_module(net={"multi_channel": False})
    assert all(isinstance(h, MultiChannelHead) for h in mc.depth_net.heads.values())
    assert all(isinstance(h, SigmoidHead) for h in single.depth_net.heads.values())
    for part in ("encoder", "decoder"):
        assert count_parameters(getattr(mc.depth_net, part)) == count_parameters(
            getattr(single.depth_net, part)
        )
    assert (
        mc.objective.smoothness == single.objective.smoothness == 1e-3
    )  # shared: the switch changes the head alone
    assert mc.pose_net is None and single.pose_net is None
    # with a PoseNet, its translation unit follows the head's first distance (Monodepth2's ratio)
    mc_pose, single_pose = (
        bare_module(objective={"real_scale": False}),
        bare_module(net={"multi_channel": False}, objective={"real_scale": False}),
    )
    # both heads start at the binned head's first distance (26 m), not Monodepth2's 1 m
    assert mc_pose.depth_net.initial_distance == pytest.approx(float(mc_pose.depth_net.bins.mean()))
    assert single_pose.depth_net.initial_distance == mc_pose.depth_net.initial_distance
    assert 25.0 < single_pose.depth_net.initial_distance < 28.0
    torch.manual_seed(0)
    image = torch.rand(2, 3, 64, 64)
    for m in (mc_pose, single_pose):
        with torch.no_grad():
            first = m.depth_net.eval()(image, scales=(0,))["distance"][0]
        assert first.median().item() == pytest.approx(m.depth_net.initial_distance, rel=0.25)
    for m in (mc_pose, single_pose):
        assert m.pose_net.decoder.translation_scale == pytest.approx(0.05 * m.depth_net.initial_distance)


def test_real_scale_switch_replaces_only_the_poses(kitti_data):
    batch = tiny_batch(kitti_data)
    moved = dataclasses.replace(batch, poses=batch.poses.clone())
    moved.poses[..., :3, 3] *= 1.5
    real, learned = (
        bare_module(objective={"automask": False}),
        bare_module(objective={"real_scale": False, "automask": False}),
    )
    assert learned.pose_net is not None and real.pose_net is None
    assert count_parameters(real.depth_net) == count_parameters(learned.depth_net)
    with torch.no_grad():
        out = real(batch.image, batch.camera)
        assert real.objective(batch, out)[0] != real.objective(moved, out)[0]  # real-scale poses are used ...
        out = learned(batch.image, batch.camera)
        assert learned.objective(batch, out)[0] == learned.objective(moved, out)[0]  # ... or ignored


def test_mixed_cameras_in_one_batch(kitti_data):
    batch = tiny_batch(kitti_data, frames=(4,), cameras=("image_02", "image_03"))
    assert batch.camera[0] != batch.camera[1]
    module = bare_module(net={"scales": (0, 1)})
    loss, logs = module.objective(batch, module(batch.image, batch.camera))
    assert torch.isfinite(loss) and 0.1 < logs["used_pixels/0"].item() <= 1.0  # sky, body, corners: out


class _Loader(list):
    pass


def test_lightning_fit_validate_predict_and_skip_non_finite_batches(kitti_data, tmp_path):
    flat = tiny_samples(kitti_data, frames=(1, 2, 3))
    poisoned = copy.deepcopy(flat[0])
    poisoned["image"][:] = float("nan")
    train = DataLoader([poisoned, *flat], batch_size=2, collate_fn=collate)
    val = DataLoader(flat, batch_size=3, collate_fn=collate)
    module = bare_module(net={"scales": (0, 1)}, log_images_every=1)
    logger = L.pytorch.loggers.CSVLogger(tmp_path, name="run")
    trainer = L.Trainer(
        max_epochs=1,
        logger=logger,
        enable_checkpointing=False,
        enable_progress_bar=False,
        accelerator="cpu",
        gradient_clip_val=1.0,
        enable_model_summary=False,
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer.fit(module, train, val)
    assert module.skipped_batches == 1
    assert all(torch.isfinite(b).all() for b in module.buffers())  # BatchNorm statistics restored
    assert any("non-finite loss" in str(w.message) for w in caught)
    metrics = trainer.callback_metrics
    for key in ("val/abs_rel", "val/scaled/abs_rel", "val/a1", "train/loss", "train/skipped_batches"):
        assert key in metrics and torch.isfinite(metrics[key]), key
    assert 0 < metrics["val/abs_rel"] < 10
    images = list((tmp_path / "run").rglob("images/*.png"))
    assert any(p.name.startswith("train_") for p in images) and any(p.name.startswith("val_") for p in images)
    assert 0 < metrics["val/photometric"] < metrics["val/loss"] + 1e-6
    assert "test_step" not in vars(FisheyeDepthModule)  # one evaluation path: evaluation.evaluate
    predictions = trainer.predict(module, val)
    assert predictions[0].shape == (3, 1, 64, 64) and (predictions[0] > 0).all()


@pytest.mark.parametrize("multi_channel", [False, True])
def test_a_posenet_row_learns_its_poses_on_a_tiny_world(kitti_data, multi_channel):
    """The PoseNet rows used to start late or never: Monodepth2's 0.01 m translation unit against a head
    that started at 1 m (sigmoid) or 26 m (bins) made the first warps 5x-130x too short, and a PoseNet
    predicting each camera's own motion learned one motion for both side cameras (reversed for one).
    With the unit tied to the head's first distance and the body's motion predicted, the photometric
    loss falls and the translation direction is learned, for both cameras, within 20 steps (seeds 0-2,
    both heads: loss ratio 0.40-0.48, direction error 3.0-11.5 degrees, rotation under 1 degree, scale
    13-54x)."""
    torch.manual_seed(0)
    module = bare_module(
        net={"multi_channel": multi_channel, "scales": (0,)}, objective={"real_scale": False}
    )
    batch = tiny_batch(kitti_data, frames=(1, 2, 3, 4))
    before = module.objective.pose_errors(batch)
    history = photometric_after(module, batch, 20, 1e-3)
    after = module.objective.pose_errors(batch)
    assert history[-1] < 0.85 * history[0], history[::5]
    assert after["direction_deg"] < min(0.3 * before["direction_deg"], 15), (before, after)
    assert after["reversed"] == 0 and after["rotation_deg"] < 2.0, after
    assert after["scale"] > 5 * before["scale"]  # the translation grew towards the scene's parallax


def test_a_posenet_predicts_the_body_motion_and_each_camera_follows_its_extrinsic(kitti_data):
    """Given the true body motion, the PoseNet path reproduces every camera's real-scale poses, also
    for flipped samples (E becomes E M): the PoseNet rows differ from the real-scale rows only in where
    the body motion comes from."""
    from fisheyedepth.data.augment import flip_sample
    from fisheyedepth.geometry import invert_pose

    batch = tiny_batch(kitti_data, frames=(2, 3), cameras=("image_02", "image_03"))
    E = batch.cam_to_body.double()[:, None]
    body = E @ batch.poses.double() @ invert_pose(E)  # the vehicle's motion, the same for both cameras
    assert torch.allclose(body[0], body[1], atol=1e-5)  # image_02 and image_03 of frame 2
    samples = tiny_samples(kitti_data, frames=(2, 3), cameras=("image_02", "image_03"))
    flipped = collate([flip_sample(s) for s in samples])

    class Oracle(torch.nn.Module):  # a PoseNet that knows the body motion
        def forward(self, target, source, source_is_earlier):
            j = 0 if source_is_earlier else 1
            return body[:, j].to(target)

    objective = bare_objective(scales=(0,), real_scale=False, pose_net=Oracle())
    for b in (batch, flipped):
        assert torch.allclose(objective.relative_poses(b).double(), b.poses.double(), atol=1e-5)


@pytest.mark.parametrize("real_scale,multi_channel", [(True, True), (False, False)])
def test_bf16_autocast_runs_the_networks_in_bf16_and_the_geometry_in_float32(
    kitti_data, real_scale, multi_channel
):
    """``trainer.precision=bf16-mixed``: the convolutions run in bf16, every distance, pose, warp and
    loss in float32, and the loss stays within bf16 rounding of the float32 loss."""
    batch = tiny_batch(kitti_data)
    torch.manual_seed(0)
    module = bare_module(
        net={"multi_channel": multi_channel},
        objective={"real_scale": real_scale, "automask": False},
        log_images_every=0,
    )
    exact, _ = module.objective(batch, module(batch.image, batch.camera))
    seen: set[torch.dtype] = set()
    hook = module.depth_net.encoder.conv1.register_forward_hook(lambda m, i, o: seen.add(o.dtype))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outputs = module(batch.image, batch.camera)
        poses = module.objective.relative_poses(batch)
        loss, logs = module.objective(batch, outputs)
    hook.remove()
    assert seen == {torch.bfloat16}  # the network did run in bf16
    assert {v.dtype for maps in outputs.values() for v in maps.values()} == {torch.float32}
    assert poses.dtype == loss.dtype == logs["photometric/0"].dtype == torch.float32
    assert abs(loss.item() - exact.item()) < 0.03 * exact.item()
    loss.backward()
    grads = [p.grad for p in module.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)


def test_lightning_trains_with_bf16_mixed_precision(kitti_data, tmp_path):
    """As train.py runs: bf16-mixed, gradient clipping and the fused Adam together (Lightning's own
    clipping refuses a fused optimiser under mixed precision; the module clips instead)."""
    flat = tiny_samples(kitti_data, frames=(1, 2, 3))
    loader = DataLoader(flat, batch_size=2, collate_fn=collate)
    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1)}, log_images_every=0)
    before = copy.deepcopy(module.state_dict())
    trainer = L.Trainer(
        max_epochs=1,
        precision="bf16-mixed",
        gradient_clip_val=1.0,
        default_root_dir=tmp_path,  # the validation panel is written there
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        accelerator="cpu",
        enable_model_summary=False,
    )
    trainer.fit(module, loader, loader)
    assert module.skipped_batches == 0 and torch.isfinite(trainer.callback_metrics["val/photometric"])
    assert all(p.dtype == torch.float32 for p in module.parameters())  # float32 master weights
    moved = [
        k for k, v in module.state_dict().items() if v.is_floating_point() and not torch.equal(v, before[k])
    ]
    assert len(moved) > 50
    assert trainer.optimizers[0].param_groups[0]["fused"] is True


@pytest.mark.parametrize("algorithm", ["norm", "value"])
def test_the_module_clips_gradients_as_torch_does(algorithm):
    """By the norm that the non-finite test took (once per step), or by value: torch's own numbers."""
    torch.manual_seed(0)
    module = bare_module(net={"scales": (0,)})
    optimizer = module.configure_optimizers()["optimizer"]
    params = list(module.parameters())
    expected = []
    for p in params:
        p.grad = torch.randn_like(p) * 1e-3  # a total norm near 3.8
        expected.append(torch.nn.Parameter(p.detach().clone()))
        expected[-1].grad = p.grad.clone()
    limit = 1.0 if algorithm == "norm" else 1e-4
    if algorithm == "norm":
        total = float(torch.nn.utils.clip_grad_norm_(expected, limit))
    else:
        torch.nn.utils.clip_grad_value_(expected, limit)
    module.on_before_optimizer_step(optimizer)
    if algorithm == "norm":
        assert total > 3 and float(module.guard.grad_norm) == pytest.approx(total, rel=1e-5)
    module.configure_gradient_clipping(optimizer, limit, algorithm)
    assert module.guard.grad_norm is None  # used once: the next step takes its own
    worst = max(float((p.grad - e.grad).abs().max()) for p, e in zip(params, expected, strict=True))
    assert worst < 1e-9
    after = [p.grad for p in params]
    if algorithm == "norm":
        assert float(torch.nn.utils.get_total_norm(after)) == pytest.approx(1.0, rel=1e-4)
    else:
        assert max(float(g.abs().max()) for g in after) == pytest.approx(1e-4)
    with pytest.raises(ValueError, match="gradient_clip_algorithm='max'"):
        module.configure_gradient_clipping(optimizer, 1.0, "max")


def test_native_loss_resolution_warps_each_scale_at_its_own_size(kitti_data):
    """``loss_resolution=native`` compares scale s at its own size: the same scale-0 loss as "full", the
    coarser scales from resized cameras and downsampled images; with the true distance it still measures
    geometry at every scale (truth beats a wrong constant), and a bad name is refused."""
    batch = tiny_batch(kitti_data, size=None)  # 256 px: scales 1-2 at 128 and 64 px
    gt = torch.where(batch.distance > 0, batch.distance, torch.full_like(batch.distance, 1e4))
    modules = {
        r: bare_module(net={"scales": (0, 1, 2)}, objective={"automask": False, "loss_resolution": r})
        for r in ("full", "native")
    }

    def photometric(module, distance):
        maps = {s: F.interpolate(distance, scale_factor=0.5**s, mode="nearest") for s in (0, 1, 2)}
        outputs = {"distance": maps, "disp": {s: torch.full_like(d, 0.5) for s, d in maps.items()}}
        return module.objective(batch, outputs)[1]

    full, native = photometric(modules["full"], gt), photometric(modules["native"], gt)
    assert native["photometric/0"].item() == pytest.approx(full["photometric/0"].item(), rel=1e-6)
    assert native["photometric/2"].item() != pytest.approx(full["photometric/2"].item(), rel=1e-3)
    wrong = photometric(modules["native"], torch.where(batch.distance > 0, torch.full_like(gt, 5.0), gt))
    for s in (0, 1, 2):
        assert native[f"photometric/{s}"] < 0.85 * wrong[f"photometric/{s}"], s
    sizes = {(key[0].width, key[0].height) for key in modules["native"].objective.rays._entries}
    assert sizes == {(256, 256), (128, 128), (64, 64)}  # rays of the resized cameras, cached per size
    # a pixel partly covered by the vehicle body is neither scored nor sampled at the coarser size
    holed = batch.mask.clone()
    holed[:, :, 101, 37] = 0.0
    sources_holed = batch.source_mask.clone()
    sources_holed[:, :, :, 101, 37] = 0.0
    level = modules["native"].objective.level(
        dataclasses.replace(batch, mask=holed, source_mask=sources_holed), (128, 128)
    )
    inside = (batch.mask[:, 0, 100:102, 36:38] > 0.5).all()
    assert inside and not level.mask[:, 50, 18].any() and level.source_mask[:, :, :, 50, 18].eq(0).all()
    assert level.source_mask[:, :, :, 50, 19].eq(1).all() and level.mask[:, 50, 19].all()
    with pytest.raises(ValueError, match="loss_resolution: 'half' is not one of full, native"):
        bare_module(objective={"loss_resolution": "half"})


def test_the_rim_margin_drops_the_image_circles_edge_from_scoring_and_sampling(kitti_data):
    """``rim_margin=k``: a pixel within k pixels of the image circle's edge is neither scored (target) nor
    sampled (sources), at the input size and, through the footprint rule, at a coarser loss scale, where
    a pixel whose footprint reaches past the circle is dropped although its centre has a ray; the body
    masks are kept; the loss still measures geometry; a negative margin is refused."""
    batch = tiny_batch(kitti_data, size=None)  # 256 px
    plain, rim0, rim2 = (
        bare_module(objective={"rim_margin": m, "automask": False, "loss_resolution": "native"})
        for m in (None, 0, 2)
    )
    full = plain.objective.level(batch, None)
    inside = full.rays_valid  # the image circle at 256 px (one Mei camera per sample)
    assert not inside.all()  # the corners have no ray
    ring2 = inside & ~erode_field_of_view(inside, 2)
    level = rim2.objective.level(batch, None)
    assert torch.equal(level.mask, full.mask & ~ring2)
    assert torch.equal(
        rim0.objective.level(batch, None).mask, full.mask
    )  # margin 0: nothing at the input size
    body = batch.source_mask[:, :, 0] > 0.5
    assert torch.equal(level.source_mask[:, :, 0] > 0.5, body & erode_field_of_view(inside, 2)[:, None])
    assert int(ring2.sum()) > 0 and int((full.mask & ring2).sum()) > 0
    # at 64 px each pixel is a 4 x 4 footprint: with margin 0, one that reaches past the circle is dropped
    coarse_plain, coarse = plain.objective.level(batch, (64, 64)), rim0.objective.level(batch, (64, 64))
    partial = F.avg_pool2d(inside[:, None].double(), 4)[:, 0] < 1
    assert torch.equal(coarse.mask, coarse_plain.mask & ~partial)
    dropped = coarse_plain.mask & partial
    assert int(dropped.sum()) > 0 and coarse_plain.rays_valid[dropped].all()  # their centres have rays
    coarse_body = coarse_plain.source_mask[:, :, 0] > 0.5
    assert torch.equal(coarse.source_mask[:, :, 0] > 0.5, coarse_body & ~partial[:, None])
    # the loss with the truth still beats a wrong constant distance
    gt = torch.where(batch.distance > 0, batch.distance, torch.full_like(batch.distance, 1e4))

    def photometric(distance):
        maps = {s: F.interpolate(distance, scale_factor=0.5**s, mode="nearest") for s in (0, 1, 2, 3)}
        outputs = {"distance": maps, "disp": {s: torch.full_like(d, 0.5) for s, d in maps.items()}}
        return rim2.objective(batch, outputs)[1]["photometric/0"].item()

    assert photometric(gt) < 0.85 * photometric(torch.where(batch.distance > 0, torch.full_like(gt, 5.0), gt))
    with pytest.raises(ValueError, match="rim_margin: -1 pixels is negative"):
        bare_module(objective={"rim_margin": -1})


def test_compiled_kernels_give_the_plain_loss_and_gradients_and_are_undone_after_fitting(kitti_data):
    """``compile_kernels``: while fitting, the bin expectation and the photometric error are
    ``torch.compile``'d (fused kernels): the same loss and gradients; after fitting the plain functions
    are back, so evaluation, prediction and export never trace a compiled function."""
    from fisheyedepth.losses.photometric import photometric_error
    from fisheyedepth.models import bin_expectation

    batch = tiny_batch(kitti_data)
    results = []
    for compiled in (False, True):
        torch.manual_seed(0)
        module = bare_module(net={"scales": (0, 1)}, compile_kernels=compiled, log_images_every=0)
        module.on_fit_start()
        assert (module.depth_net.expectation is bin_expectation) != compiled
        assert (module.objective.reprojection.error_fn is photometric_error) != compiled
        loss, _ = module.objective(batch, module(batch.image, batch.camera))
        loss.backward()
        results.append((loss.item(), {n: p.grad for n, p in module.named_parameters() if p.grad is not None}))
        module.on_fit_end()
        assert module.depth_net.expectation is bin_expectation
        assert module.objective.reprojection.error_fn is photometric_error
    (plain, grads), (fused, fused_grads) = results
    assert fused == pytest.approx(plain, rel=1e-5)
    worst = max(float((fused_grads[n] - g).norm() / g.norm().clamp_min(1e-12)) for n, g in grads.items())
    assert worst < 1e-3, worst


def test_cosine_schedule_anneals_to_a_tenth_of_the_lr_over_the_run():
    """``model/scheduler=cosine``: from ``model.optimizer.lr`` to a tenth of it over ``trainer.max_epochs``
    (both followed when overridden); the optimiser is a config choice too."""
    from hydra import compose, initialize_config_dir

    from fisheyedepth.config import configured_model

    overrides = ["model/scheduler=cosine", "model.optimizer.lr=1e-3", "trainer.max_epochs=4"]
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides)
    scheduler = configured_model(cfg)["scheduler"]
    assert scheduler["_target_"] == "torch.optim.lr_scheduler.CosineAnnealingLR"
    assert scheduler["T_max"] == 4 and scheduler["eta_min"] == pytest.approx(1e-4)
    module = bare_module(optimizer={"lr": 1e-3}, scheduler=scheduler)
    config = module.configure_optimizers()
    optimizer, scheduler = config["optimizer"], config["lr_scheduler"]["scheduler"]
    lrs = []
    for _ in range(4):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    lrs.append(optimizer.param_groups[0]["lr"])
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] == pytest.approx(1e-4)
    assert lrs[2] == pytest.approx(1e-4 + 0.5 * (1e-3 - 1e-4))  # half way: the mean of the two
    assert all(a > b for a, b in zip(lrs, lrs[1:], strict=False))
    sgd = {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 0.1, "momentum": 0.9}
    optimizer = bare_module(optimizer=sgd).configure_optimizers()["optimizer"]
    assert type(optimizer) is torch.optim.SGD and optimizer.param_groups[0]["momentum"] == 0.9


def test_adam_is_fused_on_cpu_and_steps_like_the_foreach_kernel():
    """The fused Adam (a speed lever) takes the steps the per-tensor kernels take, weight decay included."""
    torch.manual_seed(0)
    module = bare_module(optimizer={"lr": 1e-3, "weight_decay": 1e-2})
    optimizer = module.configure_optimizers()["optimizer"]
    assert optimizer.param_groups[0]["fused"] is True
    params = list(module.parameters())
    start = [p.detach().clone() for p in params]
    reference = [p.detach().clone().requires_grad_() for p in params]
    plain = torch.optim.Adam(reference, lr=1e-3, weight_decay=1e-2, foreach=True)
    for step in range(3):
        for p, q in zip(params, reference, strict=True):
            p.grad = torch.randn_like(p) * 10.0 ** (-step)
            q.grad = p.grad.clone()
        optimizer.step()
        plain.step()
    moved = min(float((p.detach() - p0).abs().max()) for p, p0 in zip(params, start, strict=True))
    apart = max(float((p.detach() - q.detach()).abs().max()) for p, q in zip(params, reference, strict=True))
    assert moved > 1e-3  # every tensor took three steps of about lr
    assert apart < 1e-6


class _NanGradientOnce(L.Callback):
    """A finite loss whose gradient turns non-finite at one step, in one element of one weight (a hook)."""

    def __init__(self, step: int, value: float = float("nan")):
        self.step, self.value = step, value
        self.before: dict[str, torch.Tensor] = {}

    def _poison(self, grad):
        grad = grad.clone()
        grad.view(-1)[grad.numel() // 2] = self.value
        return grad

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        weight = module.depth_net.heads["0"].logits[1].weight
        if trainer.global_step == self.step:
            self.before = {n: p.detach().clone() for n, p in module.named_parameters()}
            self.handle = weight.register_hook(self._poison)

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        if getattr(self, "handle", None) is not None:
            self.handle.remove()
            self.handle = None
            self.after = {n: p.detach().clone() for n, p in module.named_parameters()}


@pytest.mark.parametrize("value", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_gradients_after_a_finite_loss_skip_the_step(kitti_data, tmp_path, value):
    """One non-finite element among 14 M finite ones: the gradients are dropped before the optimiser, no
    parameter moves (Adam's moments neither, as a parameter without a gradient is left alone), BatchNorm
    is restored, the skip is counted."""
    flat = tiny_samples(kitti_data, frames=(1, 2, 3))
    train = DataLoader(flat, batch_size=2, collate_fn=collate)
    module = bare_module(net={"scales": (0,)})
    probe = _NanGradientOnce(step=1, value=value)
    trainer = L.Trainer(
        max_steps=3, logger=False, enable_checkpointing=False, enable_progress_bar=False,
        accelerator="cpu", enable_model_summary=False, limit_val_batches=0, callbacks=[probe],
        default_root_dir=tmp_path,  # the training panel is written there, not in the working tree
    )  # fmt: skip
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        trainer.fit(module, train)
    assert module.skipped_batches == 1
    assert any("non-finite gradients" in str(w.message) for w in caught)
    assert all(torch.equal(probe.before[n], probe.after[n]) for n in probe.before)
    assert all(torch.isfinite(p).all() for p in module.parameters())
    assert all(torch.isfinite(b).all() for b in module.buffers())


DDP_SCRIPT = """
import os, sys, warnings
import torch, lightning as L
from torch.utils.data import DataLoader
sys.path.insert(0, sys.argv[2])
from conftest import bare_module, tiny_samples
from fisheyedepth.data import collate
from fisheyedepth.module import FisheyeDepthModule

def faulty(objective, args, result):
    # rank 1 alone: a non-finite loss at step 1; rank 0 alone: non-finite gradients at step 3
    loss, logs = result
    if module.training and module.global_rank == 1 and module.global_step == 1:
        loss = loss * float("nan")
    if module.training and module.global_rank == 0 and module.global_step == 3:
        loss.register_hook(lambda g: g * float("nan"))
    return loss, logs

warnings.simplefilter("ignore")
torch.manual_seed(0)
samples = tiny_samples(sys.argv[1], frames=(1, 2, 3))
module = bare_module(net={"scales": (0,)})
module.objective.register_forward_hook(faulty)

class Report(L.Callback):  # runs in each rank's process (forked from this one)
    def on_train_end(self, trainer, module):
        finite = all(bool(torch.isfinite(p).all()) for p in module.parameters())
        rank, steps = trainer.global_rank, trainer.global_step
        # one write per rank: both share the pipe, and print's text and newline can interleave
        os.write(1, f"RANK {rank} skipped {module.skipped_batches} steps {steps} finite {finite}\\n".encode())

trainer = L.Trainer(strategy="ddp_fork", accelerator="cpu", devices=2, max_steps=5, logger=False,
                    enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                    limit_val_batches=0, callbacks=[Report()])
trainer.fit(module, DataLoader(samples, batch_size=2, collate_fn=collate))
"""


def test_ddp_never_hangs_when_one_rank_meets_a_bad_step(kitti_data, tmp_path):
    """Two gloo processes; a non-finite loss on rank 1 only, later non-finite gradients on rank 0 only:
    both ranks skip both steps together, and the run ends (a rank left alone in a collective would
    wait forever: the timeout is the failure)."""
    import os
    import subprocess
    import sys

    script = tmp_path / "ddp_fault.py"
    script.write_text(DDP_SCRIPT)
    proc = subprocess.run(
        [sys.executable, str(script), str(kitti_data), os.path.dirname(__file__)],
        capture_output=True, text=True, timeout=600, cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = sorted(re.findall(r"RANK \d+ skipped \d+ steps \d+ finite \w+", proc.stdout))
    assert lines == ["RANK 0 skipped 2 steps 5 finite True", "RANK 1 skipped 2 steps 5 finite True"], (
        proc.stdout
    )


def test_error_bands_add_up_and_the_objective_prefers_the_truth(kitti_data, checkpoint, tmp_path):
    """``scripts/research/error_bands.py``: each camera's bands share its pixels and their parts add up
    to its abs_rel; the training objective (``pixel_objective``) at the ground truth is below the one at
    a barely trained model's prediction, and below the truth's at twice the distance."""
    from fisheyedepth.data import FisheyeDataset, Kitti360Layout

    from conftest import TRAIN_SEQ, load_script

    script = load_script("research/error_bands")
    module = FisheyeDepthModule.from_checkpoint(checkpoint)
    dataset = FisheyeDataset(
        Kitti360Layout(kitti_data),
        [{"sequence": TRAIN_SEQ}],
        size=(64, 64),
        offsets=(-1, 1),
        ground_truth="distance",
        cache_dir=tmp_path,
    )
    table = script.error_bands(module, dataset, edges=(0.0, 4.0, 10.0, 80.0), every=2)
    assert sorted(table) == ["image_02", "image_03"]
    for camera, bands in table.items():
        whole = bands.pop("all")
        assert whole["pixels"] == sum(b["pixels"] for b in bands.values()) > 500, camera
        assert sum(b["share"] for b in bands.values()) == pytest.approx(1.0)
        assert sum(b["part"] for b in bands.values()) == pytest.approx(whole["abs_rel"], rel=1e-5)
        assert 0.0 <= whole["used"] <= 1.0
        assert whole["loss_truth"] < 0.9 * whole["loss_pred"], (camera, whole)
    batch = collate([dataset[i] for i in range(4)])
    gt = torch.where(
        batch.distance[:, 0] > 0, batch.distance[:, 0], torch.full_like(batch.distance[:, 0], 1e4)
    )
    with torch.no_grad():
        truth, _, usable = module.objective.pixel_objective(batch, gt, batch.poses)
        doubled, _, _ = module.objective.pixel_objective(batch, gt * 2, batch.poses)
    assert truth[usable].mean() < 0.9 * doubled[usable].mean()


def test_the_truth_probe_scores_the_log_ratio_where_the_truth_is_known_and_learns_it(kitti_data):
    """``truth_weight`` adds the mean |log(predicted / true)| over pixels with ground truth inside the body
    mask, per scale; with ``photometric_weight`` 0 no warp runs in training, validation still logs the
    photometric criterion, and a few steps of the module fit the truth."""
    batch = tiny_batch(kitti_data)
    truth = batch.distance
    known = (truth > 0) & (batch.mask > 0.5)
    assert 0.2 < float(known.float().mean()) < 0.9  # the rim, sky and body: pixels left out
    objective = bare_objective(scales=(0, 1), truth_weight=1.0, photometric_weight=0.0)
    wrong = torch.where(known, truth * 2.0, torch.full_like(truth, 1e4))  # far off where unknown
    outputs = {"distance": {0: wrong, 1: F.avg_pool2d(wrong, 2)}}
    loss, logs = objective.train()(batch, outputs)
    assert not any(k.startswith("photometric") for k in logs)
    # scale 0 is exactly log 2; scale 1 is upsampled, so pixels beside unknown ones pull it up
    scale0 = bare_objective(scales=(0,), truth_weight=1.0, photometric_weight=0.0)
    assert float(scale0.train()(batch, {"distance": {0: wrong}})[0]) == pytest.approx(0.693147, abs=1e-5)
    assert float(logs["truth"]) == float(loss) and float(loss) > 0.69
    # both terms: the photometric loss and the truth term add up with their weights
    module = bare_module(objective={"truth_weight": 0.5}, log_images_every=0)
    module.train()
    out = module(batch.image, batch.camera)
    both, parts = module.objective(batch, out)
    photometric = torch.stack(
        [parts[f"photometric/{s}"] + 1e-3 / 2**s * parts[f"smoothness/{s}"] for s in module.scales]
    ).mean()
    assert float(both) == pytest.approx(float(photometric + 0.5 * parts["truth"]), rel=1e-5)
    # validation keeps Monodepth2's criterion beside the truth term
    module.objective.eval()
    with torch.no_grad():
        _, parts = module.objective(batch, out)
    assert {"automasked/0", "truth"} <= set(parts)
    # a few steps of the probe fit the truth
    torch.manual_seed(0)
    probe = bare_module(objective={"truth_weight": 1.0, "photometric_weight": 0.0}, log_images_every=0)
    opt = torch.optim.Adam(probe.parameters(), 3e-4)
    history = []
    for _ in range(20):  # 1.16 -> 0.30 (at 1e-3 the bins saturate and it stalls at 0.84)
        loss, parts = probe.objective(batch, probe(batch.image, batch.camera))
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(float(parts["truth"]))
    assert history[-1] < 0.4 * history[0], history[::4]
    # refused: no truth in the training batch, no positive weight
    with pytest.raises(ValueError, match="truth_weight.*ground_truth_splits"):
        objective.train()(dataclasses.replace(batch, distance=None), outputs)
    with pytest.raises(ValueError, match="truth_weight 0.0, photometric_weight 0.0"):
        bare_objective(truth_weight=0.0, photometric_weight=0.0)
