"""SE(3) helpers and the photometric warp."""

from __future__ import annotations

import math

import pytest
import torch

from fisheyedepth.cameras import KannalaBrandtCamera, MeiCamera, PinholeCamera, RayCache, pixel_grid
from fisheyedepth.data.kitti360 import KITTI360_CAM_TO_POSE
from fisheyedepth.geometry import (
    ALIGN_CORNERS,
    axis_angle_to_matrix,
    distance_to_depth,
    grid_to_pixels,
    invert_pose,
    make_pose,
    mirror_pose_x,
    pixels_to_grid,
    pose_from_3x4,
    quaternion_to_matrix,
    relative_pose,
    sample,
    transform_points,
    warp_to_source,
)

from conftest import all_cameras, kitti02, kitti03

D64 = torch.float64


def random_pose(g: torch.Generator, angle: float = 1.0, shift: float = 2.0) -> torch.Tensor:
    aa = (torch.rand(3, generator=g, dtype=D64) - 0.5) * 2 * angle
    t = (torch.rand(3, generator=g, dtype=D64) - 0.5) * 2 * shift
    return make_pose(axis_angle_to_matrix(aa), t)


# ----------------------------------------------------------------------------------------------- SE(3)
def test_invert_pose_is_exact():
    g = torch.Generator().manual_seed(0)
    T = torch.stack([random_pose(g) for _ in range(5)])
    assert torch.allclose(invert_pose(T) @ T, torch.eye(4, dtype=D64).expand(5, 4, 4), atol=1e-14)


def test_relative_pose_between_two_cameras_of_a_rig():
    g = torch.Generator().manual_seed(1)
    P_t, P_s, E_t, E_s = (random_pose(g) for _ in range(4))
    X_world = torch.randn(100, 3, generator=g, dtype=D64) * 5
    X_t = transform_points(invert_pose(P_t @ E_t), X_world)
    X_s = transform_points(invert_pose(P_s @ E_s), X_world)
    assert torch.allclose(transform_points(relative_pose(P_t, P_s, E_t, E_s), X_t), X_s, atol=1e-12)
    # one camera: KITTI-360's E^-1 P_s^-1 P_t E
    kitti = torch.linalg.inv(E_t) @ torch.linalg.inv(P_s) @ P_t @ E_t
    assert torch.allclose(relative_pose(P_t, P_s, E_t), kitti, atol=1e-12)


def test_pose_from_3x4_reads_kitti_rows():
    row = list(KITTI360_CAM_TO_POSE["image_02"])  # a line of the official calib_cam_to_pose.txt
    T = pose_from_3x4(row)
    assert T.shape == (4, 4) and T[3].tolist() == [0, 0, 0, 1]
    assert T[0, 3].item() == pytest.approx(0.7264036936) and T[2, 1].item() == pytest.approx(0.9999408692)
    with pytest.raises(ValueError, match="12 numbers"):
        pose_from_3x4([1.0, 2.0])


def test_transform_points_batched_shapes():
    g = torch.Generator().manual_seed(2)
    T = torch.stack([random_pose(g), random_pose(g)])
    X = torch.randn(2, 4, 5, 3, generator=g, dtype=D64)
    out = transform_points(T, X)
    assert out.shape == X.shape
    assert torch.allclose(out[1, 2, 3], T[1, :3, :3] @ X[1, 2, 3] + T[1, :3, 3])
    assert torch.allclose(transform_points(T[0], X[0]), out[0])


def test_axis_angle_to_matrix():
    aa = torch.tensor([[0.0, 0.0, math.pi / 2], [1e-10, 0.0, 0.0], [0.3, -1.2, 0.5]], dtype=D64)
    R = axis_angle_to_matrix(aa)
    assert torch.allclose(
        R[0] @ torch.tensor([1.0, 0, 0], dtype=D64), torch.tensor([0.0, 1, 0], dtype=D64), atol=1e-15
    )
    assert torch.allclose(R[1], torch.eye(3, dtype=D64), atol=1e-9)
    skew = torch.tensor([[0, -0.5, -1.2], [0.5, 0, -0.3], [1.2, 0.3, 0]], dtype=D64)
    assert torch.allclose(R[2], torch.linalg.matrix_exp(skew), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(3, dtype=D64))


def test_quaternion_to_matrix_xyzw():
    half = math.sqrt(0.5)
    R = quaternion_to_matrix(torch.tensor([0.0, 0.0, half, half], dtype=D64))  # 90 deg about z
    assert torch.allclose(R, axis_angle_to_matrix(torch.tensor([0, 0, math.pi / 2], dtype=D64)), atol=1e-12)
    R2 = quaternion_to_matrix(torch.tensor([0.2, -0.4, 0.1, 0.9], dtype=D64))
    assert torch.allclose(R2 @ R2.T, torch.eye(3, dtype=D64), atol=1e-12)


# ------------------------------------------------------------------------------------- grid convention
def test_grid_convention_align_corners_false():
    assert ALIGN_CORNERS is False
    W, H = 7, 5
    uv = pixel_grid(W, H, dtype=D64)
    grid = pixels_to_grid(uv, W, H)
    assert grid[0, 0].tolist() == pytest.approx([-1 + 1 / W, -1 + 1 / H])
    assert torch.allclose(grid_to_pixels(grid, W, H), uv)
    image = torch.arange(W * H, dtype=D64).reshape(1, 1, H, W)
    assert torch.allclose(sample(image, grid[None]), image, atol=1e-12)  # integer pixels sample themselves
    half = sample(image, pixels_to_grid(uv + torch.tensor([0.5, 0.0], dtype=D64), W, H)[None])
    assert torch.allclose(half[0, 0, :, :-1], image[0, 0, :, :-1] + 0.5)  # halfway between columns


# ------------------------------------------------------------------------------------------- the warp
def setup_warp(camera, batch=1, dtype=D64):
    rays, valid = RayCache().get(camera, dtype=dtype)
    return rays.expand(batch, -1, -1, -1), valid.expand(batch, -1, -1)


@pytest.mark.parametrize("name", list(all_cameras()))
def test_identity_warp_maps_each_pixel_to_itself(name):
    cam = all_cameras()[name]
    rays, valid = setup_warp(cam)
    dist = (
        torch.rand(1, 1, cam.height, cam.width, generator=torch.Generator().manual_seed(0), dtype=D64) * 50
        + 0.5
    )
    warp = warp_to_source(rays, valid, dist, torch.eye(4, dtype=D64)[None], cam)
    uv = pixel_grid(cam.width, cam.height, dtype=D64)
    assert bool(warp.valid[0][valid[0]].all())
    assert (warp.uv[0] - uv).norm(dim=-1)[valid[0]].max() < 1e-3
    image = torch.rand(1, 3, cam.height, cam.width, dtype=D64)
    warped = sample(image, warp.grid)
    assert torch.allclose(warped[..., warp.valid[0]], image[..., warp.valid[0]], atol=1e-6)


def test_mei_warp_hand_computed():
    cam = MeiCamera(width=100, height=80, xi=1.0, gamma1=100.0, gamma2=100.0, u0=50.0, v0=40.0)
    ray = torch.tensor([[[[0.0, 0.0, 1.0]]]], dtype=D64)
    T = make_pose(torch.eye(3, dtype=D64), torch.tensor([-1.0, 0.0, 0.0], dtype=D64))[None]
    warp = warp_to_source(
        ray, torch.ones(1, 1, 1, dtype=torch.bool), torch.full((1, 1, 1), 10.0, dtype=D64), T, cam
    )
    # X_s = (-1, 0, 10): x = s_x / (s_z + xi) = -1 / (10 + sqrt(101))
    assert warp.uv[0, 0, 0].tolist() == pytest.approx([50 - 100 / (10 + math.sqrt(101)), 40.0], abs=1e-12)
    assert bool(warp.valid.all())


def test_pinhole_warp_of_a_plane_is_the_homography():
    cam = PinholeCamera(width=64, height=48, fx=50.0, fy=52.0, cx=31.5, cy=23.5)
    K = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=D64)
    n, d = torch.tensor([0.1, -0.2, 1.0], dtype=D64), 6.0
    n = n / n.norm()
    R = axis_angle_to_matrix(torch.tensor([0.02, -0.05, 0.01], dtype=D64))
    t = torch.tensor([0.3, -0.1, 0.4], dtype=D64)
    rays, valid = setup_warp(cam)
    dist = d / (rays[0] @ n)  # ray-plane intersection: L = d / (n . r)
    warp = warp_to_source(rays, valid, dist[None], make_pose(R, t)[None], cam)
    Hm = K @ (R + torch.outer(t, n) / d) @ torch.linalg.inv(K)
    p = torch.cat((pixel_grid(64, 48, dtype=D64), torch.ones(48, 64, 1, dtype=D64)), -1) @ Hm.T
    expected = p[..., :2] / p[..., 2:]
    assert warp.valid[0].float().mean() > 0.6
    assert (warp.uv[0] - expected).norm(dim=-1)[warp.valid[0]].max() < 1e-9


def test_fisheye_warp_of_a_plane_lands_where_the_points_project():
    """Points on a ground plane 1.6 m below a KITTI-like fisheye, the rig moved by a known motion."""
    target, source = kitti02().resize(128, 128), kitti03().resize(96, 96)
    T = make_pose(
        axis_angle_to_matrix(torch.tensor([0.0, 0.15, 0.02], dtype=D64)),
        torch.tensor([0.2, 0.05, -0.9], dtype=D64),
    )
    rays, valid = setup_warp(target)
    h = 1.6
    down = rays[0, ..., 1] > 0.05
    dist = torch.where(down, h / rays[0, ..., 1].clamp_min(0.05), torch.zeros_like(rays[0, ..., 1]))
    warp = warp_to_source(rays, valid & down, dist[None], T[None], source)
    # independent: the 3-D points of the plane, moved rigidly, then projected
    X = rays[0] * dist[..., None]
    X_s = X @ T[:3, :3].T + T[:3, 3]
    expected, ok = source.project(X_s)
    assert bool(ok[warp.valid[0]].all())
    assert abs(X[..., 1][warp.valid[0]] - h).max() < 1e-12  # they are on the plane
    assert warp.valid[0].sum() > 1500
    assert (warp.uv[0] - expected).norm(dim=-1)[warp.valid[0]].max() < 1e-9
    # and the source's own unprojection of those pixels points back at the moved points
    back, _ = source.unproject(warp.uv[0][warp.valid[0]])
    moved = X_s[warp.valid[0]]
    cos = (back * moved / moved.norm(dim=-1, keepdim=True)).sum(-1)
    assert cos.min() > 1 - 1e-12


def texture(X: torch.Tensor) -> torch.Tensor:
    """A smooth world-fixed texture on the ground (x, z), band-limited so bilinear sampling is accurate."""
    x, z = X[..., 0], X[..., 2]
    return (
        0.5
        + 0.2 * torch.sin(1.3 * x + 0.4 * z)
        + 0.15 * torch.cos(0.9 * z - 0.7 * x)
        + 0.1 * torch.sin(0.5 * x * z / 4)
    )


def render_ground(camera, T_cam_to_world, height=1.5):
    rays, valid = RayCache().get(camera, dtype=D64)
    d = rays @ T_cam_to_world[:3, :3].T
    o = T_cam_to_world[:3, 3]
    lam = (height - o[1]) / d[..., 1]
    hit = valid & (d[..., 1] > 0.03) & (lam < 15)  # near ground: the texture stays well sampled
    X = o + d * lam.clamp(0, 15)[..., None]
    return torch.where(hit, texture(X), torch.zeros_like(lam)), hit, lam


def test_warp_between_two_camera_models_reproduces_the_image():
    """A Kannala-Brandt target and a Mei source of another rig position, rendered from one world."""
    target = KannalaBrandtCamera(
        width=160, height=120, fx=70.0, fy=70.0, cx=79.5, cy=59.5, k1=0.01, k2=-0.002, k3=0.0005, k4=0.0
    )
    source = kitti02().resize(160, 160)
    T_s_to_w = make_pose(
        axis_angle_to_matrix(torch.tensor([0.05, -0.3, 0.0], dtype=D64)),
        torch.tensor([0.4, -0.1, 0.8], dtype=D64),
    )
    img_t, hit_t, dist_t = render_ground(target, torch.eye(4, dtype=D64))
    img_s, hit_s, _ = render_ground(source, T_s_to_w)
    rays, valid = setup_warp(target)
    warp = warp_to_source(
        rays,
        valid & hit_t,
        dist_t[None],
        invert_pose(T_s_to_w)[None],
        source,
        source_mask=hit_s[None].to(D64),
    )
    warped = sample(img_s[None, None], warp.grid)[0, 0]
    m = warp.valid[0]
    assert m.sum() > 3000
    err = (warped - img_t).abs()[m]
    assert err.mean() < 0.01 and err.max() < 0.1
    # a wrong distance (x 1.3) must be clearly worse: the test can fail
    wrong = warp_to_source(
        rays,
        valid & hit_t,
        1.3 * dist_t[None],
        invert_pose(T_s_to_w)[None],
        source,
        source_mask=hit_s[None].to(D64),
    )
    err_wrong = (sample(img_s[None, None], wrong.grid)[0, 0] - img_t).abs()[wrong.valid[0]]
    assert err_wrong.mean() > 5 * err.mean()


def test_validity_rules():
    cam = PinholeCamera(width=32, height=24, fx=20.0, fy=20.0, cx=15.5, cy=11.5)
    rays, valid = setup_warp(cam, batch=1)
    dist = torch.full((1, 24, 32), 5.0, dtype=D64)
    dist[0, 0, 0] = 0.0  # not positive
    dist[0, 0, 1] = float("nan")  # not finite
    dist[0, 0, 2] = float("inf")
    no_ray = valid.clone()
    no_ray[0, 1, 1] = False
    T = make_pose(torch.eye(3, dtype=D64), torch.tensor([0.0, 0.0, -6.0], dtype=D64))[None]  # all behind
    assert not bool(warp_to_source(rays, valid, dist, T, cam).valid.any())
    shift = make_pose(torch.eye(3, dtype=D64), torch.tensor([1.0, 0.0, 0.0], dtype=D64))[None]  # +4 px in u
    warp = warp_to_source(rays, no_ray, dist, shift, cam)
    assert not bool(warp.valid[0, 0, :3].any()) and not bool(warp.valid[0, 1, 1])
    row = warp.uv[0, 5, :, 0]  # shifted right by fx * 1 m / z
    assert torch.equal(warp.valid[0, 5], row <= 31 + 1e-3)  # pushed out of the image on the right
    assert bool(warp.valid[0, 5, :20].all()) and not bool(warp.valid[0, 5, -4:].any())
    assert torch.isfinite(warp.grid).all() and (warp.grid[~warp.valid] == -2).all()
    mask = torch.ones(1, 1, 24, 32, dtype=D64)
    mask[..., 12:, :] = 0  # the body covers the lower half of the source image
    masked = warp_to_source(rays, no_ray, dist, shift, cam, source_mask=mask)
    assert not bool(masked.valid[0, 12:].any())
    assert torch.equal(masked.valid[0, :12], warp.valid[0, :12])  # v is unchanged: rows < 12 stay usable
    half_down = make_pose(torch.eye(3, dtype=D64), torch.tensor([0.0, 0.05, 0.0], dtype=D64))[None]
    sub = warp_to_source(rays, valid, dist, half_down, cam, source_mask=mask)  # v moves ~0.2 px down
    assert bool(sub.valid[0, 5:10, 5:25].all()) and not bool(sub.valid[0, 11, 5:25].any())  # 11.2 touches 12


def test_mixed_source_cameras_in_one_batch():
    a, b = kitti02().resize(64, 64), kitti03(tangential=True).resize(64, 64)
    g = torch.Generator().manual_seed(3)
    T = torch.stack([random_pose(g, 0.1, 0.5) for _ in range(3)])
    rays, valid = RayCache().batch([a, b, a], dtype=D64)
    dist = torch.rand(3, 64, 64, generator=g, dtype=D64) * 20 + 1
    sources = [b, a, b]
    batch = warp_to_source(rays, valid, dist, T, sources)
    for i in range(3):
        single = warp_to_source(rays[i : i + 1], valid[i : i + 1], dist[i : i + 1], T[i : i + 1], sources[i])
        assert torch.equal(single.valid[0], batch.valid[i])
        assert torch.allclose(single.grid[0], batch.grid[i], atol=1e-12)
    with pytest.raises(ValueError, match="2 cameras for a batch of 3"):
        warp_to_source(rays, valid, dist, T, [a, b])


def test_flipped_geometry_gives_the_flipped_warp():
    cam = kitti03(tangential=True).resize(80, 80)
    g = torch.Generator().manual_seed(4)
    T = random_pose(g, 0.1, 0.5)[None]
    rays, valid = setup_warp(cam)
    dist = torch.rand(1, 80, 80, generator=g, dtype=D64) * 10 + 2
    warp = warp_to_source(rays, valid, dist, T, cam)
    f = cam.flip()
    rays_f, valid_f = setup_warp(f)
    warp_f = warp_to_source(rays_f, valid_f, dist.flip(-1), mirror_pose_x(T), f)
    both = warp.valid[0].flip(-1) & warp_f.valid[0]
    assert both.sum() > 0.9 * warp.valid.sum()
    expected_u = 80 - 1 - warp.uv[0, ..., 0].flip(-1)
    assert (warp_f.uv[0, ..., 0] - expected_u)[both].abs().max() < 1e-9
    assert (warp_f.uv[0, ..., 1] - warp.uv[0, ..., 1].flip(-1))[both].abs().max() < 1e-9


def test_gradients_reach_the_distance():
    cam = kitti02().resize(48, 48)
    rays, valid = setup_warp(cam, dtype=torch.float32)
    g = torch.Generator().manual_seed(5)
    image = torch.rand(1, 3, 48, 48, generator=g)
    dist = (torch.rand(1, 1, 48, 48, generator=g) * 10 + 2).requires_grad_(True)
    T = make_pose(torch.eye(3), torch.tensor([0.3, 0.0, 0.2]))[None]
    warp = warp_to_source(rays[None].squeeze(0), valid, dist, T, cam)
    loss = sample(image, warp.grid)[..., warp.valid[0]].sum()
    loss.backward()
    assert torch.isfinite(dist.grad).all()
    assert dist.grad[0, 0][warp.valid[0]].abs().gt(0).float().mean() > 0.5
    assert dist.grad[0, 0][~warp.valid[0]].abs().max() == 0


def test_distance_to_depth_uses_the_ray():
    cam = kitti02().resize(32, 32)
    rays, _ = RayCache().get(cam)
    distance = torch.full((1, 1, 32, 32), 5.0)
    z = distance_to_depth(distance, rays[None])
    assert torch.allclose(z[0, 0], 5.0 * rays[..., 2])
    assert z[0, 0, 16, 16] == pytest.approx(5.0, abs=0.01)  # on the axis
    assert (z[0, 0, 16, :2] < 0).all()  # the image border is seen beyond 90 degrees: behind the image plane
