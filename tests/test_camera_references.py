"""The unified (UCM, EUCM), FOV and OpenCV camera models against independent references: OpenCV itself,
the papers' formulas written out in numpy, and the known relations between models; their exact domains,
beyond 90 degrees where they reach; their parameter checks."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import (
    CameraModel,
    CameraParameterError,
    ExtendedUnifiedCamera,
    FovCamera,
    MeiCamera,
    OpenCVCamera,
    PinholeCamera,
    UnifiedCamera,
)

from conftest import all_cameras
from test_cameras import angle_between, directions

F64 = torch.float64


def at_incidence(theta: np.ndarray, phi: np.ndarray) -> torch.Tensor:
    """Unit directions at incidence ``theta`` and azimuth ``phi`` (arrays of one shape), float64."""
    st = np.sin(theta)
    return torch.from_numpy(np.stack((st * np.cos(phi), st * np.sin(phi), np.cos(theta)), -1))


def azimuths(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0, 2 * math.pi, n)


# ============================================================================================ OpenCV
def cv_matrices(cam: OpenCVCamera) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[cam.fx, 0.0, cam.cx], [0.0, cam.fy, cam.cy], [0.0, 0.0, 1.0]])
    D = np.array([cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6])
    return K, D


def cv_project(cam: OpenCVCamera, points: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.projectPoints`` of ``points`` and OpenCV's Jacobian of the pixel with respect to ``(x, y)`` on
    the normalised plane (the translation columns of its Jacobian at points with Z = 1), ``[N, 2, 2]``."""
    cv2 = pytest.importorskip("cv2")
    K, D = cv_matrices(cam)
    pts = points.numpy()
    uv, _ = cv2.projectPoints(pts[:, None, :], np.zeros(3), np.zeros(3), K, D)
    plane = pts / pts[:, 2:]  # the same pixels from points at Z = 1: d(uv)/d(t) = d(uv)/d(x, y, 1)
    _, jac_plane = cv2.projectPoints(plane[:, None, :], np.zeros(3), np.zeros(3), K, D)
    dxy = jac_plane[:, 3:5].reshape(-1, 2, 2)
    return uv[:, 0], dxy


OPENCV_CAMERAS = {name: cam for name, cam in all_cameras().items() if isinstance(cam, OpenCVCamera)}
# without p1/p2 the domain is exactly the disc r < r_max, which the rim samples below test point by point
OPENCV_RADIAL = {name: dataclasses.replace(cam, p1=0.0, p2=0.0) for name, cam in OPENCV_CAMERAS.items()}


def plane_samples(cam: OpenCVCamera, n: int = 4000) -> torch.Tensor:
    """Points over the normalised plane out to 1.02 r_max, uniform in radius, and 2000 within 1e-3 .. 1e-10
    (relative) of the radial limit on either side, at Z from 0.3 to 30."""
    rng = np.random.default_rng(1)
    r_max = cam._r_max
    r = np.concatenate(
        (
            rng.uniform(0, 1.02 * r_max, n),
            r_max * (1 - 10.0 ** rng.uniform(-10, -3, 1000)),
            r_max * (1 + 10.0 ** rng.uniform(-10, -3, 1000)),
        )
    )
    phi = rng.uniform(0, 2 * math.pi, len(r))
    z = rng.uniform(0.3, 30, len(r))
    return torch.from_numpy(np.stack((r * np.cos(phi) * z, r * np.sin(phi) * z, z), -1))


@pytest.mark.parametrize("name", list(OPENCV_CAMERAS))
@pytest.mark.parametrize("tangential", [True, False])
def test_opencv_projection_matches_cv2_over_the_whole_domain(name, tangential):
    """Every point ``project`` accepts lands where ``cv2.projectPoints`` puts it (<= 1e-6 px), the rim of the
    monotonic radius included; the points it refuses are exactly those past r_max or where OpenCV's own
    Jacobian says the distortion folds the plane (det <= 0)."""
    cam = (OPENCV_CAMERAS if tangential else OPENCV_RADIAL)[name]
    assert cam.has_tangential == tangential
    X = plane_samples(cam)
    uv, ok = cam.project(X)
    expected, dxy = cv_project(cam, X)
    err = np.abs(uv.numpy() - expected).max(axis=1)[ok.numpy()]
    assert err.max() < 1e-6
    r = (X[:, :2].norm(dim=-1) / X[:, 2]).numpy()
    near_rim = ok.numpy() & (r > cam._r_max * (1 - 1e-6))
    assert near_rim.sum() > (100 if tangential else 400)  # the agreement holds at the rim too
    det = np.linalg.det(dxy) / (cam.fx * cam.fy)
    inside = r < cam._r_max
    decided = np.abs(r / cam._r_max - 1) > 1e-12  # points on the rim to rounding may go either way
    if tangential:
        decided &= np.abs(det) > 1e-9
        assert ((det <= 0) & inside).sum() > 20  # the fold sliver is sampled
    assert np.array_equal(ok.numpy()[decided], (inside & (det > 0))[decided])


@pytest.mark.parametrize("name", list(OPENCV_CAMERAS))
def test_opencv_unprojection_matches_cv2_undistort_points(name):
    """``unproject`` against ``cv2.undistortPoints`` with 300 iterations, where OpenCV's fixed-point iteration
    converges (its result reprojects to the pixel to 1e-9 px): the rays agree to 1e-11 rad.
    It converges over most of the domain; beyond, the round trip through ``project`` is the reference."""
    cv2 = pytest.importorskip("cv2")
    cam = OPENCV_CAMERAS[name]
    d = directions(cam.max_incidence, n=4000, seed=5)
    uv, ok = cam.project(d)
    assert bool(ok.all())
    K, D = cv_matrices(cam)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 300, 1e-13)
    theirs = cv2.undistortPoints(uv.numpy()[:, None, :], K, D, None, np.eye(3), np.eye(3), criteria)[:, 0]
    back, _ = cv2.projectPoints(
        np.concatenate((theirs, np.ones((len(theirs), 1))), 1)[:, None], np.zeros(3), np.zeros(3), K, D
    )
    converged = np.abs(back[:, 0] - uv.numpy()).max(axis=1) < 1e-9
    rays, ok2 = cam.unproject(uv)
    assert bool(ok2.all())
    ours = (rays[:, :2] / rays[:, 2:]).numpy()
    assert converged.mean() > 0.9
    cv_rays = torch.from_numpy(np.concatenate((theirs, np.ones((len(theirs), 1))), 1))
    assert angle_between(rays, cv_rays)[converged].max() < 1e-11
    # the round trip covers the rest, up to 1e-6 (relative) inside max_incidence
    assert angle_between(rays, d).max().item() < 1e-9
    truth = (d[:, :2] / d[:, 2:]).numpy()
    assert np.abs(ours - truth).max() < 1e-9 * max(1.0, cam._r_max)


@pytest.mark.parametrize("name", list(OPENCV_CAMERAS))
def test_opencv_pixels_past_the_image_of_the_domain_get_no_ray(name):
    """Without p1/p2: the circle of radius g(r_max) (normalised) bounds the pixels with a ray, exactly."""
    cam = OPENCV_RADIAL[name]
    N = 1 + cam.k1 * cam._r_max**2 + cam.k2 * cam._r_max**4 + cam.k3 * cam._r_max**6
    Dn = 1 + cam.k4 * cam._r_max**2 + cam.k5 * cam._r_max**4 + cam.k6 * cam._r_max**6
    g_max = cam._r_max * N / Dn
    phi = azimuths(500, seed=2)
    rows = []
    for scale in (1 - 1e-9, 1 + 1e-9):
        m = g_max * scale
        rows.append(np.stack((cam.cx + cam.fx * m * np.cos(phi), cam.cy + cam.fy * m * np.sin(phi)), -1))
    inside, outside = (torch.from_numpy(p) for p in rows)
    rays, ok = cam.unproject(inside)
    assert bool(ok.all())
    # the rays of the last pixels sit at the rim: within 1e-4 (relative; the map is flat there) of r_max
    r = (rays[:, :2].norm(dim=-1) / rays[:, 2]).numpy()
    assert np.all(np.abs(r / cam._r_max - 1) < 1e-4)
    back, ok_back = cam.project(rays)
    assert bool(ok_back.all()) and (back - inside).norm(dim=-1).max() < 1e-6
    rays, ok = cam.unproject(outside)
    assert not bool(ok.any()) and torch.isfinite(rays).all()


def test_opencv_monotonic_limit_against_a_dense_scan():
    """r_max from the polynomial roots against the first decrease of g on a grid of 2e6 radii; a pole of
    f (k4 < 0) bounds the domain just short of it; a g that increases for ever gives the half-space."""
    for cam in OPENCV_RADIAL.values():
        r = np.linspace(0, 2 * cam._r_max, 2_000_001)
        s = r * r
        g = (
            r
            * (1 + s * (cam.k1 + s * (cam.k2 + s * cam.k3)))
            / (1 + s * (cam.k4 + s * (cam.k5 + s * cam.k6)))
        )
        first_down = r[np.argmax(np.diff(g) < 0)]
        assert abs(first_down - cam._r_max) < 2 * (r[1] - r[0])
    pole = OpenCVCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, k4=-0.5)  # f = 1 / (1 - s/2)
    assert pole._radial_limit == (pytest.approx(math.sqrt(2) * (1 - 1e-7), rel=1e-12), True)
    inside = torch.tensor([[math.sqrt(2) * (1 - 2e-7), 0.0, 1.0], [0.0, -1.2, 1.0]], dtype=F64)
    uv, ok = pole.project(inside)
    assert bool(ok.all()) and torch.isfinite(uv).all() and uv[0, 0] > 1e6  # g ~ 1e7 r near the pole
    rays, ok = pole.unproject(uv)
    assert bool(ok.all()) and angle_between(rays, inside / inside.norm(dim=-1, keepdim=True)).max() < 1e-9
    _, ok = pole.project(torch.tensor([[math.sqrt(2) * 1.001, 0.0, 1.0]], dtype=F64))
    assert not bool(ok.any())
    # k1 > 0 alone: g increases for ever; the domain is Z > 0, every pixel has a ray
    forever = OpenCVCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, k1=0.1, p1=1e-3)
    assert forever._r_max == math.inf and forever.max_incidence == math.pi / 2
    d = directions(math.radians(80), n=2000)
    uv, ok = forever.project(d)
    rays, ok2 = forever.unproject(uv)
    assert bool(ok.all() and ok2.all()) and angle_between(rays, d).max() < 1e-9
    _, ok = forever.unproject(torch.tensor([[1e6, -3e5]], dtype=F64))
    assert bool(ok.all())


@pytest.mark.parametrize("name", list(OPENCV_CAMERAS))
def test_opencv_max_incidence_is_the_largest_unfolded_cone(name):
    """max_incidence: the cone inside it is in the domain at every azimuth; 1e-5 beyond it, not."""
    cam = OPENCV_CAMERAS[name]
    assert cam.max_incidence < math.atan(cam._r_max)
    phi = np.linspace(0, 2 * math.pi, 20001)
    _, ok = cam.project(at_incidence(np.full_like(phi, cam.max_incidence * (1 - 1e-9)), phi))
    assert bool(ok.all())
    _, ok = cam.project(at_incidence(np.full_like(phi, cam.max_incidence * (1 + 1e-5)), phi))
    assert not bool(ok.all())
    radial = OPENCV_RADIAL[name]
    assert radial.max_incidence == math.atan(radial._r_max)


def test_opencv_tangential_fold_cone_in_closed_form():
    """p2 alone: on the x axis det J = (1 + 6 p2 x)(1 + 2 p2 x), which first vanishes at x = -1 / (6 p2),
    the nearest fold over all azimuths; beyond it the points there have no pixel, before it they do."""
    p2 = 0.05
    cam = OpenCVCamera(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, p2=p2)
    assert cam._r_max == math.inf
    assert cam.max_incidence == pytest.approx(math.atan(1 / (6 * p2)), abs=1e-12)
    x = -1 / (6 * p2)
    _, ok = cam.project(torch.tensor([[x * (1 - 1e-9), 0.0, 1.0], [x * (1 + 1e-9), 0.0, 1.0]], dtype=F64))
    assert ok.tolist() == [True, False]
    _, ok = cam.project(torch.tensor([[-x * 1.5, 0.0, 1.0], [0.0, x * 1.5, 1.0]], dtype=F64))
    assert bool(ok.all())  # the other side, and across, unfold further out


def test_opencv_flip_negates_p2_proved_with_cv2():
    """The mirrored camera (u -> W - 1 - u for (X, Y, Z) -> (-X, Y, Z)) is OpenCV's model with
    cx -> W - 1 - cx and p2 -> -p2: cv2 itself projects the mirrored points there; negating p1 instead, or
    neither, does not."""
    cam = OPENCV_CAMERAS["opencv_plumb_bob_usb"]
    flipped = cam.flip()
    assert flipped.p2 == -cam.p2 and flipped.p1 == cam.p1 and flipped.cx == cam.width - 1 - cam.cx
    d = directions(cam.max_incidence * 0.95, n=3000, seed=7)
    mirrored = d * torch.tensor([-1.0, 1.0, 1.0], dtype=F64)
    uv, _ = cv_project(cam, d)
    target = np.stack((cam.width - 1 - uv[:, 0], uv[:, 1]), -1)

    def error(candidate: OpenCVCamera) -> float:
        return float(np.abs(cv_project(candidate, mirrored)[0] - target).max())

    assert error(flipped) < 1e-9
    wrong_p1 = dataclasses.replace(flipped, p1=-cam.p1, p2=cam.p2)
    unchanged = dataclasses.replace(flipped, p2=cam.p2)
    assert error(wrong_p1) > 0.1 and error(unchanged) > 0.1


def test_opencv_from_ros():
    """ROS CameraInfo: plumb_bob (5 coefficients) and rational_polynomial (8); anything else is refused."""
    K = [612.3, 0.0, 318.2, 0.0, 611.8, 242.7, 0.0, 0.0, 1.0]
    plumb = OpenCVCamera.from_ros(640, 480, K, [-0.2924, 0.0899, 0.0011, -0.0007, -0.0122])
    assert plumb == OPENCV_CAMERAS["opencv_plumb_bob_usb"]
    assert plumb.to_ros() == {
        "width": 640,
        "height": 480,
        "distortion_model": "plumb_bob",
        "D": [-0.2924, 0.0899, 0.0011, -0.0007, -0.0122],
        "K": K,
    }
    rational = OPENCV_CAMERAS["opencv_rational_120"]
    info = rational.to_ros()
    assert info["distortion_model"] == "rational_polynomial" and len(info["D"]) == 8
    again = OpenCVCamera.from_ros(
        info["width"], info["height"], np.array(info["K"]).reshape(3, 3), info["D"], "rational_polynomial"
    )
    assert again == rational
    with pytest.raises(CameraParameterError, match=r"D: expected 5 \(plumb_bob\) or 8") as err:
        OpenCVCamera.from_ros(640, 480, K, [0.1, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert err.value.key == "D"
    with pytest.raises(CameraParameterError) as err:
        OpenCVCamera.from_ros(640, 480, K, [0.1] * 5, distortion_model="rational_polynomial")
    assert err.value.key == "distortion_model"
    with pytest.raises(CameraParameterError) as err:
        OpenCVCamera.from_ros(640, 480, [612.3, 0.5, 318.2, 0.0, 611.8, 242.7, 0.0, 0.0, 1.0], [0.0] * 5)
    assert err.value.key == "K" and "skew" in str(err.value)
    with pytest.raises(CameraParameterError) as err:
        OpenCVCamera.from_ros(640, 480, K, [0.0, float("nan"), 0.0, 0.0, 0.0])
    assert err.value.key == "k2"


def test_opencv_without_distortion_is_the_pinhole():
    args = dict(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25)
    cam, pin = OpenCVCamera(**args), PinholeCamera(**args)
    assert cam.max_incidence == math.pi / 2
    d = directions(math.radians(85), n=1000) * 3.0
    assert torch.allclose(cam.project(d)[0], pin.project(d)[0], rtol=0, atol=1e-12)
    uv = torch.tensor([[0.0, 0.0], [319.0, 239.0], [1e5, -3e4]], dtype=F64)
    assert torch.allclose(cam.unproject(uv)[0], pin.unproject(uv)[0], rtol=0, atol=1e-15)


# ===================================================================== unified models: the papers' formulas
def ucm_paper_project(X: np.ndarray, fx, fy, cx, cy, alpha) -> np.ndarray:
    """Usenko et al. 2018, the UCM: ``u = fx x / (alpha d + (1 - alpha) z) + cx``, one point at a time."""
    out = []
    for x, y, z in X:
        d = math.sqrt(x * x + y * y + z * z)
        den = alpha * d + (1 - alpha) * z
        out.append((fx * x / den + cx, fy * y / den + cy))
    return np.array(out)


def ucm_paper_unproject(uv: np.ndarray, fx, fy, cx, cy, alpha) -> np.ndarray:
    """Usenko et al. 2018, the UCM's inverse in Mei's form: ``xi = alpha / (1 - alpha)``,
    ``m = (1 - alpha) ((u - cx) / fx, (v - cy) / fy)``, ``ray ~ (xi + sqrt(1 + (1 - xi^2) r^2)) / (1 + r^2)
    (m_x, m_y, 1) - (0, 0, xi)``."""
    xi = alpha / (1 - alpha)
    out = []
    for u, v in uv:
        mx, my = (u - cx) / fx * (1 - alpha), (v - cy) / fy * (1 - alpha)
        r2 = mx * mx + my * my
        k = (xi + math.sqrt(1 + (1 - xi * xi) * r2)) / (1 + r2)
        ray = np.array((k * mx, k * my, k - xi))
        out.append(ray / np.linalg.norm(ray))
    return np.array(out)


def eucm_paper_project(X: np.ndarray, fx, fy, cx, cy, alpha, beta) -> np.ndarray:
    """Khomenko et al. 2016 in Usenko et al.'s form: ``d = sqrt(beta (x^2 + y^2) + z^2)``."""
    out = []
    for x, y, z in X:
        d = math.sqrt(beta * (x * x + y * y) + z * z)
        den = alpha * d + (1 - alpha) * z
        out.append((fx * x / den + cx, fy * y / den + cy))
    return np.array(out)


def eucm_paper_unproject(uv: np.ndarray, fx, fy, cx, cy, alpha, beta) -> np.ndarray:
    """``m_z = (1 - beta alpha^2 r^2) / (alpha sqrt(1 - (2 alpha - 1) beta r^2) + 1 - alpha)``."""
    out = []
    for u, v in uv:
        mx, my = (u - cx) / fx, (v - cy) / fy
        r2 = mx * mx + my * my
        mz = (1 - beta * alpha * alpha * r2) / (
            alpha * math.sqrt(1 - (2 * alpha - 1) * beta * r2) + 1 - alpha
        )
        ray = np.array((mx, my, mz))
        out.append(ray / np.linalg.norm(ray))
    return np.array(out)


def fov_paper_project(X: np.ndarray, fx, fy, cx, cy, w) -> np.ndarray:
    """Devernay and Faugeras: ``r_d = atan(2 r tan(w / 2)) / w`` with ``r = rho / z`` in front; behind the
    camera the angle continues past pi / 2 (``pi - atan(2 rho tan(w / 2) / |z|)``)."""
    out = []
    t = math.tan(w / 2)
    for x, y, z in X:
        rho = math.hypot(x, y)
        if z > 0:
            angle = math.atan(2 * t * rho / z)
        elif z < 0:
            angle = math.pi - math.atan(2 * t * rho / -z)
        else:
            angle = math.pi / 2
        rd = angle / w
        out.append((fx * rd * x / rho + cx, fy * rd * y / rho + cy))
    return np.array(out)


def fov_paper_unproject(uv: np.ndarray, fx, fy, cx, cy, w) -> np.ndarray:
    """Devernay and Faugeras' inverse ``r = tan(r_d w) / (2 tan(w / 2))``, the point in front (``z = 1``) or,
    past pi / 2, behind (``z = -1``, ``r = -tan(r_d w) / (2 tan(w / 2))``)."""
    out = []
    t = math.tan(w / 2)
    for u, v in uv:
        mx, my = (u - cx) / fx, (v - cy) / fy
        rd = math.hypot(mx, my)
        angle = rd * w
        z = 1.0 if angle < math.pi / 2 else -1.0
        r = abs(math.tan(angle)) / (2 * t)
        ray = np.array((r * mx / rd, r * my / rd, z))
        out.append(ray / np.linalg.norm(ray))
    return np.array(out)


UNIFIED_CASES = {
    # the shared fixtures, and one more regime each: UCM and EUCM with alpha < 0.5, a narrow FOV lens
    "ucm_fisheye_640": all_cameras()["ucm_fisheye_640"],
    "ucm_alpha_below_half": UnifiedCamera(
        width=400, height=300, fx=150.0, fy=151.0, cx=200.2, cy=149.7, alpha=0.4
    ),
    "eucm_fisheye_640": all_cameras()["eucm_fisheye_640"],
    "eucm_flat_ellipsoid": ExtendedUnifiedCamera(
        width=400, height=300, fx=160.0, fy=160.5, cx=199.1, cy=150.2, alpha=0.45, beta=0.6
    ),
    "fov_wide_640": all_cameras()["fov_wide_640"],
    "fov_narrow": FovCamera(width=752, height=480, fx=379.0, fy=379.0, cx=376.2, cy=240.1, w=0.9259),
}


def paper_formulas(cam: CameraModel):
    p = cam.to_dict()
    focal = (p["fx"], p["fy"], p["cx"], p["cy"])
    if isinstance(cam, UnifiedCamera):
        return (
            lambda X: ucm_paper_project(X, *focal, p["alpha"]),
            lambda uv: ucm_paper_unproject(uv, *focal, p["alpha"]),
        )
    if isinstance(cam, ExtendedUnifiedCamera):
        return (
            lambda X: eucm_paper_project(X, *focal, p["alpha"], p["beta"]),
            lambda uv: eucm_paper_unproject(uv, *focal, p["alpha"], p["beta"]),
        )
    return (
        lambda X: fov_paper_project(X, *focal, p["w"]),
        lambda uv: fov_paper_unproject(uv, *focal, p["w"]),
    )


@pytest.mark.parametrize("name", list(UNIFIED_CASES))
def test_closed_forms_match_the_papers_formulas(name):
    """project and unproject against the scalar formulas of the papers, over the whole domain (to 1e-9 px
    and 1e-9 rad in float64; pixels relative to their distance from the centre where that is large)."""
    cam = UNIFIED_CASES[name]
    project, unproject = paper_formulas(cam)
    theta_max = min(cam.max_incidence, math.radians(179.0))
    d = directions(theta_max * (1 - 1e-4), n=1500, seed=11)[
        3:
    ]  # not on the axis (the formulas divide by rho)
    X = d * torch.linspace(0.2, 40, len(d), dtype=F64)[:, None]
    uv, ok = cam.project(X)
    assert bool(ok.all())
    expected = project(X.numpy())
    radius = np.linalg.norm(expected - np.array(cam.principal_point), axis=1)
    assert (np.abs(uv.numpy() - expected).max(axis=1) / np.maximum(1.0, radius)).max() < 1e-12
    rays, ok = cam.unproject(uv)
    assert bool(ok.all())
    assert np.abs(rays.numpy() - unproject(uv.numpy())).max() < 1e-9
    assert angle_between(rays, d).max() < 1e-9


def test_ucm_with_alpha_zero_is_the_pinhole():
    args = dict(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25)
    ucm, pin = UnifiedCamera(alpha=0.0, **args), PinholeCamera(**args)
    assert ucm.max_incidence == pytest.approx(math.pi / 2, abs=1e-15)
    d = directions(math.radians(85), n=1000) * 3.0
    assert torch.allclose(ucm.project(d)[0], pin.project(d)[0], rtol=0, atol=1e-12)
    _, ok = ucm.project(torch.tensor([[1.0, 0.0, -1e-9], [0.0, 0.0, -1.0]], dtype=F64))
    assert not bool(ok.any())
    uv = torch.tensor([[0.0, 0.0], [319.0, 239.0], [1e5, -3e4]], dtype=F64)
    rays, ok = ucm.unproject(uv)
    assert bool(ok.all()) and torch.allclose(rays, pin.unproject(uv)[0], rtol=0, atol=1e-15)


@pytest.mark.parametrize("alpha", [0.0, 0.3, 0.5, 0.62, 0.9, 1.0])
def test_eucm_with_beta_one_is_the_ucm(alpha):
    args = dict(width=400, height=300, fx=150.0, fy=151.0, cx=200.2, cy=149.7, alpha=alpha)
    ucm, eucm = UnifiedCamera(**args), ExtendedUnifiedCamera(beta=1.0, **args)
    assert eucm.max_incidence == ucm.max_incidence
    d = directions(min(ucm.max_incidence, 3.1) * 0.999, n=2000)
    uv, ok = ucm.project(d)
    uv_e, ok_e = eucm.project(d)
    assert torch.equal(ok, ok_e) and bool(ok.all()) and torch.equal(uv, uv_e)
    assert torch.equal(ucm.unproject(uv)[0], eucm.unproject(uv)[0])


@pytest.mark.parametrize("alpha,beta", [(0.64, 1.1), (0.45, 0.6), (0.8, 2.5)])
def test_eucm_is_the_ucm_of_a_stretched_point(alpha, beta):
    """EUCM(fx, alpha, beta) at (x, y, z) = UCM(fx / sqrt(beta), alpha) at (sqrt(beta) x, sqrt(beta) y, z)."""
    sb = math.sqrt(beta)
    eucm = ExtendedUnifiedCamera(
        width=400, height=300, fx=160.0, fy=161.0, cx=199.1, cy=150.2, alpha=alpha, beta=beta
    )
    ucm = UnifiedCamera(width=400, height=300, fx=160.0 / sb, fy=161.0 / sb, cx=199.1, cy=150.2, alpha=alpha)
    d = directions(eucm.max_incidence * 0.999, n=2000, seed=4)
    stretched = d * torch.tensor([sb, sb, 1.0], dtype=F64)
    uv, ok = eucm.project(d)
    uv_u, ok_u = ucm.project(stretched)
    assert bool(ok.all() and ok_u.all()) and (uv - uv_u).abs().max() < 1e-9
    # the rim: the stretched rim is the UCM's, at arccos(-w)
    stretched_rim = math.atan2(sb * math.sin(eucm.max_incidence), math.cos(eucm.max_incidence))
    assert stretched_rim == pytest.approx(ucm.max_incidence, abs=1e-12)


@pytest.mark.parametrize("alpha", [0.25, 0.4, 0.62, 0.75])
def test_ucm_is_mei_with_xi_alpha_over_one_minus_alpha(alpha):
    """UCM(fx, alpha) = Mei(xi = alpha / (1 - alpha), gamma = fx / (1 - alpha)) without distortion: the same
    pixels, rays and domain."""
    ucm = UnifiedCamera(width=640, height=480, fx=184.5, fy=184.2, cx=319.6, cy=240.3, alpha=alpha)
    mei = MeiCamera(
        width=640,
        height=480,
        xi=alpha / (1 - alpha),
        gamma1=184.5 / (1 - alpha),
        gamma2=184.2 / (1 - alpha),
        u0=319.6,
        v0=240.3,
    )
    assert ucm.max_incidence == pytest.approx(mei.max_incidence, abs=1e-12)
    assert ucm.paraxial_focal() == pytest.approx(mei.paraxial_focal(), rel=1e-12)
    d = directions(ucm.max_incidence * (1 - 1e-4), n=3000, seed=9) * 2.5
    uv, ok = ucm.project(d)
    uv_m, ok_m = mei.project(d)
    assert bool(ok.all() and ok_m.all())
    radius = (uv_m - torch.tensor(mei.principal_point, dtype=F64)).norm(dim=-1).clamp_min(1.0)
    assert ((uv - uv_m).norm(dim=-1) / radius).max() < 1e-10  # both cancel near the rim (alpha < 0.5)
    rays, _ = ucm.unproject(uv)
    rays_m, _ = mei.unproject(uv)
    assert angle_between(rays, rays_m).max() < 1e-9
    beyond = at_incidence(np.full(64, ucm.max_incidence * (1 + 1e-6)), azimuths(64))
    assert not bool(ucm.project(beyond)[1].any()) and not bool(mei.project(beyond)[1].any())


def test_fov_paraxial_focal_and_pinhole_limit():
    """Near the axis the FOV model is the pinhole of focal fx 2 tan(w / 2) / w; for w -> 0, the pinhole."""
    cam = UNIFIED_CASES["fov_narrow"]
    fp = cam.fx * 2 * math.tan(cam.w / 2) / cam.w
    assert cam.paraxial_focal()[0] == pytest.approx(fp, rel=1e-15)
    eps = 1e-7
    uv, _ = cam.project(torch.tensor([[eps, 0.0, 1.0]], dtype=F64))
    assert (uv[0, 0].item() - cam.cx) / eps == pytest.approx(fp, rel=1e-9)
    tiny_w = FovCamera(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25, w=1e-6)
    pin = PinholeCamera(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25)
    d = directions(math.radians(60), n=500)
    assert (tiny_w.project(d)[0] - pin.project(d)[0]).abs().max() < 1e-6


# ====================================================================================== exact domains
def unified_rim_points(alpha: float, beta: float, rho: np.ndarray, phi: np.ndarray, factor: float):
    """Points ``z = factor * z_rim`` with the rim ``z_rim = -w sqrt(beta) rho / sqrt(1 - w^2)`` (from
    ``z = -w sqrt(beta rho^2 + z^2)``): ``factor < 1`` inside the domain, ``> 1`` outside."""
    w = alpha / (1 - alpha) if alpha <= 0.5 else (1 - alpha) / alpha
    z = -w * math.sqrt(beta) * rho / math.sqrt(1 - w * w) * factor
    return torch.from_numpy(np.stack((rho * np.cos(phi), rho * np.sin(phi), z), -1))


@pytest.mark.parametrize(
    "alpha,beta",
    [(0.2, 1.0), (0.4, 0.6), (0.55, 0.8), (0.62, 1.0), (0.64, 1.1), (0.8, 2.5), (0.95, 1.0), (1.0, 1.3)],
)
def test_unified_domain_is_exact(alpha, beta):
    """Points 1e-7 inside the rim z = -w d project, 1e-7 outside do not; pixels 1e-9 inside the rim's image
    (alpha > 0.5) get a ray, 1e-9 outside none; for alpha <= 0.5 every pixel has one. The round trip holds
    beyond 90 degrees, out to the rim."""
    cam = ExtendedUnifiedCamera(
        width=400, height=300, fx=150.0, fy=151.0, cx=200.2, cy=149.7, alpha=alpha, beta=beta
    )
    rho, phi = np.random.default_rng(3).uniform(0.1, 20, 400), azimuths(400, seed=3)
    if alpha < 1:
        _, ok = cam.project(unified_rim_points(alpha, beta, rho, phi, 1 - 1e-7))
        assert bool(ok.all())
        _, ok = cam.project(unified_rim_points(alpha, beta, rho, phi, 1 + 1e-7))
        assert not bool(ok.any())
        rim = unified_rim_points(alpha, beta, np.ones(1), np.zeros(1), 1.0)[0]
        assert cam.max_incidence == pytest.approx(math.atan2(rim[0].item(), rim[2].item()), abs=1e-12)
        assert cam.max_incidence > math.pi / 2
    else:  # alpha = 1: w = 0, the domain is z > 0
        assert cam.max_incidence == math.pi / 2
        _, ok = cam.project(torch.tensor([[1.0, 0.0, 1e-9], [1.0, 0.0, -1e-9]], dtype=F64))
        assert ok.tolist() == [True, False]
    if alpha > 0.5:
        r_max = math.sqrt(1 / (beta * (2 * alpha - 1)))
        for factor, expected in ((1 - 1e-9, True), (1.0, True), (1 + 1e-9, False)):  # the rim to rounding
            uv = torch.from_numpy(
                np.stack(
                    (
                        200.2 + 150.0 * r_max * factor * np.cos(phi),
                        149.7 + 151.0 * r_max * factor * np.sin(phi),
                    ),
                    -1,
                )
            )
            rays, ok = cam.unproject(uv)
            assert bool((ok == expected).all()) and torch.isfinite(rays).all()
    else:
        far = torch.tensor([[1e7, -3e6], [-1e5, 1e5]], dtype=F64)
        rays, ok = cam.unproject(far)
        assert bool(ok.all()) and bool((rays[:, 2] < 0).all())  # far pixels look backwards, near the rim
        assert bool(cam.project(rays)[1].all())
    # beyond 90 degrees, out to the rim (alpha < 1), or up to it (alpha = 1)
    low = math.pi / 2 if alpha < 1 else math.radians(80)
    theta = np.random.default_rng(5).uniform(low, cam.max_incidence * (1 - 1e-6), 2000)
    d = at_incidence(theta, azimuths(2000, seed=6))
    uv, ok = cam.project(d)
    rays, ok2 = cam.unproject(uv)
    assert bool(ok.all() and ok2.all()) and angle_between(rays, d).max() < 1e-8


@pytest.mark.parametrize("w", [0.3, 0.9259, 1.05, 2.0, 3.0])
def test_fov_domain_is_everything_but_the_back_axis(w):
    """The atan2 form reaches every incidence below 180 degrees, whatever w: round trip beyond 90 degrees
    to 1e-9 rad; only the axis behind the camera (and the centre) is outside. Pixels with w r_d < pi have a
    ray, the others none."""
    cam = FovCamera(width=640, height=480, fx=230.0, fy=229.6, cx=321.2, cy=238.9, w=w)
    assert cam.max_incidence == math.pi
    theta = np.random.default_rng(5).uniform(math.pi / 2, math.pi * (1 - 1e-7), 2000)
    d = at_incidence(theta, azimuths(2000, seed=6))
    uv, ok = cam.project(d)
    rays, ok2 = cam.unproject(uv)
    assert bool(ok.all() and ok2.all()) and angle_between(rays, d).max() < 1e-9
    edge = torch.tensor(
        [[1e-12, 0.0, -1.0], [0.0, 1e-100, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], dtype=F64
    )
    _, ok = cam.project(edge)
    assert ok.tolist() == [True, True, False, False]
    phi = azimuths(200)
    for factor, expected in ((1 - 1e-9, True), (1 + 1e-9, False)):
        rd = math.pi / w * factor
        uv = torch.from_numpy(
            np.stack((cam.cx + cam.fx * rd * np.cos(phi), cam.cy + cam.fy * rd * np.sin(phi)), -1)
        )
        rays, ok = cam.unproject(uv)
        assert bool((ok == expected).all()) and torch.isfinite(rays).all()
        if expected:  # the last pixels look almost straight back
            assert bool((rays[:, 2] < -0.999999).all())


# ================================================================================= parameter checks
@pytest.mark.parametrize(
    "cls,params,key",
    [
        (UnifiedCamera, dict(alpha=-0.1), "alpha"),
        (UnifiedCamera, dict(alpha=1.1), "alpha"),
        (UnifiedCamera, dict(alpha=float("nan")), "alpha"),
        (ExtendedUnifiedCamera, dict(alpha=1.5, beta=1.0), "alpha"),
        (ExtendedUnifiedCamera, dict(alpha=0.6, beta=0.0), "beta"),
        (ExtendedUnifiedCamera, dict(alpha=0.6, beta=-1.0), "beta"),
        (FovCamera, dict(w=0.0), "w"),
        (FovCamera, dict(w=-0.2), "w"),
        (FovCamera, dict(w=math.pi), "w"),
        (FovCamera, dict(w=4.0), "w"),
        (OpenCVCamera, dict(k5=float("inf")), "k5"),
        (OpenCVCamera, dict(fx=-1.0), "fx"),
    ],
)
def test_bad_parameters_name_the_field(cls, params, key):
    base = dict(width=64, height=48, fx=100.0, fy=100.0, cx=31.5, cy=23.5)
    with pytest.raises(CameraParameterError) as info:
        cls(**{**base, **params})
    assert info.value.key == key and str(info.value).startswith(f"{key}:")


def test_new_models_serialise_by_name():
    for name, cls in (
        ("ucm", UnifiedCamera),
        ("eucm", ExtendedUnifiedCamera),
        ("fov", FovCamera),
        ("opencv", OpenCVCamera),
    ):
        assert cls.model_name == name
    cam = CameraModel.from_dict(
        {
            "model": "opencv",
            "width": 64,
            "height": 48,
            "fx": 50.0,
            "fy": 50.0,
            "cx": 31.5,
            "cy": 23.5,
            "k1": -0.1,
        }
    )
    assert isinstance(cam, OpenCVCamera) and cam.k4 == 0.0 and cam.p2 == 0.0
    assert OpenCVCamera.param_names() == (
        "fx",
        "fy",
        "cx",
        "cy",
        "k1",
        "k2",
        "p1",
        "p2",
        "k3",
        "k4",
        "k5",
        "k6",
    )
    assert UnifiedCamera.param_names() == ("fx", "fy", "cx", "cy", "alpha")
    assert ExtendedUnifiedCamera.param_names() == ("fx", "fy", "cx", "cy", "alpha", "beta")
    assert FovCamera.param_names() == ("fx", "fy", "cx", "cy", "w")
