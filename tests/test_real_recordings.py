"""Real fisheye data (../shared/realdata, or FISHEYEDEPTH_REALDATA): skipped when absent."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import KannalaBrandtCamera, RayCache, load_camera
from fisheyedepth.geometry import make_pose, quaternion_to_matrix, relative_pose, sample, warp_to_source

from conftest import bare_module

cv2 = pytest.importorskip("cv2")
D64 = torch.float64


def fit_plane_ransac(X: torch.Tensor, threshold: float = 0.05, iters: int = 1000, seed: int = 0):
    """RANSAC plane n . X + d = 0 (|n| = 1), refined by least squares on the inliers."""
    g = torch.Generator().manual_seed(seed)
    best = None
    for _ in range(iters):
        p = X[torch.randint(0, len(X), (3,), generator=g)]
        n = torch.linalg.cross(p[1] - p[0], p[2] - p[0])
        if n.norm() < 1e-9:
            continue
        n = n / n.norm()
        inliers = (X @ n - n @ p[0]).abs() < threshold
        if best is None or inliers.sum() > best.sum():
            best = inliers
    P = X[best]
    centre = P.mean(0)
    n = torch.linalg.svd(P - centre).Vh[-1]
    return n, -(n @ centre), best


def test_kitti360_lidar_ground_plane(realdata):
    """Backprojected LiDAR distances put the ground about 1.8 m below image_02, normal ~ (0, -1, 0)."""
    root = realdata / "kitti360_frame"
    cam = load_camera(root / "image_02.yaml")
    distance = (
        cv2.imread(str(root / "image_02_lidar_distance.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 256
    )
    assert distance.shape == (cam.height, cam.width)
    rays, valid = RayCache().get(cam, dtype=D64)
    L = torch.from_numpy(distance)
    has = (L > 0) & valid
    assert has.sum() > 40_000
    X = (rays * L[..., None])[has]
    n, d, inliers = fit_plane_ransac(X)
    if n[1] > 0:  # orient the normal upwards (camera y points down)
        n, d = -n, -d
    angle = math.degrees(math.acos(min(1.0, -n[1].item())))
    assert angle < 5.0
    assert 1.7 < d.item() < 1.95  # height of the camera above the ground plane
    assert inliers.float().mean() > 0.2


def aria(realdata):
    root = realdata / "adt_slam"
    meta = json.loads((root / "adt_sample.json").read_text())
    fits = json.loads((root / "fitted_models.json").read_text())

    def camera(name):
        fx, fy, cx, cy, k1, k2, k3, k4 = fits[name]["KB4_opencv_fisheye"]["params"]
        w, h = meta["cameras"][name]["image_size"]
        return KannalaBrandtCamera(width=w, height=h, fx=fx, fy=fy, cx=cx, cy=cy, k1=k1, k2=k2, k3=k3, k4=k4)

    def frame(prefix):
        (path,) = sorted(root.glob(f"{prefix}_*.png"))
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED), int(path.stem.rsplit("_", 1)[1])

    def body_pose(t_ns):
        p = min(meta["poses_T_world_device"], key=lambda p: abs(p["t_us"] * 1000 - t_ns))
        return make_pose(
            quaternion_to_matrix(torch.tensor(p["q_xyzw"], dtype=D64)), torch.tensor(p["t"], dtype=D64)
        )

    def extrinsic(name):
        return torch.tensor(meta["cameras"][name]["T_device_camera"], dtype=D64)

    return camera, frame, body_pose, extrinsic


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    return float((a * b).sum() / math.sqrt((a * a).sum() * (b * b).sum()))


def test_aria_slam_left_warped_into_slam_right(realdata):
    """GT z-depth of slam-right frame 0 + GT extrinsics + KB fits: left warps onto right."""
    camera, frame, body_pose, extrinsic = aria(realdata)
    right, left = camera("camera-slam-right"), camera("camera-slam-left")
    img_r, t_r = frame("camera-slam-right_0")
    img_l, t_l = frame("camera-slam-left_0")
    z_mm, _ = frame("depthskel_camera-slam-right_0")
    T = relative_pose(
        body_pose(t_r), body_pose(t_l), extrinsic("camera-slam-right"), extrinsic("camera-slam-left")
    )
    rays, valid = RayCache().get(right, dtype=D64)
    z = torch.from_numpy(z_mm.astype(np.float64) / 1000)
    front = rays[..., 2] > 1e-3
    distance = torch.where((z > 0) & front, z / rays[..., 2].clamp_min(1e-3), torch.zeros_like(z))  # z-depth!
    source = torch.from_numpy(img_l.astype(np.float64))[None, None]
    scores = {}
    for scale in (0.8, 0.9, 1.0, 1.1, 1.25):
        warp = warp_to_source(rays[None], valid[None] & front, scale * distance[None], T[None], left)
        overlap = warp.valid[0].numpy()
        assert overlap.mean() > 0.3
        warped = sample(source, warp.grid)[0, 0].numpy()
        scores[scale] = ncc(warped[overlap], img_r.astype(np.float64)[overlap])
    assert scores[1.0] >= 0.55
    assert max(scores, key=scores.get) == 1.0, scores
    assert scores[1.0] - scores[0.8] > 0.03  # the depth really matters


# ------------------------------------------------------------------ the real four-camera Aria Gen2 rig
ARIA_CAMERAS = ("slam-front-left", "slam-front-right", "slam-side-left", "slam-side-right")


@pytest.fixture(scope="module")
def aria_rig(tmp_path_factory):
    """``realdata/aria_gen2_rig`` converted into the rig layout once (fisheyedepth-import-aria's function)."""
    from fisheyedepth.data.aria import aria_to_rig

    from conftest import realdata_dir

    src = realdata_dir() / "aria_gen2_rig"
    if not src.is_dir():
        pytest.skip(f"real data not found at {src} (set FISHEYEDEPTH_REALDATA)")
    out = tmp_path_factory.mktemp("aria") / "rig"
    summary = aria_to_rig(src, out)
    return src, out, summary


def aria_batch(root, size=128):
    """One target per camera (the middle frame) with its two neighbours, through the rig data module.
    The head-mounted rig moves 1.3 cm per frame, so ``min_translation`` comes down from 3 cm to 5 mm."""
    from fisheyedepth.data import FisheyeDataModule, collate

    dm = FisheyeDataModule(
        root, "rig", {"train": "all"}, size=(size, size), batch_size=4, num_workers=0, augment=None,
        cache_dir=str(root.parent / "cache"), min_translation=0.005,
    )  # fmt: skip
    dataset = dm.dataloader("train").dataset
    assert len(dataset) == 4 * 7  # 9 frames per camera, the first and the last have one neighbour only
    return collate([dataset[i] for i in (3, 10, 17, 24)])


def test_aria_rig_converts_with_each_cameras_own_model_extrinsic_and_poses(aria_rig):
    from fisheyedepth.cameras import Fisheye624Camera
    from fisheyedepth.data.layouts import RigLayout

    src, root, summary = aria_rig
    assert summary["images"] == dict.fromkeys(ARIA_CAMERAS, 9) and summary["poses"] == 237
    layout = RigLayout(root)
    calib = json.loads((src / "calib_slam_fisheye624.json").read_text())
    assert sorted(layout.cameras) == list(ARIA_CAMERAS)
    for name, spec in layout.cameras.items():
        assert spec.camera == Fisheye624Camera.from_aria(src / "calib_slam_fisheye624.json", name)
        assert np.allclose(spec.cam_to_body, np.array(calib[name]["T_device_camera"]), atol=1e-12)
        frames = layout.frames("seq0", name)
        stamps = sorted(int(p.name.split("_")[1].split(".")[0]) for p in (src / name).glob("*.png"))
        assert [f.key for f in frames] == stamps  # every image kept: all inside the pose stream
    # the poses at the image stamps lie on the odometry's path: between the two bracketing rows
    rows = np.loadtxt(src / "vio_high_frequency_T_odometry_device.csv", delimiter=",", skiprows=1)
    times = rows[:, 0] * 1000
    for f in layout.frames("seq0", "slam-side-left"):
        i = int(np.searchsorted(times, f.key)) - 1
        a, b = rows[i, 1:4], rows[i + 1, 1:4]
        u = (f.key - times[i]) / (times[i + 1] - times[i])
        assert np.allclose(f.pose[:3, 3], a + u * (b - a), atol=1e-9)
    with pytest.raises(FileExistsError, match="rig.yaml exists; pass overwrite=True"):
        from fisheyedepth.data.aria import aria_to_rig

        aria_to_rig(src, root)


def test_real_odometry_explains_the_aria_frames_in_every_camera(aria_rig):
    """Warping each camera's neighbour frame into it with the odometry's relative pose and a plausible
    constant distance (2 m, indoors) lowers the photometric error against the identity pose by at
    least a fifth in all four cameras; at 0.5 m the same poses explain the frames worse (the poses'
    translation is metric)."""
    from fisheyedepth.losses.photometric import photometric_error

    batch = aria_batch(aria_rig[1])
    assert batch.camera_name == list(ARIA_CAMERAS)
    assert [c.model_name for c in batch.camera] == ["fisheye624"] * 4
    rays, has_ray = RayCache().batch(batch.camera, batch.image.device, batch.image.dtype)

    def error(distance, poses):
        d = torch.full((4, 1, 128, 128), distance)
        warp = warp_to_source(rays, has_ray, d, poses, batch.camera)
        err = photometric_error(sample(batch.sources[:, 0], warp.grid), batch.image)
        valid = warp.valid & has_ray
        return torch.stack([err[i][valid[i]].mean() for i in range(4)])

    identity = error(2.0, torch.eye(4).expand(4, 4, 4))
    real = error(2.0, batch.poses[:, 0])
    near = error(0.5, batch.poses[:, 0])
    assert bool((real < 0.8 * identity).all()), (real, identity)
    assert bool((near > real).all()), (near, real)


def test_a_short_finetune_on_the_real_rig_lowers_its_photometric_loss(aria_rig):
    """Twenty steps of the full model on one batch of the four real cameras (each with its own
    Fisheye624 model, extrinsic and interpolated poses): the self-supervised loss of the last five
    steps is below that of the first five. Slowly: with 1.3 cm between frames the warp depends little
    on the distance, and a moving hand fills much of the view (3.5-5 %, measured at 1 and 2 threads)."""

    torch.manual_seed(0)
    batch = aria_batch(aria_rig[1], size=96)
    module = bare_module(net={"scales": (0, 1), "base_focal": 45.0}, input_size=(96, 96))
    optimiser = torch.optim.Adam(module.parameters(), 1e-3)
    losses = []
    for _ in range(20):
        loss, _ = module.objective(batch, module(batch.image, batch.camera))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(float(loss))
    assert all(math.isfinite(x) for x in losses)
    assert np.mean(losses[-5:]) < 0.98 * np.mean(losses[:5]), losses


def test_train_py_trains_on_the_real_rig(aria_rig, tmp_path, monkeypatch, caplog):
    """``train.py data=rig`` (its function, on Hydra's composition of its config) on the converted Aria
    rig: its four cameras load and one step trains."""
    import logging
    from pathlib import Path

    from hydra import compose, initialize_config_dir

    from fisheyedepth.cli.train import train

    root = Path(__file__).resolve().parents[1]
    monkeypatch.setenv("RIG_ROOT", str(aria_rig[1]))
    overrides = [
        "data=rig", "data.datamodule.min_translation=0.005", "data.datamodule.size=[64,64]",
        "data.datamodule.num_workers=0", "data.datamodule.batch_size=4", "trainer.fast_dev_run=true",
        "model.compile_kernels=false", "logger=none", "callbacks.progress=null", f"paths.data_dir={tmp_path}",
        f"paths.output_dir={tmp_path / 'run'}",
    ]  # fmt: skip
    with initialize_config_dir(config_dir=str(root / "conf"), version_base="1.3"):
        cfg = compose("train", overrides)
    caplog.set_level(logging.INFO)
    train(cfg)
    assert "20 samples kept" in caplog.text  # 4 cameras x the 5 of 9 frames with +-2 neighbours
    assert "`Trainer.fit` stopped: `max_steps=1` reached" in caplog.text
