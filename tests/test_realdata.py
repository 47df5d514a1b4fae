"""Real fisheye data (../shared/realdata, or FISHEYEDEPTH_REALDATA): skipped when absent."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import KannalaBrandtCamera, RayCache, load_camera
from fisheyedepth.geometry import make_pose, quaternion_to_matrix, relative_pose, sample, warp_to_source

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
