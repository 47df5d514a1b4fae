"""Camera rigs for the synthetic world: cameras, camera-to-pose extrinsics, LiDAR and the ego body.

Frames follow KITTI-360: the pose frame is x forward, y right, z down; ``cam_to_pose`` maps a camera
into it; the Velodyne pose is ``E_00 @ inv(T_cam0_to_velo)``.

- ``kitti360``: the side-looking Mei fisheyes image_02 (left) and image_03 (right) with KITTI-360's real
  calibration scaled to the render size and its real extrinsics.
- ``surround4``: four fisheyes looking left (image_02, Mei), right (image_03, Mei), front (image_04,
  Kannala-Brandt) and back (image_05, Kannala-Brandt), like a robot's surround rig.
- ``stereo``: a stereo pair of fisheyes whose views overlap, on the car's front like a robot's head:
  image_02 (left) and image_03 (right), KITTI-360's Mei intrinsics, :data:`STEREO_BASELINE` apart and
  each turned :data:`STEREO_YAW` degrees outward from straight ahead (their optical axes 40 degrees
  apart); the rig's other camera is a source at the same instant (``rig_offsets: [0]``) where nothing
  moves.

In the indoor scene the same cameras look the same ways from a compact hand-held rig: every camera and the
LiDAR within ``indoor.RIG_RADIUS`` of the body's origin, and no vehicle body in view.

``random_cameras=True`` draws each camera anew from ``seed`` (:func:`random_camera`): its model family
(Mei, Kannala-Brandt, double sphere, Fisheye624, UCM, EUCM, FOV, or a wide-angle pinhole with OpenCV's
rational distortion), focal length (from a field of view), principal point
(a small offset), distortion within the family's usual range, and its mounting height and tilt; every
drawn camera is checked to project monotonically over its field of view (:func:`camera_is_valid`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ..cameras import CAMERA_MODELS, CameraModel, KannalaBrandtCamera, MeiCamera
from ..data.kitti360.presets import KITTI360_CAM0_TO_VELO, KITTI360_CAM_TO_POSE, kitti360_camera
from ..geometry import make_pose, pose_from_3x4

RIGS = ("kitti360", "surround4", "stereo")
STEREO_BASELINE = 0.2  # metres between the stereo rig's two cameras
STEREO_YAW = 20.0  # degrees each of them is turned outward from straight ahead
FAMILIES = ("mei", "kannala_brandt", "double_sphere", "fisheye624", "ucm", "eucm", "fov", "opencv")
# Incidence of the ray at the image's left and right edges (degrees): fisheyes of 150-200 degrees; the
# pinhole with OpenCV's distortion is a wide-angle lens of 100-124 degrees (it cannot reach 90 degrees).
EDGE_INCIDENCE = {"opencv": (50.0, 62.0)}
FISHEYE_EDGE = (75.0, 100.0)

# The ego vehicle's body as boxes in the pose frame (z down; the ground is at z = +0.73): a cabin with
# the roof 0.37 m below the side fisheyes, and a lower body (bonnet, boot, flanks). The lower part of the
# side fisheyes' images sees the roof and flanks, as in KITTI-360.
EGO_BODY = (
    (np.array([-1.9, -0.62, -0.70]), np.array([0.95, 1.22, 0.55])),
    (np.array([-3.4, -0.70, -0.15]), np.array([1.65, 1.30, 0.55])),
)


def _pose(values) -> np.ndarray:
    return pose_from_3x4(np.asarray(values, dtype=np.float64)).numpy()


def _looking(forward, right, position) -> np.ndarray:
    """Camera-to-pose for a camera whose optical axis is ``forward`` and image x axis ``right``."""
    z, x = np.asarray(forward, float), np.asarray(right, float)
    return make_pose(np.stack((x, np.cross(z, x), z), 1), position).numpy()


@dataclasses.dataclass
class Rig:
    name: str
    cameras: dict[str, CameraModel]  # render-size cameras, as a reader interprets the written files
    written: dict[str, CameraModel]  # what calibration/image_0X.yaml holds (KITTI-360: with p1/p2)
    cam_to_pose: dict[str, np.ndarray]  # every line of calib_cam_to_pose.txt
    cam0_to_velo: np.ndarray
    ego: bool = True  # the ego vehicle's body is in view (EGO_BODY)

    @property
    def velo_to_pose(self) -> np.ndarray:
        return self.cam_to_pose["image_00"] @ np.linalg.inv(self.cam0_to_velo)


def make_rig(name: str, size: int, scene: str = "street", random_cameras: bool = False, seed: int = 0) -> Rig:
    """The rig ``name`` with images of ``size`` x ``size`` pixels: mounted on the car (``scene``
    "street") or hand-held ("indoor"); ``random_cameras``: every camera drawn anew from ``seed``."""
    rig = _fixed_rig(name, size)
    if scene == "indoor":
        rig = _handheld(rig)
    elif scene != "street":
        raise ValueError(f"unknown scene {scene!r}; one of ('street', 'indoor')")
    if random_cameras:
        rig = _randomised(rig, size, seed, scene)
    return rig


def _fixed_rig(name: str, size: int) -> Rig:
    if name not in RIGS:
        raise ValueError(f"unknown rig {name!r}; one of {RIGS}")
    cam_to_pose = {k: _pose(v) for k, v in KITTI360_CAM_TO_POSE.items()}
    written = {f"image_0{i}": kitti360_camera(i, tangential=True).resize(size, size) for i in (2, 3)}
    cameras = {f"image_0{i}": kitti360_camera(i).resize(size, size) for i in (2, 3)}
    if name == "surround4":
        f = 0.27 * size
        for cam_name, forward, right, position in (
            ("image_04", (1, 0, 0), (0, 1, 0), (1.7, 0.3, -0.95)),
            ("image_05", (-1, 0, 0), (0, -1, 0), (-3.5, 0.3, -0.95)),
        ):
            cam = KannalaBrandtCamera(
                width=size,
                height=size,
                fx=f,
                fy=f,
                cx=(size - 1) / 2,
                cy=(size - 1) / 2,
                k1=0.02,
                k2=-0.004,
                k3=0.0005,
                k4=0.0,
            )
            cameras[cam_name] = written[cam_name] = cam
            cam_to_pose[cam_name] = _looking(forward, right, position)
    if name == "stereo":
        for cam_name, side in (("image_02", -1.0), ("image_03", 1.0)):  # pose frame: y right
            yaw = math.radians(STEREO_YAW) * side
            forward = (math.cos(yaw), math.sin(yaw), 0.0)
            right = (-math.sin(yaw), math.cos(yaw), 0.0)
            cam_to_pose[cam_name] = _looking(forward, right, (1.7, side * STEREO_BASELINE / 2, -0.95))
    return Rig(name, cameras, written, cam_to_pose, _pose(KITTI360_CAM0_TO_VELO))


# ----------------------------------------------------------------------------------- hand-held (indoor)
def _handheld(rig: Rig) -> Rig:
    """The same cameras looking the same ways, 8 cm from the body's origin along their (horizontal) view
    direction; the LiDAR 12 cm above the origin, upright; no vehicle body."""
    cam_to_pose = {}
    for name, T in rig.cam_to_pose.items():
        forward = T[:3, 2] * np.array([1.0, 1.0, 0.0])
        offset = 0.08 * forward / max(np.linalg.norm(forward), 1e-9)
        if rig.name == "stereo":  # the pair keeps its baseline
            offset = offset + np.array([0.0, T[1, 3], 0.0])
        if name in ("image_00", "image_01"):  # the perspective pair: not rendered, image_00 anchors the LiDAR
            offset = np.array([0.0, 0.0 if name == "image_00" else 0.1, 0.0])
        cam_to_pose[name] = make_pose(T[:3, :3], offset).numpy()
    velo_to_pose = np.diag([1.0, -1.0, -1.0, 1.0])  # Velodyne x forward, y left, z up; pose z down
    velo_to_pose[2, 3] = -0.12
    cam0_to_velo = np.linalg.inv(velo_to_pose) @ cam_to_pose["image_00"]
    return Rig(rig.name, rig.cameras, rig.written, cam_to_pose, cam0_to_velo, ego=False)


# ----------------------------------------------------------------------------------- random cameras
def _unit_radius(family: str, params: dict, theta: float) -> float:
    """The normalised image radius (focal 1, principal point 0) of a ray at incidence ``theta``."""
    cam = _camera(family, params, 1.0, 1.0, 0.0, 0.0, 64)
    point = torch.tensor([[math.sin(theta), 0.0, math.cos(theta)]], dtype=torch.float64)
    uv, ok = cam.project(point)
    return float(uv[0, 0]) if bool(ok[0]) else math.nan


def _camera(family: str, params: dict, fx: float, fy: float, cx: float, cy: float, size: int) -> CameraModel:
    if family == "mei":
        return MeiCamera(width=size, height=size, gamma1=fx, gamma2=fy, u0=cx, v0=cy, **params)
    return CAMERA_MODELS[family](width=size, height=size, fx=fx, fy=fy, cx=cx, cy=cy, **params)


def _distortion(rng: np.random.Generator, family: str, edge: float) -> dict:
    """Distortion parameters within the family's usual range (calibrated fisheyes of 150-200 degrees);
    Mei's radial terms scaled to the mirror radius of the image edge (incidence ``edge``), so that they
    change the edge's radius by at most about 25 %, as in calibrated fisheyes."""
    u = rng.uniform
    if family == "mei":
        xi = u(0.6, 2.2)
        r2 = (math.sin(edge) / (math.cos(edge) + xi)) ** 2
        return {"xi": xi, "k1": u(-0.15, 0.15) / r2, "k2": u(0.0, 0.1) / r2**2}
    if family == "kannala_brandt":
        return {"k1": u(-0.03, 0.03), "k2": u(-0.01, 0.01), "k3": u(-0.003, 0.003), "k4": u(-5e-4, 5e-4)}
    if family == "double_sphere":
        return {"xi": u(-0.3, 0.15), "alpha": u(0.45, 0.65)}
    if family == "ucm":
        return {"alpha": u(0.5, 0.7)}
    if family == "eucm":
        return {"alpha": u(0.5, 0.7), "beta": u(0.8, 1.3)}
    if family == "fov":
        return {"w": u(0.8, 1.1)}
    if family == "opencv":  # a wide-angle lens's barrel distortion, rational terms of either sign
        return {
            "k1": u(-0.3, -0.05), "k2": u(0.0, 0.08), "p1": u(-1e-3, 1e-3), "p2": u(-1e-3, 1e-3),
            "k3": u(-0.01, 0.0), "k4": u(-0.05, 0.05), "k5": u(-0.01, 0.01), "k6": u(-0.002, 0.002),
        }  # fmt: skip
    return {
        "k0": u(-0.03, 0.03), "k1": u(-0.01, 0.01), "k2": u(-0.003, 0.003), "k3": u(-3e-4, 3e-4),
        "k4": u(-3e-5, 3e-5), "k5": u(-3e-6, 3e-6), "p0": u(-5e-4, 5e-4), "p1": u(-5e-4, 5e-4),
        "s0": u(-5e-4, 5e-4), "s1": u(-1e-4, 1e-4), "s2": u(-5e-4, 5e-4), "s3": u(-1e-4, 1e-4),
    }  # fmt: skip


def camera_is_valid(camera: CameraModel, azimuths: int = 16, steps: int = 200) -> bool:
    """Whether ``camera`` projects monotonically over its field of view: along every azimuth, rays from
    the optical axis out to the largest incidence any of its pixels sees project ever farther from the
    principal point, inside the model's domain, and unproject back to themselves; and at least half of
    the image has a ray."""
    if camera.pixel_coverage() < 0.5:
        return False
    # the widest ray lies on the image's border (the incidence grows away from the principal point)
    u = torch.arange(camera.width, dtype=torch.float64)
    v = torch.arange(camera.height, dtype=torch.float64)
    border = torch.cat(
        [torch.stack((u, torch.full_like(u, e)), -1) for e in (0.0, camera.height - 1.0)]
        + [torch.stack((torch.full_like(v, e), v), -1) for e in (0.0, camera.width - 1.0)]
    )
    rays, valid = camera.unproject(border)
    fov = float(torch.acos(rays[..., 2][valid].clamp(-1, 1)).max()) if bool(valid.any()) else 0.0
    if not fov < camera.max_incidence:
        fov = camera.max_incidence - 1e-3
    theta = torch.linspace(1e-3, fov, steps, dtype=torch.float64)[:, None]
    phi = torch.linspace(0, 2 * math.pi, azimuths + 1, dtype=torch.float64)[:-1][None]
    points = torch.stack(
        (
            torch.sin(theta) * torch.cos(phi),
            torch.sin(theta) * torch.sin(phi),
            torch.cos(theta).expand(-1, azimuths),
        ),
        -1,
    )
    uv, ok = camera.project(points)
    if not bool(ok.all()):
        return False
    radius = (uv - torch.tensor(camera.principal_point, dtype=torch.float64)).norm(dim=-1)
    if not bool((radius.diff(dim=0) > 0).all()):
        return False
    back, ok = camera.unproject(uv)
    return bool(ok.all()) and float((back - points).norm(dim=-1).max()) < 1e-6


def random_camera(rng: np.random.Generator, family: str, size: int) -> CameraModel:
    """A valid camera of ``family`` for ``size`` x ``size`` images: the ray at the image's left and right
    edges has an incidence of 75-100 degrees (a 150-200 degree horizontal field of view; 50-62 degrees
    for ``opencv``'s pinhole), the focal differs by up to 1 % between the axes, the principal point is up
    to 2 % of the size off the centre."""
    if family not in FAMILIES:
        raise ValueError(f"unknown camera family {family!r}; one of {FAMILIES}")
    for _ in range(200):
        edge = math.radians(rng.uniform(*EDGE_INCIDENCE.get(family, FISHEYE_EDGE)))
        params = _distortion(rng, family, edge)
        aspect, offset = rng.uniform(-0.01, 0.01), rng.uniform(-0.02, 0.02, 2) * size
        radius = _unit_radius(family, params, edge)
        if not radius > 0:  # the edge ray is outside this model's domain
            continue
        fx = (size / 2) / radius
        centre = (size - 1) / 2
        camera = _camera(family, params, fx, fx * (1 + aspect), centre + offset[0], centre + offset[1], size)
        equidistant = (size / 2) / edge  # the focal of an equidistant fisheye of this field of view
        usual = 0.6 < min(camera.paraxial_focal()) / equidistant < 1.6
        if usual and camera.max_incidence > edge + math.radians(2) and camera_is_valid(camera):
            return camera
    raise RuntimeError(f"no valid {family} camera drawn in 200 tries")  # cannot happen with these ranges


def _tilted(T: np.ndarray, tilt: float, lift: float) -> np.ndarray:
    """``T`` (camera to pose) tilted by ``tilt`` radians about the camera's x axis (down for positive) and
    raised by ``lift`` metres (the pose frame's z points down)."""
    c, s = math.cos(tilt), math.sin(tilt)
    R = T[:3, :3] @ np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
    return make_pose(R, T[:3, 3] - np.array([0.0, 0.0, lift])).numpy()


def _randomised(rig: Rig, size: int, seed: int, scene: str) -> Rig:
    """Every rendered camera drawn anew: family, intrinsics (:func:`random_camera`), mounting height
    (+-15 cm on the car, +-5 cm hand-held) and tilt (+-10 degrees on the car, +-15 hand-held)."""
    rng = np.random.default_rng([seed, 11, 0 if scene == "street" else 1])  # a room's cameras differ too
    lift, tilt = (0.15, 10.0) if scene == "street" else (0.05, 15.0)
    cameras, cam_to_pose = {}, dict(rig.cam_to_pose)
    for name in rig.cameras:
        family = FAMILIES[int(rng.integers(len(FAMILIES)))]
        cameras[name] = random_camera(rng, family, size)
        cam_to_pose[name] = _tilted(
            rig.cam_to_pose[name], math.radians(rng.uniform(-tilt, tilt)), rng.uniform(-lift, lift)
        )
        if not camera_is_valid(cameras[name]):
            raise AssertionError(f"{name}: drew an invalid camera {cameras[name]}")
    return dataclasses.replace(rig, cameras=cameras, written=dict(cameras), cam_to_pose=cam_to_pose)
