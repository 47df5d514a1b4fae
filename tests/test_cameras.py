"""Camera models: exactness of project/unproject, domains, resize, flip, serialisation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import (
    CameraModel,
    DoubleSphereCamera,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    load_camera,
    pinhole_like,
    pixel_grid,
    save_camera,
)

from conftest import KITTI_02, all_cameras, kitti02, kitti03


def directions(theta_max: float, n: int = 20000, dtype=torch.float64, seed: int = 0) -> torch.Tensor:
    """Unit directions with incidence spread over [0, theta_max), the axis and the rim included.

    The rim sample sits 1e-6 (float64) or 1e-4 (float32, which cannot resolve less) inside theta_max.
    """
    g = torch.Generator().manual_seed(seed)
    theta = torch.rand(n, generator=g, dtype=torch.float64) * theta_max
    rim = 1e-6 if dtype == torch.float64 else 1e-4
    theta[:5] = torch.tensor([0.0, 1e-9, 1e-4, theta_max * (1 - rim), theta_max * (1 - 1e-3)])
    phi = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    d = torch.stack(
        (torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)), -1
    )
    return d.to(dtype)


def angle_between(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def domain_limit(cam: CameraModel) -> float:
    # a pinhole sees (0, 90) degrees; keep away from the asymptote where u -> infinity
    return math.radians(80) if isinstance(cam, PinholeCamera) else cam.max_incidence


# ------------------------------------------------------------------------------------------ exactness
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_kitti360_image02_full_grid_round_trip(dtype):
    """project(unproject(uv)) on every valid pixel of the 1400x1400 image_02 grid."""
    cam = kitti02()
    uv = pixel_grid(1400, 1400, dtype=dtype)
    rays, valid = cam.unproject(uv)
    uv2, valid2 = cam.project(rays)
    err = (uv2 - uv).norm(dim=-1)
    incidence = torch.rad2deg(torch.acos(rays[..., 2].double().clamp(-1, 1)))
    beyond_90 = valid & (incidence > 90)
    assert valid.sum() > 0.85 * 1400 * 1400  # everything but the corners beyond the mirror's rim
    assert beyond_90.sum() > 200_000  # a large part of the image lies beyond 90 degrees
    assert bool(valid2[valid].all())
    tol = 1e-3 if dtype == torch.float64 else 1e-2
    assert err[valid].max().item() < tol
    assert err[beyond_90].max().item() < tol
    assert rays.dtype == dtype and uv2.dtype == dtype


def test_kitti360_domain_facts():
    cam2, cam3 = kitti02(), kitti03()
    assert math.degrees(cam2.max_incidence) == pytest.approx(
        math.degrees(math.acos(-1 / KITTI_02["xi"])), abs=1e-9
    )
    assert math.degrees(cam2.max_incidence) == pytest.approx(116.9, abs=0.05)
    assert math.degrees(cam3.max_incidence) == pytest.approx(113.1, abs=0.05)
    # the middle of the left image border is seen at about 100 degrees of incidence
    ray, ok = cam2.unproject(torch.tensor([0.0, 705.0], dtype=torch.float64))
    assert bool(ok)
    assert 95 < math.degrees(math.acos(ray[2].item())) < 110
    # the image corner is beyond the mirror's rim: no ray, finite output
    ray, ok = cam2.unproject(torch.tensor([0.0, 0.0], dtype=torch.float64))
    assert not bool(ok) and torch.isfinite(ray).all()


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 2e-3)])
def test_unproject_project_directions_over_whole_domain(camera, dtype, tol):
    """unproject(project(X)) recovers the direction of X over the model's whole field of view."""
    d = directions(domain_limit(camera), dtype=dtype)
    scale = torch.linspace(0.5, 80.0, d.shape[0], dtype=dtype)[:, None]  # the norm must not matter
    uv, ok = camera.project(d * scale)
    assert bool(ok.all())
    rays, ok2 = camera.unproject(uv)
    assert bool(ok2.all())
    err = angle_between(rays.double(), d.double())
    assert err.max().item() < tol
    assert torch.allclose(rays.norm(dim=-1).double(), torch.ones(len(d), dtype=torch.float64), atol=1e-6)


def test_round_trip_float64_beyond_90_degrees_is_exact():
    for name, cam in all_cameras().items():
        if cam.max_incidence <= math.pi / 2:
            continue
        d = directions(cam.max_incidence)
        d = d[torch.acos(d[:, 2]) > math.pi / 2]
        assert len(d) > 100, name
        uv, _ = cam.project(d)
        rays, ok = cam.unproject(uv)
        assert bool(ok.all()), name
        assert angle_between(rays, d).max().item() < 1e-6, name


def test_tangential_fold_is_outside_the_domain():
    """With p1/p2 near a radial fold the plane folds before g'(r) = 0; both directions agree on it."""
    cam = MeiCamera(
        width=320,
        height=240,
        xi=0.8,
        k1=-0.25,
        k2=0.02,
        p1=1e-3,
        p2=-5e-4,
        gamma1=300.0,
        gamma2=302.0,
        u0=160.3,
        v0=119.6,
    )
    d = directions(cam.max_incidence)
    uv, ok = cam.project(d)
    assert 0.95 < ok.float().mean() < 1.0  # a sliver at the rim folds
    rays, ok2 = cam.unproject(uv[ok])
    assert bool(ok2.all())
    assert angle_between(rays, d[ok]).max() < 1e-6


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-3), (torch.float32, 1e-2)])
def test_pixel_round_trip_every_model(camera, dtype, tol):
    uv = pixel_grid(camera.width, camera.height, dtype=dtype)
    rays, valid = camera.unproject(uv)
    assert valid.float().mean() > 0.3
    uv2, valid2 = camera.project(rays)
    assert bool(valid2[valid].all())
    assert (uv2 - uv).norm(dim=-1)[valid].max().item() < tol


def test_outside_domain_is_invalid_and_finite(camera):
    beyond = camera.max_incidence + 0.05
    rows = [[0.0, 0.0, 0.0], [0.0, 0.0, -1.0]]  # the centre of projection; straight behind
    if beyond < math.pi:  # a model whose domain ends before 180 degrees: just beyond its rim
        rows += [
            [math.sin(beyond), 0.0, math.cos(beyond)],
            [0.0, -math.sin(beyond) * 3, math.cos(beyond) * 3],
        ]
    pts = torch.tensor(rows, dtype=torch.float64, requires_grad=True)
    uv, ok = camera.project(pts)
    assert not bool(ok.any())
    assert torch.isfinite(uv).all()
    uv.sum().backward()
    assert torch.isfinite(pts.grad).all()
    far = torch.tensor(
        [[-1e7, -1e7], [1e9, 3.0], [float(camera.width) * 1e6, float(camera.height) * 1e6]],
        dtype=torch.float64,
    )
    rays, ok = camera.unproject(far)
    assert torch.isfinite(rays).all()
    if not isinstance(camera, PinholeCamera):  # every pixel of a pinhole image has a ray
        assert not bool(ok.any())


def test_project_is_differentiable(camera):
    d = directions(domain_limit(camera) * 0.95, n=12, seed=3) * 4.0
    d.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: camera.project(x)[0], (d,), eps=1e-6, atol=1e-5)


def test_any_leading_batch_shape(camera):
    d = directions(domain_limit(camera) * 0.9, n=2 * 3 * 5).reshape(2, 3, 5, 3)
    uv, ok = camera.project(d)
    assert uv.shape == (2, 3, 5, 2) and ok.shape == (2, 3, 5)
    flat, _ = camera.project(d.reshape(-1, 3))
    assert torch.equal(uv.reshape(-1, 2), flat)
    rays, ok = camera.unproject(uv)
    assert rays.shape == (2, 3, 5, 3) and ok.shape == (2, 3, 5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu(camera):
    d = directions(domain_limit(camera) * 0.99, n=5000)
    uv_cpu, ok_cpu = camera.project(d)
    uv_gpu, ok_gpu = camera.project(d.cuda())
    assert uv_gpu.device.type == "cuda"
    assert torch.allclose(uv_gpu.cpu(), uv_cpu, atol=1e-9) and torch.equal(ok_gpu.cpu(), ok_cpu)
    rays, _ = camera.unproject(uv_gpu)
    assert angle_between(rays.cpu(), d).max() < 1e-6


# ------------------------------------------------------------------------------- against references
def test_kannala_brandt_matches_opencv_fisheye():
    cv2 = pytest.importorskip("cv2")
    cam = all_cameras()["kb_tumvi"]
    d = directions(math.radians(89), n=5000) * torch.linspace(0.3, 50, 5000, dtype=torch.float64)[:, None]
    K = np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]])
    D = np.array([cam.k1, cam.k2, cam.k3, cam.k4])
    expected, _ = cv2.fisheye.projectPoints(d.numpy()[:, None, :], np.zeros(3), np.zeros(3), K, D)
    uv, ok = cam.project(d)
    assert bool(ok.all())
    assert np.abs(uv.numpy() - expected[:, 0]).max() < 1e-6
    # and OpenCV's inverse agrees with ours inside the front hemisphere
    undist = cv2.fisheye.undistortPoints(expected, K, D)[:, 0]  # normalised X/Z, Y/Z
    rays, _ = cam.unproject(uv)
    assert np.abs(rays[:, :2].numpy() / rays[:, 2:].numpy() - undist).max() < 1e-5


def _mei_reference(X: np.ndarray, p: dict) -> np.ndarray:
    """The REFERENCE.md formula with OpenCV's tangential terms, written independently in numpy."""
    s = X / np.linalg.norm(X, axis=1, keepdims=True)
    x, y = s[:, 0] / (s[:, 2] + p["xi"]), s[:, 1] / (s[:, 2] + p["xi"])
    r2 = x * x + y * y
    rad = 1 + p["k1"] * r2 + p["k2"] * r2 * r2
    xd = x * rad + 2 * p["p1"] * x * y + p["p2"] * (r2 + 2 * x * x)
    yd = y * rad + p["p1"] * (r2 + 2 * y * y) + 2 * p["p2"] * x * y
    return np.stack((p["gamma1"] * xd + p["u0"], p["gamma2"] * yd + p["v0"]), axis=1)


def test_mei_matches_reference_formula():
    cam = kitti02(tangential=True)
    d = directions(cam.max_incidence * 0.999, n=3000) * 7.0
    uv, ok = cam.project(d)
    assert bool(ok.all())
    assert np.abs(uv.numpy() - _mei_reference(d.numpy(), KITTI_02)).max() < 1e-9


@pytest.mark.parametrize("make,low,high", [(kitti02, 0.5, 0.7), (kitti03, 1.0, 1.4)])
def test_kitti360_tangential_terms_matter_about_a_pixel(make, low, high):
    """The official tools ignore p1/p2; keeping them moves pixels by up to ~1.2 px at 1400 px."""
    with_t, without = make(tangential=True), make()
    uv = pixel_grid(1400, 1400, dtype=torch.float64)[::7, ::7]
    rays, ok = without.unproject(uv)
    uv_t, ok_t = with_t.project(rays)
    shift = (uv_t - uv).norm(dim=-1)[ok & ok_t]
    assert low < shift.max().item() < high


def test_double_sphere_matches_paper_formula():
    cam = all_cameras()["ds_tumvi"]
    X = directions(math.radians(120), n=500).numpy() * 3.0
    x, y, z = X.T
    d1 = np.sqrt(x * x + y * y + z * z)
    d2 = np.sqrt(x * x + y * y + (cam.xi * d1 + z) ** 2)
    den = cam.alpha * d2 + (1 - cam.alpha) * (cam.xi * d1 + z)
    expected = np.stack((cam.fx * x / den + cam.cx, cam.fy * y / den + cam.cy), 1)
    uv, ok = cam.project(torch.from_numpy(X))
    assert bool(ok.all())
    assert np.abs(uv.numpy() - expected).max() < 1e-9


def test_pinhole_matches_intrinsic_matrix():
    cam = all_cameras()["pinhole"]
    X = torch.tensor([[0.5, -0.2, 2.0], [-3.0, 1.0, 10.0]], dtype=torch.float64)
    K = torch.tensor([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]], dtype=torch.float64)
    h = X @ K.T
    uv, ok = cam.project(X)
    assert bool(ok.all()) and torch.allclose(uv, h[:, :2] / h[:, 2:], atol=1e-12)


def test_pinhole_like_matches_fisheye_near_the_centre(camera):
    pin = pinhole_like(camera)
    assert (pin.cx, pin.cy) == camera.principal_point
    theta = 2e-3  # paraxial: the two agree to first order in theta
    d = torch.tensor(
        [[math.sin(theta), 0, math.cos(theta)], [0, math.sin(theta), math.cos(theta)]], dtype=torch.float64
    )
    uv_f, _ = camera.project(d)
    uv_p, _ = pin.project(d)
    moved = (uv_f - torch.tensor(camera.principal_point, dtype=torch.float64)).norm(dim=-1)
    assert moved.min() > 0.05  # the test point really is off-centre
    assert (uv_f - uv_p).norm(dim=-1).max() < 1e-3 * moved.max()


# ------------------------------------------------------------------------------- resize and flip
def test_resize_maps_pixels_with_pixel_centre_convention(camera):
    small = camera.resize(camera.width // 2 + 7, camera.height // 3 + 5)
    su, sv = small.width / camera.width, small.height / camera.height
    d = directions(domain_limit(camera) * 0.99, n=2000)
    uv, ok = camera.project(d)
    uv_s, ok_s = small.project(d)
    assert torch.equal(ok, ok_s)
    expected = (uv + 0.5) * torch.tensor([su, sv], dtype=torch.float64) - 0.5
    assert (uv_s - expected).abs().max() < 1e-9
    back = small.resize(camera.width, camera.height).to_dict()
    for key, value in camera.to_dict().items():
        assert back[key] == (
            value if isinstance(value, str) else pytest.approx(value, rel=1e-12, abs=1e-9)
        ), key


def test_kitti_resize_to_training_resolution():
    cam = kitti02().resize(384, 384)
    s = 384 / 1400
    assert cam.gamma1 == pytest.approx(KITTI_02["gamma1"] * s)
    assert cam.u0 == pytest.approx((KITTI_02["u0"] + 0.5) * s - 0.5)
    assert (cam.xi, cam.k1, cam.k2) == (KITTI_02["xi"], KITTI_02["k1"], KITTI_02["k2"])


def test_flip_mirrors_projection(camera):
    flipped = camera.flip()
    d = directions(domain_limit(camera) * 0.99, n=2000)
    uv, ok = camera.project(d)
    mirrored = d * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    uv_f, ok_f = flipped.project(mirrored)
    assert torch.equal(ok, ok_f)
    assert (uv_f[:, 0] - (camera.width - 1 - uv[:, 0])).abs().max() < 1e-9
    assert (uv_f[:, 1] - uv[:, 1]).abs().max() < 1e-9
    twice = flipped.flip().to_dict()
    assert all(twice[k] == pytest.approx(v, abs=1e-12) for k, v in camera.to_dict().items() if k != "model")
    rays_f, ok_r = flipped.unproject(uv_f)
    assert bool(ok_r.all())
    assert angle_between(rays_f, mirrored).max() < 1e-6


def test_kitti_flip_principal_point():
    cam = kitti02(tangential=True).resize(384, 384)
    flipped = cam.flip()
    assert flipped.u0 == pytest.approx(384 - 1 - cam.u0)
    assert flipped.p2 == -cam.p2 and flipped.p1 == cam.p1


# ------------------------------------------------------------------------------- values and serialisation
def test_cameras_are_hashable_values(camera):
    same = CameraModel.from_dict(camera.to_dict())
    assert same == camera and hash(same) == hash(camera) and type(same) is type(camera)
    assert camera.resize(100, 90) != camera


def test_project_yaml_round_trip(tmp_path, camera):
    saved = save_camera(camera, tmp_path / "cam.yaml")
    loaded = load_camera(saved)
    assert loaded == camera and type(loaded) is type(camera)
    assert loaded.to_dict() == camera.to_dict()


def test_to_dict_is_plain_data(camera):
    data = camera.to_dict()
    assert data["model"] == type(camera).model_name
    assert all(isinstance(v, str | int | float) for v in data.values())
    assert (data["width"], data["height"]) == (camera.width, camera.height)


@pytest.mark.parametrize(
    "cls,params,key",
    [
        (MeiCamera, dict(xi=-0.1, gamma1=100.0, gamma2=100.0, u0=1.0, v0=1.0), "xi"),
        (MeiCamera, dict(xi=1.0, gamma1=0.0, gamma2=100.0, u0=1.0, v0=1.0), "gamma1"),
        (MeiCamera, dict(xi=1.0, gamma1=100.0, gamma2=100.0, u0=1.0, v0=1.0, k1=float("nan")), "k1"),
        (KannalaBrandtCamera, dict(fx=100.0, fy=-1.0, cx=1.0, cy=1.0), "fy"),
        (KannalaBrandtCamera, dict(fx=100.0, fy=100.0, cx=1.0, cy=1.0, k4=float("inf")), "k4"),
        (DoubleSphereCamera, dict(fx=100.0, fy=100.0, cx=1.0, cy=1.0, xi=0.1, alpha=1.5), "alpha"),
        (DoubleSphereCamera, dict(fx=100.0, fy=100.0, cx=1.0, cy=1.0, xi=-2.0, alpha=0.5), "xi"),
        (PinholeCamera, dict(fx=100.0, fy=100.0, cx="a", cy=1.0), "cx"),
    ],
)
def test_impossible_parameters_name_the_key(cls, params, key):
    with pytest.raises(ValueError) as info:
        cls(width=64, height=48, **params)
    assert info.value.key == key and key in str(info.value)


def test_impossible_size_names_the_key():
    with pytest.raises(ValueError, match="width"):
        PinholeCamera(width=0, height=10, fx=1.0, fy=1.0, cx=0.0, cy=0.0)
    with pytest.raises(ValueError, match="height"):
        PinholeCamera(width=10, height=2.5, fx=1.0, fy=1.0, cx=0.0, cy=0.0)


# ------------------------------------------------------------------------------------------ Fisheye624
def aria_formula(x, y, z, params):
    """Aria's FisheyeRadTanThinPrism projection written out for one point in front (scalar floats)."""
    f, cx, cy, *rest = params
    k, (p0, p1), (s0, s1, s2, s3) = rest[:6], rest[6:8], rest[8:]
    a, b = x / z, y / z
    r = math.hypot(a, b)
    th = math.atan(r)
    radial = 1 + sum(ki * th ** (2 * i + 2) for i, ki in enumerate(k))
    xr, yr = (radial * th / r * a, radial * th / r * b) if r > 0 else (0.0, 0.0)
    rd2 = xr * xr + yr * yr
    ud = xr + (2 * xr * xr + rd2) * p0 + 2 * xr * yr * p1 + s0 * rd2 + s1 * rd2 * rd2
    vd = yr + (2 * yr * yr + rd2) * p1 + 2 * xr * yr * p0 + s2 * rd2 + s3 * rd2 * rd2
    return f * ud + cx, f * vd + cy


def test_fisheye624_matches_arias_formula_in_front_of_the_camera():
    from conftest import ARIA_SIDE_LEFT, aria_fisheye624

    cam = aria_fisheye624()
    d = directions(math.radians(89.0), n=500)
    uv, ok = cam.project(d * 3.7)
    assert bool(ok.all())
    expected = torch.tensor([aria_formula(*p.tolist(), ARIA_SIDE_LEFT) for p in d * 3.7], dtype=torch.float64)
    assert (uv - expected).abs().max().item() < 1e-9


def test_fisheye624_whole_image_round_trip_and_beyond_90_degrees():
    """Every pixel of the real Aria camera: unproject, project back, to 1e-6 px; about 1 % of the
    image (the corners, past the fold of the factory polynomial at 107.5 degrees) has no ray."""
    from conftest import aria_fisheye624

    cam = aria_fisheye624()
    uv = pixel_grid(512, 512, dtype=torch.float64)
    rays, valid = cam.unproject(uv)
    back, valid2 = cam.project(rays)
    incidence = torch.rad2deg(torch.acos(rays[..., 2].clamp(-1, 1)))
    assert 0.985 < valid.double().mean().item() < 0.995
    assert bool(valid2[valid].all())
    assert (back - uv).norm(dim=-1)[valid].max().item() < 1e-6
    beyond = valid & (incidence > 90)
    assert beyond.sum() > 5000 and incidence[valid].max().item() < 107.49  # a ring beyond 90 degrees
    assert bool((rays[beyond][:, 2] < 0).all())  # behind the camera's plane, not folded in front
    # a ray past the polynomial's fold has no pixel; a point behind it on the axis neither
    behind = torch.tensor([[math.sin(math.radians(110)), 0.0, math.cos(math.radians(110))], [0, 0, -1.0]])
    _, ok = cam.project(behind.double())
    assert not bool(ok.any())
    # at 100 degrees (Z < 0) the projection continues outwards, where Aria's atan(|ab|) would fold
    ring = [
        cam.project(torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=torch.float64)) for t in (1.5, 1.7)
    ]
    assert all(bool(ok) for _, ok in ring) and ring[1][0][0] > ring[0][0][0] > cam.cx


def test_fisheye624_reads_arias_calibration_and_round_trips_through_yaml(realdata, tmp_path):
    from fisheyedepth.cameras import CalibrationError, Fisheye624Camera, load_camera, save_camera

    path = realdata / "aria_gen2_rig" / "calib_slam_fisheye624.json"
    names = ("slam-front-left", "slam-front-right", "slam-side-left", "slam-side-right")
    for name in names:
        cam = Fisheye624Camera.from_aria(path, name)
        assert (cam.width, cam.height) == (512, 512) and cam.fx == cam.fy and 240 < cam.fx < 250
        saved = save_camera(cam, tmp_path / f"{name}.yaml")
        assert load_camera(saved) == cam
        assert 0.9 < cam.pixel_coverage() <= 1.0
    from conftest import aria_fisheye624

    assert Fisheye624Camera.from_aria(path, "slam-side-left") == aria_fisheye624()
    with pytest.raises(
        CalibrationError, match=r"key 'rgb'.*no such camera; the file has \['slam-front-left'"
    ):
        Fisheye624Camera.from_aria(path, "rgb")
    bad = tmp_path / "bad.json"
    bad.write_text('{"cam": {"model": "CameraModelType.FISHEYE624", "params": [1, 2, 3], "size": [8, 8]}}')
    with pytest.raises(CalibrationError, match=r"bad.json: key 'cam.params': expected 15 numbers"):
        Fisheye624Camera.from_aria(bad, "cam")
    bad.write_text('{"cam": {"model": "CameraModelType.KANNALA_BRANDT_K3", "params": [], "size": [8, 8]}}')
    with pytest.raises(CalibrationError, match=r"key 'cam.model': .*is not a FISHEYE624 calibration"):
        Fisheye624Camera.from_aria(bad, "cam")
    params = [-5.0] + [1.0] * 14
    bad.write_text(json.dumps({"cam": {"model": "FISHEYE624", "params": params, "size": [8, 8]}}))
    with pytest.raises(CalibrationError, match=r"key 'cam.fx': focal length must be positive"):
        Fisheye624Camera.from_aria(bad, "cam")
