"""Data layer: KITTI-360 and rig layouts, the dataset and DataModule, flip consistency, LiDAR ground truth,
bad input."""

from __future__ import annotations

import math
import shutil

import cv2
import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import RayCache, load_camera
from fisheyedepth.data import (
    Augment,
    FisheyeDataModule,
    FisheyeDataset,
    ImageCache,
    Kitti360Layout,
    RigLayout,
    collate,
    colour_jitter,
    flip_sample,
)
from fisheyedepth.data.kitti360 import (
    LidarGroundTruth,
    project_points,
    read_cam_to_pose,
    read_poses,
    read_velodyne,
)
from fisheyedepth.geometry import sample as grid_sample_image
from fisheyedepth.geometry import warp_to_source

from conftest import TRAIN_SEQ, bare_module, quaternion_xyzw


@pytest.fixture
def cache(tmp_path):
    return tmp_path / "cache"


def warp_l1(s: dict, j: int = 0, scale: float = 1.0) -> tuple[float, float]:
    """``(mean |warped source j - target|, fraction of target pixels warped)``, warping with the sample's
    own GT distance times ``scale`` and its geometry (the source's own camera and mask when it has one)."""
    rays, valid = RayCache().get(s["camera"])
    usable = valid & (s["distance"][0] > 0) & (s["mask"][0] > 0.5)  # the target's own body mask too
    camera = s["source_camera"][j] if "source_camera" in s else s["camera"]
    mask = s["source_mask"][j] if "source_mask" in s else s["mask"]
    distance = s["distance"][None] * scale
    warp = warp_to_source(rays[None], usable[None], distance, s["poses"][j][None], camera, mask[None])
    warped = grid_sample_image(s["sources"][j][None], warp.grid)[0]
    return (warped - s["image"]).abs().mean(0)[warp.valid[0]].mean().item(), warp.valid.float().mean().item()


def photometric_l1(s: dict, j: int = 0) -> float:
    """Mean |warped source j - target| over valid pixels, warping with the sample's own GT and geometry."""
    return warp_l1(s, j)[0]


def test_datamodule_batches(kitti_data, cache):
    dm = FisheyeDataModule(kitti_data, size=(128, 128), batch_size=4, augment=Augment(), cache_dir=cache)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch.image.shape == (4, 3, 128, 128) and batch.sources.shape == (4, 2, 3, 128, 128)
    assert batch.poses.shape == (4, 2, 4, 4) and batch.mask.shape == (4, 1, 128, 128)
    assert batch.image_aug.shape == batch.image.shape
    assert batch.distance is None  # nothing scores the train split: no ground truth is read for it
    val = next(iter(dm.val_dataloader()))
    assert val.distance.shape[1:] == (1, 128, 128) and val.distance_source == ["rendered"] * len(val)
    assert all(c.width == 128 for c in batch.camera)
    assert len(dm.dataset("train")) == 2 * (12 - 2 * 3 - 2)  # both cameras, minus frames without neighbours
    assert dm.dataset("train").dropped["no neighbour"] == 4
    cams = {dm.dataset("val").items[i].camera for i in range(len(dm.dataset("val")))}
    assert cams == {"image_02", "image_03"}
    assert (cache / "resized" / "128x128").is_dir()
    for key in ("image", "sources", "poses", "mask", "image_aug"):
        assert torch.isfinite(getattr(batch, key)).all()
    assert torch.isfinite(val.distance).all()


def test_base_focal_auto_is_the_mean_focal_of_the_training_cameras_at_the_training_size(kitti_data, cache):
    native = [
        min(load_camera(kitti_data / "calibration" / f"{c}.yaml").paraxial_focal())
        for c in ("image_02", "image_03")
    ]
    dm = FisheyeDataModule(kitti_data, size=(128, 128), cache_dir=cache)
    assert dm.base_focal("train") == pytest.approx(sum(native) / 2 / 2, rel=1e-9)  # 256 -> 128 px halves it
    one = FisheyeDataModule(kitti_data, size=(64, 64), cameras=["image_03"], cache_dir=cache)
    assert one.base_focal("train") == pytest.approx(native[1] / 4, rel=1e-9)
    first_frame = [{"sequence": TRAIN_SEQ, "start": 0, "stop": 1}]  # no previous frame: no sample
    empty = FisheyeDataModule(kitti_data, splits={"train": first_frame}, cache_dir=cache)
    with pytest.raises(ValueError, match="'train' split has no samples, so no base focal"):
        empty.base_focal("train")


@pytest.fixture(scope="module")
def surround4(tmp_path_factory):
    """A surround4 world (9 frames at 64 px, no LiDAR), rendered once for the tests that only read it."""
    from fisheyedepth.synthetic import WorldSpec, generate

    out = tmp_path_factory.mktemp("s4") / "s4"
    return generate(out, WorldSpec("surround4", frames=9, size=64, seed=2), lidar=False, progress=False)


def test_mixed_cameras_and_models_in_one_batch(surround4, cache):
    root = surround4
    dm = FisheyeDataModule(
        root, size=(64, 64), batch_size=8, splits={"train": "splits/train.txt"}, cache_dir=cache
    )
    batch = next(iter(dm.train_dataloader()))
    models = {type(c).__name__ for c in batch.camera}
    assert models == {"MeiCamera", "KannalaBrandtCamera"}
    focals = {c: min(dm.layout.cameras[c].camera.paraxial_focal()) for c in dm.layout.cameras}
    assert len(focals) == 4 and max(focals.values()) / min(focals.values()) > 1.05  # the cameras differ
    base = dm.base_focal("train")
    assert base == pytest.approx(sum(focals.values()) / 4, rel=1e-9)
    module = bare_module(net={"scales": (0,), "base_focal": base})
    scale = module.depth_net.depth_scale(batch.camera)
    assert torch.allclose(scale, torch.tensor([min(c.paraxial_focal()) / base for c in batch.camera]))
    loss, _ = module.objective(batch, module(batch.image, batch.camera))
    assert torch.isfinite(loss)


def test_rig_sources_are_the_other_cameras_warped_with_extrinsics_and_odometry(surround4, cache):
    root = surround4
    layout = Kitti360Layout(root)
    names = sorted(layout.cameras)
    ds = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], rig_offsets=(0,), cache_dir=cache)
    poses = read_poses(root / "data_poses" / TRAIN_SEQ / "poses.txt")
    E = read_cam_to_pose(root / "calibration" / "calib_cam_to_pose.txt")
    frames = sorted(poses)
    assert len(ds) == 4 * (3 - 2) and ds.dropped["no neighbour"] == 4 * 2  # rig sources drop no frame here
    better = []
    for i in range(len(ds)):  # every camera once as the target
        item, s = ds.items[i], ds[i]
        others = [n for n in names if n != item.camera]
        assert s["sources"].shape == (2 + 3, 3, 64, 64) and s["source_mask"].shape == (5, 1, 64, 64)
        assert s["source_camera"][:2] == [s["camera"]] * 2  # the temporal sources: the target's camera
        for j, other in enumerate(others, start=2):
            assert s["source_camera"][j] == layout.cameras[other].camera
            assert torch.equal(
                s["sources"][j],
                ds._image(
                    layout.image(TRAIN_SEQ, other, layout.frames(TRAIN_SEQ, other)[item.row]),
                    s["source_camera"][j],
                    layout.cameras[other].camera,
                ),
            )
            t = poses[frames[item.row]]
            expected = np.linalg.inv(E[other]) @ np.linalg.inv(t) @ t @ E[item.camera]  # same instant
            assert np.allclose(s["poses"][j].numpy(), expected, atol=1e-5)
            error, coverage = warp_l1(s, j)
            if coverage > 0.1:  # the two cameras see the same part of the world: GT explains it best
                better.append((error, warp_l1(s, j, scale=0.7)[0], warp_l1(s, j, scale=1.4)[0]))
        for j in range(2):  # the temporal sources are unchanged
            assert warp_l1(s, j)[0] < 0.03
        flipped = flip_sample(s)
        for j in range(5):
            a, b = warp_l1(s, j), warp_l1(flipped, j)
            assert b[1] == pytest.approx(a[1], abs=0.02) and b[0] == pytest.approx(a[0], rel=0.05, abs=2e-3)
    assert len(better) >= 5  # of 12 camera pairs at 64 px (measured: 6, covering 13-31% of the target)
    assert all(gt < min(near, far) and gt < 0.035 for gt, near, far in better)  # 0.014-0.030 at GT


def test_the_stereo_rig_overlaps_and_its_other_camera_is_a_source(tmp_path, cache):
    """The stereo rig: two fisheyes 0.2 m apart, axes 40 degrees apart (on the car; hand-held 0.25 m),
    whose views overlap: the other camera, warped with the ground truth, explains the target better than
    at 0.7x or 1.4x the distance, over much of the image."""
    from fisheyedepth.synthetic import WorldSpec, generate, make_rig

    for scene, baseline in (("street", 0.2), ("indoor", 0.255)):
        rig = make_rig("stereo", 64, scene)
        a, b = rig.cam_to_pose["image_02"], rig.cam_to_pose["image_03"]
        assert np.linalg.norm(a[:3, 3] - b[:3, 3]) == pytest.approx(baseline, abs=0.001)
        assert math.degrees(math.acos(a[:3, 2] @ b[:3, 2])) == pytest.approx(40.0)
    spec = WorldSpec("stereo", frames=9, size=64, seed=2)
    root = generate(tmp_path / "stereo", spec, lidar=False, progress=False)
    ds = FisheyeDataset(Kitti360Layout(root), [{"sequence": TRAIN_SEQ}], rig_offsets=(0,), cache_dir=cache)
    assert len(ds) == 2  # each camera once as the target, the other one its rig source
    for i in range(len(ds)):
        s = ds[i]
        error, coverage = warp_l1(s, 2)
        assert coverage > 0.4, coverage
        assert error < 0.025 and error < min(warp_l1(s, 2, 0.7)[0], warp_l1(s, 2, 1.4)[0]), error


def test_rig_sources_train_the_full_model_and_a_posenet_row_refuses_them(surround4, cache):
    root = surround4
    dm = FisheyeDataModule(
        root,
        size=(64, 64),
        batch_size=4,
        splits={"train": "splits/train.txt"},
        cache_dir=cache,
        rig_offsets=(0,),
    )
    batch = next(iter(dm.train_dataloader()))
    assert batch.sources.shape == (4, 5, 3, 64, 64) and batch.source_mask.shape == (4, 5, 1, 64, 64)
    assert {type(c).__name__ for cams in batch.source_camera for c in cams} == {
        "MeiCamera",
        "KannalaBrandtCamera",
    }
    module = bare_module(
        net={"scales": (0, 1), "base_focal": dm.base_focal("train")}, objective={"rig_offsets": (0,)}
    )
    loss, _ = module.objective(batch, module(batch.image, batch.camera))
    loss.backward()
    grads = [p.grad for p in module.depth_net.parameters() if p.grad is not None]
    assert torch.isfinite(loss) and grads and all(torch.isfinite(g).all() for g in grads)
    with pytest.raises(ValueError, match="rig_offsets.*real_scale=true"):
        bare_module(objective={"real_scale": False, "rig_offsets": (0,)})


def test_rig_frames_are_paired_by_nearest_timestamp_and_a_missing_one_drops_the_target(
    kitti_data, tmp_path, cache
):
    kitti, stamp = write_rig(kitti_data, tmp_path / "rig")
    folder = tmp_path / "rig" / "drive" / "images" / "image_03"
    keys = sorted(stamp.values())
    for k in keys:  # image_03 is triggered 3 ms after image_02 (its own poses: interpolated)
        (folder / f"{k}.png").rename(folder / f"{k + 3_000_000}.png")
    (folder / f"{keys[2] + 3_000_000}.png").unlink()  # and drops one frame
    rig = RigLayout(tmp_path / "rig")
    ds = FisheyeDataset(rig, [{"sequence": "drive"}], size=(64, 64), rig_offsets=(0,), cache_dir=cache)
    assert ds.rig_frame("drive", "image_03", keys[1]) == 1
    assert ds.rig_frame("drive", "image_03", keys[2]) is None  # 97 ms from the nearest: no partner
    assert ds.rig_frame("drive", "image_03", keys[3]) == 2  # the row after the gap
    assert ds.rig_frame("drive", "image_02", keys[3] + 3_000_000) == 3
    plain = FisheyeDataset(rig, [{"sequence": "drive"}], size=(64, 64), cache_dir=cache)
    targets = {(i.camera, i.row) for i in ds.items}
    assert ("image_02", 2) not in targets and ("image_02", 1) in targets
    assert len(ds) == len(plain) - 1 and ds.dropped["no neighbour"] == plain.dropped["no neighbour"] + 1
    s = ds[[i for i, it in enumerate(ds.items) if (it.camera, it.row) == ("image_02", 1)][0]]
    assert s["source_camera"][2] == rig.cameras["image_03"].camera.resize(64, 64)
    target, partner = rig.frames("drive", "image_02")[1], rig.frames("drive", "image_03")[1]
    assert partner.key == keys[1] + 3_000_000
    E_t, E_s = (rig.cameras[c].cam_to_body for c in ("image_02", "image_03"))
    expected = np.linalg.inv(E_s) @ np.linalg.inv(partner.pose) @ target.pose @ E_t
    assert np.allclose(s["poses"][2].numpy(), expected, atol=1e-5)
    assert not np.allclose(partner.pose, target.pose)  # the 3 ms later pose is the partner's own


def test_relative_pose_equals_the_files(kitti_data, cache):
    layout = Kitti360Layout(kitti_data)
    ds = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], cache_dir=cache)
    poses = read_poses(kitti_data / "data_poses" / TRAIN_SEQ / "poses.txt")
    E = read_cam_to_pose(kitti_data / "calibration" / "calib_cam_to_pose.txt")
    for i in (0, 3, len(ds) - 1):
        item = ds.items[i]
        frames = sorted(poses)
        t, prev, nxt = frames[item.row], frames[item.row - 1], frames[item.row + 1]
        s = ds[i]
        for j, other in enumerate((prev, nxt)):
            expected = np.linalg.inv(E[item.camera]) @ np.linalg.inv(poses[other]) @ poses[t] @ E[item.camera]
            assert np.allclose(s["poses"][j].numpy(), expected, atol=1e-5)


def test_flip_is_geometrically_consistent(kitti_data, cache):
    ds = FisheyeDataset(
        Kitti360Layout(kitti_data), [{"sequence": TRAIN_SEQ}], size=(128, 128), cache_dir=cache
    )
    for i in (1, 4):
        s = ds[i]
        f = flip_sample(s)
        assert torch.equal(f["image"], s["image"].flip(-1)) and f["camera"] == s["camera"].flip()
        for j in (0, 1):
            original, flipped = photometric_l1(s, j), photometric_l1(f, j)
            assert flipped == pytest.approx(original, rel=0.03, abs=1e-3)
            assert original < 0.03
        # and a wrong flip (image flipped, geometry not) is clearly worse
        wrong = dict(f, poses=s["poses"], camera=s["camera"])
        assert photometric_l1(wrong) > 2 * photometric_l1(f)


def test_colour_jitter_only_on_the_network_input(kitti_data, cache):
    ds = FisheyeDataset(
        Kitti360Layout(kitti_data),
        [{"sequence": TRAIN_SEQ}],
        size=(64, 64),
        augment=Augment(flip=0.0, brightness=0.5),
        cache_dir=cache,
    )
    plain = FisheyeDataset(
        Kitti360Layout(kitti_data), [{"sequence": TRAIN_SEQ}], size=(64, 64), cache_dir=cache
    )
    torch.manual_seed(1)
    s, p = ds[2], plain[2]
    assert torch.equal(s["image"], p["image"]) and torch.equal(s["sources"], p["sources"])
    assert not torch.allclose(s["image_aug"], s["image"])
    assert (s["image_aug"] >= 0).all() and (s["image_aug"] <= 1).all()


def _jitter_step_by_step(images, brightness, contrast, saturation, hue, generator):
    """Monodepth2's colour jitter as a chain of operations (the reference for the one-map version)."""

    def draw(spread):
        return 1.0 + (2 * torch.rand((), generator=generator).item() - 1) * spread

    grey_w = torch.tensor([0.299, 0.587, 0.114], dtype=images.dtype)[:, None, None]
    out = images * draw(brightness)
    mean = (out * grey_w).sum(-3, keepdim=True).mean((-2, -1), keepdim=True)
    out = mean + draw(contrast) * (out - mean)
    grey = (out * grey_w).sum(-3, keepdim=True)
    out = grey + draw(saturation) * (out - grey)
    angle = (2 * torch.rand((), generator=generator).item() - 1) * hue * 2 * math.pi
    y = out[..., 0, :, :] * 0.299 + out[..., 1, :, :] * 0.587 + out[..., 2, :, :] * 0.114
    i = out[..., 0, :, :] * 0.596 - out[..., 1, :, :] * 0.274 - out[..., 2, :, :] * 0.322
    q = out[..., 0, :, :] * 0.211 - out[..., 1, :, :] * 0.523 + out[..., 2, :, :] * 0.312
    i, q = math.cos(angle) * i - math.sin(angle) * q, math.sin(angle) * i + math.cos(angle) * q
    yiq = torch.stack((y, i, q), -3)
    m = torch.tensor(
        [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]], dtype=torch.float64
    )
    out = torch.einsum("ij,...jhw->...ihw", torch.linalg.inv(m).to(images), yiq)
    return out.clamp(0, 1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_colour_jitter_in_one_map_equals_the_chain_of_operations(dtype):
    images = torch.rand(3, 3, 17, 23, generator=torch.Generator().manual_seed(0), dtype=dtype)
    for seed in range(6):
        args = (0.4, 0.4, 0.6, 0.25)
        fast = colour_jitter(images, *args, generator=torch.Generator().manual_seed(seed))
        slow = _jitter_step_by_step(images, *args, generator=torch.Generator().manual_seed(seed))
        assert fast.dtype == dtype and fast.shape == images.shape
        assert torch.allclose(fast, slow, atol=1e-5 if dtype == torch.float32 else 1e-12, rtol=0)
        assert float((fast - images).abs().max()) > 0.02  # it did jitter
    # identity ranges leave the images alone; each image's contrast pivots about its own mean grey
    same = colour_jitter(images, 0.0, 0.0, 0.0, 0.0)
    assert torch.allclose(same, images, atol=1e-6)


def test_worker_seeding_is_deterministic(kitti_data, cache):
    def first_batch():
        dm = FisheyeDataModule(
            kitti_data,
            size=(64, 64),
            batch_size=4,
            num_workers=2,
            augment=Augment(),
            cache_dir=cache,
            seed=7,
            splits={"train": "splits/train.txt"},
        )
        return next(iter(dm.train_dataloader()))

    a, b = first_batch(), first_batch()
    assert a.camera == b.camera  # the same flips (a flip mirrors the principal point)
    assert torch.equal(a.image_aug, b.image_aug)


def test_translation_bounds_drop_samples(kitti_data, cache):
    layout = Kitti360Layout(kitti_data)
    none = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], min_translation=5.0, cache_dir=cache)
    assert len(none) == 0 and none.dropped["below min_translation"] == 2 * 4
    jumpy = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], max_translation=0.1, cache_dir=cache)
    assert len(jumpy) == 0 and jumpy.dropped["above max_translation"] == 2 * 4


def test_baseline_rows_pick_the_frame_nearest_the_wanted_distance_on_each_side():
    from fisheyedepth.data.dataset import baseline_rows

    # a drive along x: 1.4 m per frame, then 0.4 m per frame from frame 4 on
    x = np.concatenate([np.arange(5) * 1.4, 5.6 + np.arange(1, 10) * 0.4])
    positions = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    # fast stretch: one frame back is 1.4 m (nearer 1.8 than 2.8); forward at frame 2: 1.4 then 2.8
    assert baseline_rows(positions, 2, (-2, 2), 1.8) == [1, 3]
    # slow stretch (frame 8, at 7.2 m): back 1.6 m at frame 4 ... forward 1.6 m four frames on (1.2 at
    # three, 2.0 at five: 1.6 is the nearest to 1.8)
    assert baseline_rows(positions, 8, (-2, 2), 1.8) == [4, 12]
    # offsets of two sizes share the baseline in proportion: +-1 wants 0.9 m, +-2 wants 1.8 m
    assert baseline_rows(positions, 8, (-2, -1, 1, 2), 1.8) == [4, 6, 10, 12]
    # a tie keeps the nearer frame: at frame 10 (8.0 m) forward 0.4, 0.8, 1.2: want 1.0 -> 0.8 or 1.2
    assert baseline_rows(positions, 10, (1,), 1.0) == [12]
    # the sequence ends before the distance is passed: no neighbour
    assert baseline_rows(positions, 11, (2,), 1.8) is None
    assert baseline_rows(positions, 0, (-2, 2), 1.8) is None
    # a stop with jittering poses (1 cm) does not end the search: the source is where the car got to
    stop = np.concatenate([np.zeros(6), 0.01 * (-1.0) ** np.arange(6), np.arange(1, 6) * 0.5])
    jitter = np.stack([stop, np.zeros_like(stop), np.zeros_like(stop)], 1)
    assert baseline_rows(jitter, 0, (1,), 1.67) == [14]  # 1.5 m (nearer 1.67 than 2.0)
    # nor does a turn back (distances that fall again before they reach the baseline)
    back = np.array([[0, 0, 0], [0.6, 0, 0], [0.9, 0, 0], [0.5, 0, 0], [1.2, 0, 0], [1.9, 0, 0]], dtype=float)
    assert baseline_rows(back, 0, (1,), 1.67) == [5]


def test_source_baseline_loads_the_chosen_frames_with_their_poses(kitti_data, cache):
    layout = Kitti360Layout(kitti_data)
    fixed = FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], offsets=(-1, 1), cache_dir=cache)
    frames = layout.frames(TRAIN_SEQ, "image_02")
    positions = np.stack([f.pose[:3, 3] for f in frames])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    want = float(np.median(steps)) * 2  # about two frames' travel: the sources move out to +-2
    ds = FisheyeDataset(
        layout, [{"sequence": TRAIN_SEQ}], offsets=(-1, 1), source_baseline=want, cache_dir=cache
    )
    assert len(ds) > 0
    moved = False
    for item in ds.items:
        back, ahead = item.sources
        assert back < item.row < ahead
        for source in (back, ahead):  # no other frame on that side is nearer the wanted distance
            gap = abs(np.linalg.norm(positions[source] - positions[item.row]) - want)
            side = range(0, item.row) if source < item.row else range(item.row + 1, len(frames))
            assert all(
                gap <= abs(np.linalg.norm(positions[k] - positions[item.row]) - want) + 1e-9 for k in side
            )
        moved |= (back, ahead) != (item.row - 1, item.row + 1)
    assert moved  # the baseline chose other frames than the offsets' neighbours
    assert all(it.sources == (it.row - 1, it.row + 1) for it in fixed.items)
    item = ds.items[0]
    sample = ds[0]
    E = read_cam_to_pose(kitti_data / "calibration" / "calib_cam_to_pose.txt")[item.camera]
    for j, source in enumerate(item.sources):
        expected = np.linalg.inv(E) @ np.linalg.inv(frames[source].pose) @ frames[item.row].pose @ E
        assert np.allclose(sample["poses"][j].numpy(), expected, atol=1e-5)
    with pytest.raises(ValueError, match="source_baseline: -1.0"):
        FisheyeDataset(layout, [{"sequence": TRAIN_SEQ}], source_baseline=-1.0, cache_dir=cache)
    with pytest.raises(ValueError, match="needs offsets with a direction"):
        FisheyeDataset(
            layout, [{"sequence": TRAIN_SEQ}], offsets=(0, 1), source_baseline=1.0, cache_dir=cache
        )


def test_lidar_ground_truth(kitti_data, cache):
    layout = Kitti360Layout(kitti_data)
    gt = LidarGroundTruth(layout, cache, occlusion=0.1)
    cam = layout.cameras["image_02"].camera
    frame = layout.frames(TRAIN_SEQ)[3]
    d, z = gt(TRAIN_SEQ, "image_02", cam, frame)
    files = list((cache / "lidar" / TRAIN_SEQ).rglob("*.npz"))
    assert [f.name.split("_")[0] for f in files] == [f"{frame.key:010d}"]  # this frame only, lazily
    rendered = np.load(layout.distance(TRAIN_SEQ, "image_02", frame))
    both = (d > 0) & (rendered > 0)
    assert both.sum() > 500
    assert np.median(np.abs(d[both] - rendered[both]) / rendered[both]) < 0.01
    rays, valid = RayCache().get(cam)
    has = (d > 0) & valid.numpy()
    assert has.sum() > 0.99 * (d > 0).sum()
    # z / distance is the cosine of incidence: that of the pixel's ray, up to the point's sub-pixel offset
    assert np.abs(z[has] / d[has] - rays[..., 2].numpy()[has]).max() < 0.03
    assert (z[has] < 0).sum() > 0  # points beyond 90 degrees of incidence are kept
    # the filter applied on reading is the projection's own
    T = layout.velo_to_camera("image_02")
    direct = project_points(read_velodyne(layout.lidar(TRAIN_SEQ, frame)), T, cam, occlusion=0.1)
    assert np.array_equal(direct[0], d) and np.array_equal(direct[1], z)
    unfiltered, _ = LidarGroundTruth(layout, cache, occlusion=None)(TRAIN_SEQ, "image_02", cam, frame)
    assert (unfiltered > 0).sum() > (d > 0).sum() and np.array_equal(unfiltered[d > 0], d[d > 0])
    assert len(list((cache / "lidar").rglob("*.npz"))) == 1  # one cache file serves both


def test_lidar_cache_is_keyed_by_calibration_and_scan(kitti_data, tmp_path, monkeypatch, caplog):
    data = tmp_path / "data"
    shutil.copytree(kitti_data, data)
    layout, cache = Kitti360Layout(data), tmp_path / "cache"
    cam = layout.cameras["image_02"].camera
    frame = layout.frames(TRAIN_SEQ)[2]
    first = LidarGroundTruth(layout, cache)(TRAIN_SEQ, "image_02", cam, frame)

    def refuse(*args):
        raise AssertionError("projected again")

    monkeypatch.setattr(LidarGroundTruth, "project", refuse)
    again = LidarGroundTruth(layout, cache)(TRAIN_SEQ, "image_02", cam, frame)  # a new process: the disk
    assert np.array_equal(again[0], first[0])
    monkeypatch.undo()
    small = cam.resize(128, 128)  # another calibration: its own entry, projected at its size
    d_small, _ = LidarGroundTruth(layout, cache)(TRAIN_SEQ, "image_02", small, frame)
    assert d_small.shape == (128, 128) and len(list(cache.rglob("*.npz"))) == 2
    scan = layout.lidar(TRAIN_SEQ, frame)
    points = read_velodyne(scan)
    points[:, :3] *= 2.0  # the scan is replaced (points twice as far from the scanner): never stale
    scan.write_bytes(points.astype(np.float32).tobytes())
    doubled, _ = LidarGroundTruth(layout, cache, occlusion=None)(TRAIN_SEQ, "image_02", cam, frame)
    expected, _ = project_points(points, layout.velo_to_camera("image_02"), cam)
    assert np.array_equal(doubled, expected) and np.median(doubled[doubled > 0]) > 1.5 * np.median(
        first[0][first[0] > 0]
    )
    newest = max(cache.rglob("*.npz"), key=lambda p: p.stat().st_mtime_ns)
    newest.write_bytes(b"not a zip")  # a corrupt cache file is rebuilt, with a word
    with caplog.at_level("WARNING"):
        rebuilt, _ = LidarGroundTruth(layout, cache, occlusion=None)(TRAIN_SEQ, "image_02", cam, frame)
    assert np.array_equal(rebuilt, doubled) and f"{newest}: unreadable LiDAR cache" in caplog.text


def test_building_a_lidar_dataset_projects_nothing_and_train_reads_no_ground_truth(
    kitti_data, cache, monkeypatch
):
    def refuse(*args):
        raise AssertionError("LiDAR projected")

    monkeypatch.setattr(LidarGroundTruth, "project", refuse)
    dm = FisheyeDataModule(kitti_data, ground_truth="lidar", cache_dir=cache, size=(64, 64))
    dm.setup("fit")
    dm.setup("test")
    assert dm.dataset("train").lidar is None and dm.dataset("test").lidar is not None
    assert "distance" not in dm.dataset("train")[0]  # training reads no scan
    with pytest.raises(AssertionError, match="LiDAR projected"):
        dm.dataset("test")[0]  # the first read of a scored frame projects it
    monkeypatch.undo()
    sample = dm.dataset("test")[0]
    assert sample["distance_source"] == "lidar_filtered"  # validation's default: the occlusion filter
    assert 0 < (sample["distance"] > 0).float().mean() < 0.3
    item = dm.dataset("test").items[0]
    scan = dm.layout.lidar(item.sequence, dm.layout.frames(item.sequence)[item.row])
    scan.rename(scan.with_suffix(".moved"))
    try:
        with pytest.raises(FileNotFoundError, match=f"{scan}: no Velodyne scan"):
            dm.dataset("test")[0]
    finally:
        scan.with_suffix(".moved").rename(scan)


def write_rig(src, dst, keep_every=1, early_images=0):
    """Re-express a synthetic KITTI-layout dataset as a robot-rig recording (timestamps in ns); keep every
    ``keep_every``-th pose only, and add ``early_images`` images before the first pose."""
    layout = Kitti360Layout(src)
    frames = layout.frames(TRAIN_SEQ)
    stamp = {f.key: 10_000_000_000 + 100_000_000 * f.key for f in frames}
    cams = []
    (dst / "masks").mkdir(parents=True)
    for name, spec in layout.cameras.items():
        folder = dst / "drive" / "images" / name
        folder.mkdir(parents=True)
        for f in frames:
            shutil.copy(layout.image(TRAIN_SEQ, name, f), folder / f"{stamp[f.key]}.png")
        for k in range(early_images):
            shutil.copy(
                layout.image(TRAIN_SEQ, name, frames[0]),
                folder / f"{stamp[frames[0].key] - 10**9 * (k + 1)}.png",
            )
        shutil.copy(spec.mask, dst / "masks" / f"{name}.png")
        cams.append(
            {
                "name": name,
                "model": spec.camera.to_dict(),
                "cam_to_body": spec.cam_to_body[:3].tolist(),
                "mask": f"masks/{name}.png",
            }
        )
    (dst / "rig.yaml").write_text(yaml.safe_dump({"cameras": cams}))
    kept = frames[::keep_every] if frames[-1] in frames[::keep_every] else [*frames[::keep_every], frames[-1]]
    rows = []
    for f in kept:
        q = quaternion_xyzw(f.pose[:3, :3])
        rows.append(" ".join(str(v) for v in [stamp[f.key], *f.pose[:3, 3], *q]))
    (dst / "drive" / "poses.txt").write_text("# timestamp_ns tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")
    return layout, stamp


def test_rig_layout_reads_a_robot_recording(kitti_data, tmp_path, cache):
    kitti, stamp = write_rig(kitti_data, tmp_path / "rig", early_images=2)
    rig = RigLayout(tmp_path / "rig")
    assert sorted(rig.cameras) == ["image_02", "image_03"] and rig.sequences() == ["drive"]
    frames = rig.frames("drive", "image_02")
    assert len(frames) == len(kitti.frames(TRAIN_SEQ))  # the two early images are reported, not invented
    assert len(rig.outside[("drive", "image_02")]) == 2
    for f_rig, f_kitti in zip(frames, kitti.frames(TRAIN_SEQ), strict=True):
        assert np.allclose(f_rig.pose, f_kitti.pose, atol=1e-6)
    ds_rig = FisheyeDataset(rig, [{"sequence": "drive"}], size=(64, 64), cache_dir=cache)
    ds_kitti = FisheyeDataset(kitti, [{"sequence": TRAIN_SEQ}], size=(64, 64), cache_dir=cache)
    a, b = ds_rig[2], ds_kitti[2]
    assert a["camera"] == b["camera"] and torch.equal(a["image"], b["image"])
    assert torch.equal(a["mask"], b["mask"]) and torch.allclose(a["poses"], b["poses"], atol=1e-5)


def test_rig_poses_are_interpolated_with_slerp(kitti_data, tmp_path):
    kitti, _ = write_rig(kitti_data, tmp_path / "rig", keep_every=2)
    rig = RigLayout(tmp_path / "rig")
    errors_t, errors_r = [], []
    for f_rig, f_kitti in zip(rig.frames("drive", "image_02"), kitti.frames(TRAIN_SEQ), strict=True):
        errors_t.append(np.linalg.norm(f_rig.pose[:3, 3] - f_kitti.pose[:3, 3]))
        R = f_rig.pose[:3, :3].T @ f_kitti.pose[:3, :3]
        errors_r.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
        assert np.allclose(f_rig.pose[:3, :3] @ f_rig.pose[:3, :3].T, np.eye(3), atol=1e-9)
    assert max(errors_t) < 0.05 and max(errors_r) < 0.5  # a smooth drive: halfway poses are close
    assert max(errors_t) > 0  # and they really were interpolated


def test_bad_rig_description_names_file_and_key(kitti_data, tmp_path):
    write_rig(kitti_data, tmp_path / "rig")
    rig_yaml = tmp_path / "rig" / "rig.yaml"
    data = yaml.safe_load(rig_yaml.read_text())
    del data["cameras"][1]["cam_to_body"]
    rig_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=r"rig.yaml: key 'cameras\[1\].cam_to_body'"):
        RigLayout(tmp_path / "rig")
    data["cameras"][1]["cam_to_body"] = [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]
    rig_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match="not a rigid transform"):
        RigLayout(tmp_path / "rig")
    data["cameras"][1]["cam_to_body"] = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0.5, 1]]
    rig_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=r"cameras\[1\].cam_to_body'.*last row .* must be 0 0 0 1"):
        RigLayout(tmp_path / "rig")
    data["cameras"][1]["cam_to_body"] = {"translation": [1, 2, 3], "quaternion_xyzw": [0, 0, 0, 2]}
    rig_yaml.write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError, match=r"cameras\[1\].cam_to_body.quaternion_xyzw'.*norm 2; .*unit"):
        RigLayout(tmp_path / "rig")  # a norm of 2 is a column gone wrong, never normalised silently
    data["cameras"][1]["cam_to_body"] = {"translation": [1, 2, 3], "quaternion_xyzw": [0, 0, 0, 1.0005]}
    rig_yaml.write_text(yaml.safe_dump(data))
    name = data["cameras"][1]["name"]
    assert np.allclose(RigLayout(tmp_path / "rig").cameras[name].cam_to_body[:3, 3], (1, 2, 3))


@pytest.fixture
def broken(kitti_data, tmp_path):
    root = tmp_path / "broken"
    shutil.copytree(kitti_data, root, ignore=shutil.ignore_patterns("data_3d_raw"))
    return root


def image_path(root, frame, cam="image_02"):
    return root / "data_2d_raw" / TRAIN_SEQ / cam / "data_rgb" / f"{frame:010d}.png"


@pytest.mark.parametrize("damage", ["missing", "corrupt", "wrong_size"])
def test_bad_images_name_the_file_or_are_skipped_and_counted(broken, cache, damage):
    path = image_path(broken, 3)
    if damage == "missing":
        path.unlink()
    elif damage == "corrupt":
        path.write_bytes(b"\x89PNG not really")
    else:
        cv2.imwrite(str(path), np.zeros((100, 120, 3), np.uint8))
    for size in (None, (64, 64)):
        ds = FisheyeDataset(Kitti360Layout(broken), [{"sequence": TRAIN_SEQ}], size=size, cache_dir=cache)
        with pytest.raises((FileNotFoundError, ValueError), match=str(path)):
            [ds[i] for i in range(len(ds))]
    ds = FisheyeDataset(
        Kitti360Layout(broken),
        [{"sequence": TRAIN_SEQ}],
        size=(64, 64),
        skip_bad_frames=True,
        cache_dir=cache,
    )
    batch = collate([ds[i] for i in range(len(ds))])
    # frame 3 is the target of one sample and a neighbour of two others, for the damaged camera
    assert len(batch.skipped_frames) == 3 and all(str(path) in r for r in batch.skipped_frames)
    assert batch.image.shape[0] == len(ds) - 3 and torch.isfinite(batch.image).all()
    module = bare_module(net={"scales": (0,)})
    module._count_skipped(batch)
    with pytest.warns(UserWarning, match="3 frames skipped"):
        module.on_train_epoch_end()


def test_missing_calibration_and_poses_name_the_file(broken, cache):
    (broken / "calibration" / "image_03.yaml").unlink()
    with pytest.raises(FileNotFoundError, match="image_03.yaml"):
        Kitti360Layout(broken, cameras=["image_02", "image_03"])
    with pytest.raises(FileNotFoundError, match="image_03.yaml"):  # discovery: its images are there
        Kitti360Layout(broken)
    for folder in (broken / "data_2d_raw").glob("*/image_03"):
        shutil.rmtree(folder)
    assert list(Kitti360Layout(broken).cameras) == ["image_02"]  # no yaml and no images: not a camera
    (broken / "splits" / "odd.txt").write_text(f"{TRAIN_SEQ} 3\n{TRAIN_SEQ} 999\n")
    with pytest.raises(KeyError, match="no pose for frame"):
        FisheyeDataset(Kitti360Layout(broken), "splits/odd.txt", cache_dir=cache)
    ds = FisheyeDataset(Kitti360Layout(broken), "splits/odd.txt", skip_bad_frames=True, cache_dir=cache)
    assert ds.dropped["no pose"] == 1 and len(ds) == 1
    (broken / "data_poses" / TRAIN_SEQ / "poses.txt").unlink()
    with pytest.raises(FileNotFoundError, match="poses.txt"):
        FisheyeDataset(Kitti360Layout(broken), [{"sequence": TRAIN_SEQ}], cache_dir=cache)


def test_image_cache_is_keyed_by_content_and_size(kitti_data, tmp_path):
    src = tmp_path / "img.png"
    shutil.copy(image_path(kitti_data, 2), src)
    cache = ImageCache(tmp_path / "c")
    a = cache.read(src, (64, 64), (256, 256))
    files = list((tmp_path / "c" / "resized" / "64x64").glob("*.png"))
    assert len(files) == 1 and a.shape == (64, 64, 3)
    assert np.array_equal(cache.read(src, (64, 64), (256, 256)), a)
    cv2.imwrite(str(src), np.zeros((256, 256, 3), np.uint8))
    assert cache.read(src, (64, 64), (256, 256)).max() == 0  # a changed source is not served stale
    with pytest.raises(ValueError, match="calibration says 300x300"):
        cache.read(src, (64, 64), (300, 300))


def test_real_kitti360_frame_loads(realdata):
    root = realdata / "kitti360_frame"
    cam = load_camera(root / "image_02.yaml")
    lidar = cv2.imread(str(root / "image_02_lidar_distance.png"), cv2.IMREAD_UNCHANGED)
    mask = cv2.imread(str(root / "image_02_body_mask.png"), cv2.IMREAD_GRAYSCALE)
    assert lidar.shape == mask.shape == (cam.height, cam.width)
    rays, valid = RayCache().get(cam)
    body = mask == 0
    assert 0.15 < body.mean() < 0.35
    assert body[-50:].mean() > 0.9 and body[:600].mean() == 0  # the car is at the bottom
    # the LiDAR returns avoid the body and lie on pixels that have a ray
    has = lidar > 0
    assert (has & body).sum() < 0.01 * has.sum() and valid.numpy()[has].all()


def test_collate_builds_a_typed_batch_with_every_optional_part_resolved(kitti_data):
    """A sample without the optional keys gets them in the batch: the network's inputs are the frames
    themselves, the sources share the target's mask and camera; unknown or missing keys are refused."""
    from fisheyedepth.data import Batch, SkippedBatch

    from conftest import tiny_samples

    samples = tiny_samples(kitti_data, frames=(2,), cameras=("image_02", "image_03"))
    bare = [
        {k: v for k, v in s.items() if k in ("image", "sources", "poses", "mask", "camera")} for s in samples
    ]
    batch = collate(bare)
    assert isinstance(batch, Batch) and len(batch) == 2 and batch.n_sources == 2
    assert batch.image_aug is batch.image and batch.sources_aug is batch.sources
    assert batch.source_mask.shape == (2, 2, 1, 64, 64) and torch.equal(batch.source_mask[:, 1], batch.mask)
    assert batch.source_camera == [[c, c] for c in batch.camera] and batch.camera[0] != batch.camera[1]
    assert batch.cam_to_body is None and batch.distance is None and batch.skipped_frames == []
    assert batch.camera_name is None
    full = collate(samples)
    assert full.cam_to_body.shape == (2, 4, 4) and full.distance.shape == (2, 1, 64, 64)
    assert full.camera_name == ["image_02", "image_03"]
    assert full.poses.dtype == torch.float32
    moved = full.to("cpu")
    assert moved.camera is full.camera and torch.equal(moved.image, full.image)
    with pytest.raises(ValueError, match="does not know: flipped"):
        collate([{**s, "flipped": torch.tensor(True)} for s in samples])
    with pytest.raises(ValueError, match="sample 0 lacks poses"):
        collate([{k: v for k, v in s.items() if k != "poses"} for s in samples])
    skipped = collate([{"skipped": "a: truncated"}])
    assert (
        isinstance(skipped, SkippedBatch) and skipped.skipped_frames == ["a: truncated"] and len(skipped) == 0
    )


def test_a_kitti360_camera_without_a_body_mask_is_warned_once_by_name(kitti_data, tmp_path, caplog):
    """KITTI-360 ships no body masks: the layout says which camera has none and which file it expected,
    once per file and process, and treats every pixel as usable."""
    import logging

    from fisheyedepth.data import Kitti360Layout

    root = tmp_path / "k"
    shutil.copytree(kitti_data / "calibration", root / "calibration")
    (root / "calibration" / "body_mask_image_03.png").unlink()
    with caplog.at_level(logging.WARNING, logger="fisheyedepth.data.kitti360.layout"):
        layout = Kitti360Layout(root, ["image_02", "image_03"])
        Kitti360Layout(root, ["image_02", "image_03"])
    warnings = [r.getMessage() for r in caplog.records if "no body mask" in r.getMessage()]
    expected = root / "calibration" / "body_mask_image_03.png"
    assert warnings == [
        f"camera image_03 has no body mask (expected {expected}): every pixel counts as usable, the "
        "vehicle's body included; estimate it from a recording (fisheyedepth-estimate-mask --root ROOT "
        "--sequence SEQ --camera image_03), write that PNG yourself (255 = usable) or pass "
        "data.datamodule.masks={image_03: FILE}"
    ]
    caplog.clear()
    (root / "calibration" / "body_mask_image_02.png").unlink()
    with caplog.at_level(logging.WARNING, logger="fisheyedepth.data.kitti360.layout"):
        Kitti360Layout(root, ["image_02"], expect_masks=False)  # the mask command, about to write it
        Kitti360Layout(root, ["image_02"])
    assert [r.getMessage()[:36] for r in caplog.records] == ["camera image_02 has no body mask (ex"]
    assert layout.cameras["image_03"].mask is None and layout.cameras["image_02"].mask is not None
