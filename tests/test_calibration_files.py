"""Calibration tools' multi-camera files: Kalibr camchains and Basalt calibration JSON, read into the
project's cameras and camera -> body transforms, and a rig.yaml that takes its cameras from one.

Every fixture is written here with realistic numbers (EuRoC / TUM-VI-like calibrations); each camera's
projection is checked against one computed by hand (or by OpenCV) from the file's own numbers."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import CAMERA_MODELS, CalibrationError
from fisheyedepth.cameras.calibration_files import (
    CalibratedCamera,
    read_basalt,
    read_calibration,
    read_kalibr,
)
from fisheyedepth.data.layouts import RigLayout

from conftest import quaternion_xyzw


# ----------------------------------------------------------------------------------- geometry helpers
def rot(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {
        "x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]),
        "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
        "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]),
    }[axis]


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def inv(T: np.ndarray) -> np.ndarray:
    return np.linalg.inv(T)


def apply(T: np.ndarray, p) -> np.ndarray:
    return T[:3, :3] @ np.asarray(p, float) + T[:3, 3]


# A camera looking forward along the body's x (camera x = -body y, camera y = -body z).
FORWARD = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def project(camera, points) -> np.ndarray:
    uv, valid = camera.project(torch.tensor(np.asarray(points, float), dtype=torch.float64))
    assert bool(valid.all())
    return uv.numpy()


# ------------------------------------------------------------------------- projections by hand (numpy)
def mei_uv(p, xi, fu, fv, pu, pv, k1=0.0, k2=0.0, p1=0.0, p2=0.0):
    p = np.asarray(p, float)
    s = p / np.linalg.norm(p, axis=-1, keepdims=True)
    x, y = s[:, 0] / (s[:, 2] + xi), s[:, 1] / (s[:, 2] + xi)
    r2 = x * x + y * y
    rad = 1 + k1 * r2 + k2 * r2 * r2
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack((fu * xd + pu, fv * yd + pv), -1)


def ds_uv(p, xi, alpha, fx, fy, cx, cy):
    x, y, z = np.asarray(p, float).T
    d1 = np.sqrt(x * x + y * y + z * z)
    d2 = np.sqrt(x * x + y * y + (xi * d1 + z) ** 2)
    den = alpha * d2 + (1 - alpha) * (xi * d1 + z)
    return np.stack((fx * x / den + cx, fy * y / den + cy), -1)


def eucm_uv(p, alpha, beta, fx, fy, cx, cy):
    x, y, z = np.asarray(p, float).T
    den = alpha * np.sqrt(beta * (x * x + y * y) + z * z) + (1 - alpha) * z
    return np.stack((fx * x / den + cx, fy * y / den + cy), -1)


def ucm_uv(p, alpha, fx, fy, cx, cy):
    return eucm_uv(p, alpha, 1.0, fx, fy, cx, cy)


def fov_uv(p, w, fx, fy, cx, cy):
    x, y, z = np.asarray(p, float).T
    ru = np.sqrt(x * x + y * y) / z
    on_axis = ru == 0  # the limit of atan(2 ru tan(w / 2)) / (w ru): 2 tan(w / 2) / w
    safe = np.where(on_axis, 1.0, ru)
    scale = np.where(on_axis, 2 * math.tan(w / 2) / w, np.arctan(2 * safe * math.tan(w / 2)) / (w * safe))
    return np.stack((fx * x / z * scale + cx, fy * y / z * scale + cy), -1)


def pinhole_uv(p, fx, fy, cx, cy):
    x, y, z = np.asarray(p, float).T
    return np.stack((fx * x / z + cx, fy * y / z + cy), -1)


def cv_pinhole_uv(p, fx, fy, cx, cy, dist):
    cv2 = pytest.importorskip("cv2")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    uv, _ = cv2.projectPoints(
        np.asarray(p, float).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, np.array(dist)
    )
    return uv.reshape(-1, 2)


def cv_fisheye_uv(p, fx, fy, cx, cy, dist):
    cv2 = pytest.importorskip("cv2")
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    pts = np.asarray(p, float).reshape(-1, 1, 3)
    uv, _ = cv2.fisheye.projectPoints(pts, np.zeros((3, 1)), np.zeros((3, 1)), K, np.array(dist))
    return uv.reshape(-1, 2)


NEAR = [[0.31, -0.22, 1.0], [-0.52, 0.38, 1.6], [0.05, 0.61, 2.3], [0.0, 0.0, 4.0]]  # within ~35 degrees
WIDE = [*NEAR, [1.9, -0.4, 1.0], [-1.2, -1.6, 0.7]]  # up to ~72 degrees: for the fisheyes


# ------------------------------------------------------------------------------------ Kalibr fixtures
def matrix_yaml(T: np.ndarray, indent: str = "  ") -> str:
    return "".join(f"{indent}- [{', '.join(repr(float(v)) for v in row)}]\n" for row in T)


def camchain_text(cameras: list[dict]) -> str:
    """A camchain in Kalibr's layout: cameras are dicts of camera_model, distortion_model, intrinsics,
    distortion_coeffs, resolution and optional 4x4 T_cam_imu / T_cn_cnm1 (numpy)."""
    out = []
    for i, cam in enumerate(cameras):
        out.append(f"cam{i}:\n")
        for key in ("T_cam_imu", "T_cn_cnm1"):
            if key in cam:
                out.append(f"  {key}:\n" + matrix_yaml(cam[key]))
        out.append(f"  cam_overlaps: {[j for j in range(len(cameras)) if j != i]}\n")
        for key in ("camera_model", "distortion_coeffs", "distortion_model", "intrinsics", "resolution"):
            if key in cam:
                value = cam[key]
                if isinstance(value, list):
                    value = "[" + ", ".join(repr(v) for v in value) + "]"
                out.append(f"  {key}: {value}\n")
        out.append(f"  rostopic: /cam{i}/image_raw\n")
        if "T_cam_imu" in cam:
            out.append("  timeshift_cam_imu: 0.0019837\n")
    return "".join(out)


# camchain-imucam: four cameras around an IMU; T_imu_cam (the camera's pose in the IMU frame) is known
IMU_POSES = [
    pose(rot("z", 0) @ rot("x", -4) @ FORWARD, [0.085, 0.021, 0.012]),
    pose(rot("z", 90) @ rot("x", 7) @ FORWARD, [0.013, 0.092, -0.004]),
    pose(rot("z", 180) @ rot("y", 3) @ FORWARD, [-0.081, -0.018, 0.015]),
    pose(rot("z", -90) @ rot("x", -11) @ FORWARD, [0.009, -0.095, 0.006]),
]
IMUCAM = [
    {
        "camera_model": "pinhole",
        "distortion_model": "radtan",
        "intrinsics": [458.654, 457.296, 367.215, 248.375],
        "distortion_coeffs": [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
        "resolution": [752, 480],
    },
    {
        "camera_model": "pinhole",
        "distortion_model": "equidistant",
        "intrinsics": [380.81, 380.12, 510.29, 514.31],
        "distortion_coeffs": [0.0103, -0.0021, 0.0006, -0.0001],
        "resolution": [1024, 1024],
    },
    {
        "camera_model": "omni",
        "distortion_model": "radtan",
        "intrinsics": [1.7257, 1007.3, 1006.9, 639.5, 511.2],
        "distortion_coeffs": [-0.0413, 0.0197, 0.0004, -0.0002],
        "resolution": [1280, 1024],
    },
    {
        "camera_model": "ds",
        "distortion_model": "none",
        "intrinsics": [-0.2409, 0.567, 349.75, 348.72, 365.89, 249.33],
        "distortion_coeffs": [],
        "resolution": [752, 480],
    },
]

# camchain without an IMU: four cameras chained by T_cn_cnm1, with rotations that do not commute
CHAIN_STEPS = [  # T_cnm1_cn: camera n in camera n-1
    None,
    pose(rot("y", 35) @ rot("x", 10), [0.11, 0.0, -0.02]),
    pose(rot("x", -25) @ rot("z", 50), [0.0, 0.09, 0.03]),
    pose(rot("z", 70) @ rot("y", -15), [-0.05, 0.02, 0.12]),
]
CHAIN = [
    {
        "camera_model": "pinhole",
        "distortion_model": "fov",
        "intrinsics": [420.3, 419.8, 320.4, 240.6],
        "distortion_coeffs": [0.925],
        "resolution": [640, 480],
    },
    {
        "camera_model": "eucm",
        "distortion_model": "none",
        "intrinsics": [0.6351, 1.0453, 357.2, 356.9, 376.1, 240.2],
        "distortion_coeffs": [],
        "resolution": [752, 480],
    },
    {
        "camera_model": "omni",
        "distortion_model": "none",
        "intrinsics": [0.9, 560.1, 559.7, 512.3, 383.8],
        "distortion_coeffs": [],
        "resolution": [1024, 768],
    },
    {
        "camera_model": "pinhole",
        "distortion_model": "none",
        "intrinsics": [500.0, 501.0, 319.5, 239.5],
        "distortion_coeffs": [],
        "resolution": [640, 480],
    },
]


def imucam_cameras() -> list[dict]:
    cams = [dict(c) for c in IMUCAM]
    for i, cam in enumerate(cams):
        cam["T_cam_imu"] = inv(IMU_POSES[i])
        if i:  # Kalibr writes both: T_cn_cnm1 = T_cn_imu @ T_imu_cnm1
            cam["T_cn_cnm1"] = inv(IMU_POSES[i]) @ IMU_POSES[i - 1]
    return cams


def chain_cameras() -> list[dict]:
    cams = [dict(c) for c in CHAIN]
    for i in range(1, len(cams)):
        cams[i]["T_cn_cnm1"] = inv(CHAIN_STEPS[i])
    return cams


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


# ------------------------------------------------------------------------------------ Kalibr: cameras
def test_kalibr_imucam_models_fields_and_projections(tmp_path):
    cams = read_kalibr(write(tmp_path / "camchain-imucam.yaml", camchain_text(imucam_cameras())))
    assert [c.name for c in cams] == ["cam0", "cam1", "cam2", "cam3"]
    assert all(isinstance(c, CalibratedCamera) and c.body == "imu" for c in cams)
    assert [c.topic for c in cams] == [f"/cam{i}/image_raw" for i in range(4)]
    radtan, equi, omni, ds = (c.camera for c in cams)

    # pinhole-radtan -> opencv: fu fv pu pv, k1 k2 r1 r2 (k3 = 0)
    assert isinstance(radtan, CAMERA_MODELS["opencv"]) and (radtan.width, radtan.height) == (752, 480)
    fx, fy, cx, cy = IMUCAM[0]["intrinsics"]
    k1, k2, p1, p2 = IMUCAM[0]["distortion_coeffs"]
    assert (radtan.fx, radtan.fy, radtan.cx, radtan.cy) == (fx, fy, cx, cy)
    assert (radtan.k1, radtan.k2, radtan.p1, radtan.p2, radtan.k3) == (k1, k2, p1, p2, 0.0)
    assert np.allclose(
        project(radtan, NEAR), cv_pinhole_uv(NEAR, fx, fy, cx, cy, [k1, k2, p1, p2]), atol=1e-6
    )

    # pinhole-equidistant -> kannala_brandt, as cv2.fisheye
    assert equi.model_name == "kannala_brandt" and (equi.width, equi.height) == (1024, 1024)
    fx, fy, cx, cy = IMUCAM[1]["intrinsics"]
    D = IMUCAM[1]["distortion_coeffs"]
    assert (equi.fx, equi.fy, equi.cx, equi.cy, equi.k1, equi.k2, equi.k3, equi.k4) == (fx, fy, cx, cy, *D)
    assert np.allclose(project(equi, WIDE), cv_fisheye_uv(WIDE, fx, fy, cx, cy, D), atol=1e-6)

    # omni-radtan -> mei: [xi fu fv pu pv] -> xi gamma1 gamma2 u0 v0; [k1 k2 r1 r2] -> k1 k2 p1 p2
    xi, fu, fv, pu, pv = IMUCAM[2]["intrinsics"]
    k1, k2, p1, p2 = IMUCAM[2]["distortion_coeffs"]
    assert omni.model_name == "mei" and (omni.width, omni.height) == (1280, 1024)
    assert (omni.xi, omni.gamma1, omni.gamma2, omni.u0, omni.v0) == (xi, fu, fv, pu, pv)
    assert (omni.k1, omni.k2, omni.p1, omni.p2) == (k1, k2, p1, p2)
    assert np.allclose(project(omni, WIDE), mei_uv(WIDE, xi, fu, fv, pu, pv, k1, k2, p1, p2), atol=1e-6)

    # ds-none -> double_sphere: [xi alpha fu fv pu pv]
    xi, alpha, fx, fy, cx, cy = IMUCAM[3]["intrinsics"]
    assert ds.model_name == "double_sphere"
    assert (ds.xi, ds.alpha, ds.fx, ds.fy, ds.cx, ds.cy) == (xi, alpha, fx, fy, cx, cy)
    assert np.allclose(project(ds, WIDE), ds_uv(WIDE, xi, alpha, fx, fy, cx, cy), atol=1e-6)


def test_kalibr_chain_models_fields_and_projections(tmp_path):
    cams = read_kalibr(write(tmp_path / "camchain.yaml", camchain_text(chain_cameras())))
    fov, eucm, omni, pinhole = (c.camera for c in cams)
    assert all(c.body == "cam0" for c in cams)

    fx, fy, cx, cy = CHAIN[0]["intrinsics"]
    (w,) = CHAIN[0]["distortion_coeffs"]
    assert isinstance(fov, CAMERA_MODELS["fov"]) and (fov.fx, fov.fy, fov.cx, fov.cy, fov.w) == (
        fx,
        fy,
        cx,
        cy,
        w,
    )
    assert np.allclose(project(fov, NEAR), fov_uv(NEAR, w, fx, fy, cx, cy), atol=1e-6)

    alpha, beta, fx, fy, cx, cy = CHAIN[1]["intrinsics"]
    assert isinstance(eucm, CAMERA_MODELS["eucm"])
    assert (eucm.alpha, eucm.beta, eucm.fx, eucm.fy, eucm.cx, eucm.cy) == (alpha, beta, fx, fy, cx, cy)
    assert np.allclose(project(eucm, WIDE), eucm_uv(WIDE, alpha, beta, fx, fy, cx, cy), atol=1e-6)

    xi, fu, fv, pu, pv = CHAIN[2]["intrinsics"]
    assert omni.model_name == "mei" and (omni.k1, omni.k2, omni.p1, omni.p2) == (0, 0, 0, 0)
    assert np.allclose(project(omni, WIDE), mei_uv(WIDE, xi, fu, fv, pu, pv), atol=1e-6)

    assert pinhole.model_name == "pinhole" and (pinhole.width, pinhole.height) == (640, 480)
    assert np.allclose(project(pinhole, NEAR), pinhole_uv(NEAR, *CHAIN[3]["intrinsics"]), atol=1e-9)


# --------------------------------------------------------------------------------- Kalibr: extrinsics
def test_kalibr_extrinsics_from_t_cam_imu(tmp_path):
    cams = read_kalibr(write(tmp_path / "camchain-imucam.yaml", camchain_text(imucam_cameras())))
    for cam, T_imu_cam in zip(cams, IMU_POSES, strict=True):
        assert cam.cam_to_body.dtype == np.float64 and cam.cam_to_body.shape == (4, 4)
        assert np.allclose(cam.cam_to_body, T_imu_cam, atol=1e-12)
    # cam1 looks left (+y of the IMU), rolled 7 degrees about its axis: a point 2 m ahead of it lies 2 m
    # to the left of its centre; 1 m to its right (camera x) lies ahead (+x), 7 degrees down
    t = np.array([0.013, 0.092, -0.004])
    assert np.allclose(apply(cams[1].cam_to_body, [0.0, 0.0, 2.0]), t + [0.0, 2.0, 0.0], atol=1e-12)
    c, s = math.cos(math.radians(7)), math.sin(math.radians(7))
    assert np.allclose(apply(cams[1].cam_to_body, [1.0, 0.0, 0.0]), t + [c, 0.0, -s], atol=1e-12)


def test_kalibr_chain_composes_previous_to_current(tmp_path):
    """T_cn_cnm1 maps camera n-1 to camera n: the pose of cam2 in cam0 is T_c0_c1 @ T_c1_c2, which
    differs from the other order with these rotations."""
    cams = read_kalibr(write(tmp_path / "camchain.yaml", camchain_text(chain_cameras())))
    T01, T12, T23 = CHAIN_STEPS[1:]
    assert np.allclose(cams[0].cam_to_body, np.eye(4))
    assert np.allclose(cams[1].cam_to_body, T01, atol=1e-12)
    assert np.allclose(cams[2].cam_to_body, T01 @ T12, atol=1e-12)
    assert np.allclose(cams[3].cam_to_body, T01 @ T12 @ T23, atol=1e-12)
    assert not np.allclose(T01 @ T12, T12 @ T01, atol=1e-3)  # the order matters
    # a point 1.5 m in front of cam2, placed by hand: first into cam1, then into cam0
    p_cam2 = np.array([0.2, -0.1, 1.5])
    p_cam1 = CHAIN_STEPS[2][:3, :3] @ p_cam2 + CHAIN_STEPS[2][:3, 3]
    p_cam0 = CHAIN_STEPS[1][:3, :3] @ p_cam1 + CHAIN_STEPS[1][:3, 3]
    assert np.allclose(apply(cams[2].cam_to_body, p_cam2), p_cam0, atol=1e-12)


def test_kalibr_chain_from_the_imu_and_disagreement_warned(tmp_path, caplog):
    """In the IMU frame a camera without its own T_cam_imu is chained to the previous one; a T_cam_imu
    that contradicts the chain is used, with a warning."""
    cams = imucam_cameras()
    del cams[2]["T_cam_imu"]
    read = read_kalibr(write(tmp_path / "a.yaml", camchain_text(cams)))
    assert np.allclose(read[2].cam_to_body, IMU_POSES[2], atol=1e-12)
    cams = imucam_cameras()
    cams[3]["T_cam_imu"] = inv(IMU_POSES[3] @ pose(np.eye(3), [0.01, 0, 0]))  # 1 cm off the chain
    with caplog.at_level(logging.WARNING):
        read = read_kalibr(write(tmp_path / "b.yaml", camchain_text(cams)))
    assert "cam3: T_cam_imu and the T_cn_cnm1 chain disagree by 0.0100 m" in caplog.text
    assert np.allclose(read[3].cam_to_body, IMU_POSES[3] @ pose(np.eye(3), [0.01, 0, 0]), atol=1e-12)


# ------------------------------------------------------------------------------------ Kalibr: refusals
def refused(tmp_path, cameras, *expected: str, name="camchain.yaml") -> None:
    path = write(tmp_path / name, camchain_text(cameras) if isinstance(cameras, list) else cameras)
    with pytest.raises(CalibrationError) as info:
        read_kalibr(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    for part in expected:
        assert part in message, message


@pytest.mark.parametrize(
    "camera_model, distortion_model, coeffs",
    [("omni", "equidistant", [0.1, 0, 0, 0]), ("ds", "radtan", [0.1, 0, 0, 0]), ("scaramuzza", "none", [])],
)
def test_kalibr_unsupported_combinations_are_named(tmp_path, camera_model, distortion_model, coeffs):
    cams = imucam_cameras()
    cams[2].update(camera_model=camera_model, distortion_model=distortion_model, distortion_coeffs=coeffs)
    refused(
        tmp_path,
        cams,
        "key 'cam2'",
        f"camera_model '{camera_model}' with distortion_model '{distortion_model}'",
        f"({camera_model}-{distortion_model}) is not supported",
        "pinhole-radtan",
    )


def test_kalibr_bad_fields_are_named(tmp_path):
    cams = imucam_cameras()
    cams[2]["intrinsics"] = [1007.3, 1006.9, 639.5, 511.2]  # the omni's xi left out
    refused(
        tmp_path, cams, "key 'cam2.intrinsics'", "expected 5 numbers [xi fu fv pu pv] for omni-radtan, got 4"
    )
    cams = imucam_cameras()
    cams[0]["distortion_coeffs"] = [-0.28, 0.07, 0.0002, 0.00002, 0.001]  # radtan5 is not Kalibr's radtan
    refused(
        tmp_path, cams, "key 'cam0.distortion_coeffs'", "expected 4 numbers [k1 k2 r1 r2] for pinhole-radtan"
    )
    cams = imucam_cameras()
    cams[3]["distortion_coeffs"] = [0.1]
    refused(tmp_path, cams, "key 'cam3.distortion_coeffs'", "expected 0 numbers")
    cams = imucam_cameras()
    del cams[1]["resolution"]
    refused(tmp_path, cams, "key 'cam1.resolution'", "missing")
    cams = imucam_cameras()
    cams[1]["resolution"] = [1024.5, 1024]
    refused(tmp_path, cams, "key 'cam1.resolution'", "width must be a positive whole number")
    cams = imucam_cameras()
    cams[1]["intrinsics"] = [380.81, "380.12", 510.29, 514.31]
    refused(tmp_path, cams, "key 'cam1.intrinsics[1]'", "expected a finite number")
    cams = imucam_cameras()
    del cams[2]["camera_model"]
    refused(tmp_path, cams, "key 'cam2.camera_model'", "missing")
    cams = imucam_cameras()
    cams[3]["intrinsics"] = [-0.2409, 1.3, 349.75, 348.72, 365.89, 249.33]  # alpha outside [0, 1)
    refused(tmp_path, cams, "key 'cam3.intrinsics[1] (alpha)'", "must lie in [0, 1), got 1.3")


def test_kalibr_bad_transforms_are_named(tmp_path):
    cams = imucam_cameras()
    cams[1]["T_cam_imu"] = cams[1]["T_cam_imu"] @ np.diag([1.0, 1.0, 1.2, 1.0])  # scaled
    refused(tmp_path, cams, "key 'cam1.T_cam_imu'", "not a rigid transform")
    cams = imucam_cameras()
    cams[2]["T_cn_cnm1"] = cams[2]["T_cn_cnm1"] @ np.diag([1.0, -1.0, 1.0, 1.0])  # mirrored
    refused(tmp_path, cams, "key 'cam2.T_cn_cnm1'", "not a rigid transform")
    cams = imucam_cameras()
    cams[0]["T_cam_imu"] = cams[0]["T_cam_imu"][:3]
    refused(tmp_path, cams, "key 'cam0.T_cam_imu'", "expected a 4x4 matrix")
    cams = imucam_cameras()
    cams[3]["T_cam_imu"] = cams[3]["T_cam_imu"].copy()
    cams[3]["T_cam_imu"][3] = [0, 0, 0.5, 1]
    refused(tmp_path, cams, "key 'cam3.T_cam_imu'", "last row of a 4x4 transform must be 0 0 0 1")
    cams = chain_cameras()
    del cams[2]["T_cn_cnm1"]
    refused(tmp_path, cams, "key 'cam2.T_cn_cnm1'", "missing")
    cams = chain_cameras()
    cams[2]["T_cam_imu"] = np.eye(4)
    refused(tmp_path, cams, "key 'cam2.T_cam_imu'", "cam0 has no T_cam_imu")
    cams = imucam_cameras()
    del cams[1]["T_cam_imu"], cams[1]["T_cn_cnm1"]
    refused(tmp_path, cams, "key 'cam1.T_cam_imu'", "missing")
    text = camchain_text(imucam_cameras()).replace("cam1:", "cam7:")
    refused(tmp_path, text, "key 'cam1'", "missing (the file has cam0, cam2, cam3, cam7)")


# -------------------------------------------------------------------------------------------- Basalt
# the camera's pose in the IMU frame as Basalt writes it; cam0's quaternion, (qx, qy, qz, qw) =
# (-0.5, 0.5, -0.5, 0.5), is FORWARD: the optical axis along the IMU's x
BASALT_CAMERAS = [
    ("kb4", [512, 512], {"fx": 190.97847715128717, "fy": 190.9733070521226, "cx": 254.93170605935475,
                         "cy": 256.8974428996504, "k1": 0.0034823894022493434, "k2": 0.0007150348452162257,
                         "k3": -0.0020532361418706202, "k4": 0.00020293673591811182}),
    ("ds", [752, 480], {"fx": 349.7560023050409, "fy": 348.72454229977037, "cx": 365.8944076259015,
                        "cy": 249.32995565708704, "xi": -0.2409573942178872, "alpha": 0.566996899163044}),
    ("eucm", [752, 480], {"fx": 460.7648465156647, "fy": 459.4051018049483, "cx": 365.8937161309615,
                          "cy": 249.33499869752445, "alpha": 0.5903365915227143, "beta": 1.127468196965374}),
    ("ucm", [640, 480], {"fx": 280.2, "fy": 280.1, "cx": 320.3, "cy": 240.7, "alpha": 0.65}),
    ("fov", [640, 480], {"fx": 258.3, "fy": 258.1, "cx": 318.9, "cy": 241.2, "w": 0.93}),
    ("pinhole-radtan8", [1280, 800], {"fx": 903.94, "fy": 905.33, "cx": 645.59, "cy": 386.88, "k1": 0.28,
                                      "k2": -0.05, "p1": 0.0003, "p2": -0.0002, "k3": 0.01, "k4": 0.62,
                                      "k5": -0.01, "k6": 0.04, "rpmax": 2.0}),
    ("pinhole", [640, 480], {"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5}),
]  # fmt: skip


def basalt_rotation(i: int) -> np.ndarray:
    return FORWARD if i == 0 else rot("z", 30 * i) @ rot("x", 5 * i) @ FORWARD


def basalt_translation(i: int) -> list[float]:
    return [0.04, -0.02, 0.01] if i == 0 else [0.01 * i, -0.02 * i, 0.005]


def basalt_tree(cameras=BASALT_CAMERAS) -> dict:
    poses = [{"px": 0.04, "py": -0.02, "pz": 0.01, "qx": -0.5, "qy": 0.5, "qz": -0.5, "qw": 0.5}]
    for i in range(1, len(cameras)):
        q = quaternion_xyzw(basalt_rotation(i))
        t = basalt_translation(i)
        poses.append(
            {
                **dict(zip(("px", "py", "pz"), t, strict=True)),
                **dict(zip(("qx", "qy", "qz", "qw"), q, strict=True)),
            }
        )
    return {
        "value0": {
            "T_imu_cam": poses,
            "intrinsics": [{"camera_type": t, "intrinsics": dict(p)} for t, _, p in cameras],
            "resolution": [list(size) for _, size, _ in cameras],
            "calib_accel_bias": [0.0] * 9,
            "calib_gyro_bias": [0.0] * 12,
            "imu_update_rate": 200.0,
            "accel_noise_std": [0.016, 0.016, 0.016],
            "gyro_noise_std": [0.000282, 0.000282, 0.000282],
            "accel_bias_std": [0.001, 0.001, 0.001],
            "gyro_bias_std": [0.0001, 0.0001, 0.0001],
            "cam_time_offset_ns": 0,
            "vignette": [],
        }
    }


def write_basalt(path: Path, tree=None) -> Path:
    return write(path, json.dumps(basalt_tree() if tree is None else tree, indent=4))


def test_basalt_models_fields_and_projections(tmp_path):
    cams = read_basalt(write_basalt(tmp_path / "calib.json"))
    assert [c.name for c in cams] == [f"cam{i}" for i in range(7)] and all(c.body == "imu" for c in cams)
    models = [c.camera.model_name for c in cams]
    assert models == ["kannala_brandt", "double_sphere", "eucm", "ucm", "fov", "opencv", "pinhole"]
    for cam, (_, size, params) in zip(cams, BASALT_CAMERAS, strict=True):
        assert [cam.camera.width, cam.camera.height] == size
        for key, value in params.items():
            if key != "rpmax":
                assert getattr(cam.camera, key) == value, (cam.name, key)
    kb4, ds, eucm, ucm, fov, radtan8, pinhole = (c.camera for c in cams)
    p = {t: params for t, _, params in BASALT_CAMERAS}
    focal = ("fx", "fy", "cx", "cy")

    def f(t):
        return [p[t][k] for k in focal]

    kb = p["kb4"]
    assert np.allclose(
        project(kb4, WIDE), cv_fisheye_uv(WIDE, *f("kb4"), [kb[k] for k in ("k1", "k2", "k3", "k4")])
    )
    assert np.allclose(project(ds, WIDE), ds_uv(WIDE, p["ds"]["xi"], p["ds"]["alpha"], *f("ds")), atol=1e-6)
    assert np.allclose(
        project(eucm, WIDE), eucm_uv(WIDE, p["eucm"]["alpha"], p["eucm"]["beta"], *f("eucm")), atol=1e-6
    )
    assert np.allclose(project(ucm, WIDE), ucm_uv(WIDE, p["ucm"]["alpha"], *f("ucm")), atol=1e-6)
    assert np.allclose(project(fov, NEAR), fov_uv(NEAR, p["fov"]["w"], *f("fov")), atol=1e-6)
    r8 = p["pinhole-radtan8"]
    dist = [r8[k] for k in ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")]
    assert np.allclose(project(radtan8, NEAR), cv_pinhole_uv(NEAR, *f("pinhole-radtan8"), dist), atol=1e-6)
    assert np.allclose(project(pinhole, NEAR), pinhole_uv(NEAR, *f("pinhole")), atol=1e-9)


def test_basalt_extrinsics_quaternion_is_xyzw(tmp_path):
    cams = read_basalt(write_basalt(tmp_path / "calib.json"))
    # cam0: (qx, qy, qz, qw) = (-0.5, 0.5, -0.5, 0.5) is the forward-looking camera: its z is the IMU's x,
    # its x the IMU's -y, its y the IMU's -z
    assert np.allclose(cams[0].cam_to_body[:3, :3], FORWARD, atol=1e-12)
    assert np.allclose(apply(cams[0].cam_to_body, [0.0, 0.0, 2.0]), [2.04, -0.02, 0.01], atol=1e-12)
    assert np.allclose(apply(cams[0].cam_to_body, [0.5, 0.0, 0.0]), [0.04, -0.52, 0.01], atol=1e-12)
    for i, cam in enumerate(cams):
        assert np.allclose(cam.cam_to_body, pose(basalt_rotation(i), basalt_translation(i)), atol=1e-12)


def basalt_refused(tmp_path, tree, *expected: str) -> None:
    path = write_basalt(tmp_path / "calib.json", tree)
    with pytest.raises(CalibrationError) as info:
        read_basalt(path)
    message = str(info.value)
    assert message.startswith(str(path)), message
    for part in expected:
        assert part in message, message


def test_basalt_bad_fields_are_named(tmp_path):
    tree = basalt_tree()
    tree["value0"]["intrinsics"][1]["camera_type"] = "bal"
    basalt_refused(
        tmp_path, tree, "key 'value0.intrinsics[1].camera_type'", "camera cam1", "'bal' is not supported"
    )
    tree = basalt_tree()
    del tree["value0"]["intrinsics"][2]["intrinsics"]["beta"]
    basalt_refused(tmp_path, tree, "key 'value0.intrinsics[2].intrinsics.beta'", "missing (camera cam2, eucm")
    tree = basalt_tree()
    tree["value0"]["intrinsics"][0]["intrinsics"]["xi"] = 0.1  # a ds parameter in a kb4 camera
    basalt_refused(
        tmp_path, tree, "key 'value0.intrinsics[0].intrinsics.xi'", "not a parameter of camera_type kb4"
    )
    tree = basalt_tree()
    tree["value0"]["intrinsics"][1]["intrinsics"]["alpha"] = 1.4
    basalt_refused(tmp_path, tree, "key 'value0.intrinsics[1].intrinsics.alpha'", "alpha")
    tree = basalt_tree()
    del tree["value0"]["resolution"]
    basalt_refused(tmp_path, tree, "key 'value0.resolution'", "missing (one per camera, 7 cameras)")
    tree = basalt_tree()
    tree["value0"]["resolution"].pop()
    basalt_refused(tmp_path, tree, "key 'value0.resolution'", "one entry per camera (7), got 6")
    tree = basalt_tree()
    tree["value0"]["resolution"][3] = [640]
    basalt_refused(tmp_path, tree, "key 'value0.resolution[3]'", "expected [width, height]")
    tree = basalt_tree()
    tree["value0"]["T_imu_cam"][4]["qw"] = 2.0
    basalt_refused(tmp_path, tree, "key 'value0.T_imu_cam[4]'", "not a unit quaternion")
    tree = basalt_tree()
    del tree["value0"]["T_imu_cam"][5]["qx"]
    basalt_refused(tmp_path, tree, "key 'value0.T_imu_cam[5].qx'", "missing")


# -------------------------------------------------------------------------------------------- either
def test_read_calibration_tells_the_formats_apart(tmp_path):
    kalibr = read_calibration(write(tmp_path / "camchain.yaml", camchain_text(chain_cameras())))
    basalt = read_calibration(write_basalt(tmp_path / "calib.json"))
    assert [c.camera.model_name for c in kalibr][:2] == ["fov", "eucm"]
    assert [c.camera.model_name for c in basalt][:2] == ["kannala_brandt", "double_sphere"]
    single = write(tmp_path / "left.yaml", yaml.safe_dump({"model": "pinhole", "width": 64, "height": 48}))
    with pytest.raises(CalibrationError, match=r"left.yaml: neither a Kalibr camchain .* nor a Basalt"):
        read_calibration(single)
    with pytest.raises(CalibrationError, match=r"broken.json: not valid JSON"):
        read_calibration(write(tmp_path / "broken.json", '{"value0": {'))
    with pytest.raises(CalibrationError, match=r"absent.yaml: cannot read calibration file"):
        read_calibration(tmp_path / "absent.yaml")


# -------------------------------------------------------------------------------- rig.yaml from a file
def write_rig(root: Path, rig: dict, cameras: dict[str, tuple[int, int]]) -> None:
    """rig.yaml, the Kalibr camchain under calib/, and a sequence with two poses and one image per
    camera (timestamps in between)."""
    cv2 = pytest.importorskip("cv2")
    write(root / "calib" / "camchain-imucam.yaml", camchain_text(imucam_cameras()))
    write(root / "rig.yaml", yaml.safe_dump(rig, sort_keys=False))
    t0 = 1_700_000_000_000_000_000
    write(root / "seq0" / "poses.txt", f"{t0} 0 0 0 0 0 0 1\n{t0 + 10**8} 0.1 0 0 0 0 0 1\n")
    for name, (w, h) in cameras.items():
        (root / "seq0" / "images" / name).mkdir(parents=True)
        cv2.imwrite(
            str(root / "seq0" / "images" / name / f"{t0 + 5 * 10**7}.png"), np.zeros((h, w), np.uint8)
        )


def test_rig_takes_cameras_and_extrinsics_from_a_camchain(tmp_path):
    T_body_imu = pose(rot("z", 180), [0.3, 0.0, 1.1])  # the IMU mounted backwards, 1.1 m up
    rig = {
        "calibration": "calib/camchain-imucam.yaml",
        "calibration_to_body": T_body_imu[:3].tolist(),
        "cameras": [
            {"name": "front", "calibration_camera": "cam0", "mask": "masks/front.png"},
            {"name": "left", "calibration_camera": "/cam1/image_raw"},  # by its rostopic
            {"name": "cam3"},  # by its own name
            {"name": "back", "model": {"model": "pinhole", "width": 64, "height": 48, "fx": 50, "fy": 50,
                                       "cx": 31.5, "cy": 23.5}, "cam_to_body": np.eye(4).tolist()},
        ],
    }  # fmt: skip
    write_rig(tmp_path, rig, {"front": (752, 480), "left": (1024, 1024), "cam3": (752, 480)})
    (tmp_path / "masks").mkdir()
    (tmp_path / "masks" / "front.png").write_bytes(b"")  # only its existence is checked here
    layout = RigLayout(tmp_path)
    assert list(layout.cameras) == ["front", "left", "cam3", "back"]
    from_file = read_kalibr(tmp_path / "calib" / "camchain-imucam.yaml")
    for name, index in (("front", 0), ("left", 1), ("cam3", 3)):
        spec = layout.cameras[name]
        assert spec.camera == from_file[index].camera
        assert np.allclose(spec.cam_to_body, T_body_imu @ IMU_POSES[index], atol=1e-12)
    assert layout.cameras["front"].camera.model_name == "opencv"
    assert layout.cameras["front"].mask == tmp_path / "masks" / "front.png"
    # a point 2 m ahead of the left camera, in the body frame by hand: IMU frame first, then the body
    p_imu = apply(IMU_POSES[1], [0.0, 0.0, 2.0])
    p_body = rot("z", 180) @ p_imu + [0.3, 0.0, 1.1]
    assert np.allclose(apply(layout.cameras["left"].cam_to_body, [0.0, 0.0, 2.0]), p_body, atol=1e-12)
    assert [f.key for f in layout.frames("seq0", "left")] == [1_700_000_000_050_000_000]


def test_rig_without_cameras_takes_every_camera_of_the_file(tmp_path):
    write_rig(tmp_path, {"calibration": "calib/camchain-imucam.yaml"}, {})
    layout = RigLayout(tmp_path)
    assert list(layout.cameras) == ["cam0", "cam1", "cam2", "cam3"]
    for i, spec in enumerate(layout.cameras.values()):
        assert np.allclose(spec.cam_to_body, IMU_POSES[i], atol=1e-12)  # no calibration_to_body: the IMU


def test_rig_calibration_file_errors_are_named(tmp_path):
    rig = {
        "calibration": "calib/camchain-imucam.yaml",
        "cameras": [{"name": "front", "calibration_camera": "cam9"}],
    }
    write_rig(tmp_path, rig, {})
    with pytest.raises(CalibrationError) as info:
        RigLayout(tmp_path)
    message = str(info.value)
    assert "rig.yaml: key 'cameras[0].calibration_camera'" in message
    assert "camchain-imucam.yaml: no camera named 'cam9'; the file has cam0 (/cam0/image_raw)" in message
    rig = {"cameras": [{"name": "front", "calibration_camera": "cam0"}]}
    write(tmp_path / "rig.yaml", yaml.safe_dump(rig))
    with pytest.raises(
        CalibrationError, match=r"'cameras\[0\].calibration_camera': given, but rig.yaml has no"
    ):
        RigLayout(tmp_path)
    rig = {"calibration": "calib/missing.yaml", "cameras": [{"name": "cam0"}]}
    write(tmp_path / "rig.yaml", yaml.safe_dump(rig))
    with pytest.raises(FileNotFoundError, match=r"missing.yaml: calibration file not found"):
        RigLayout(tmp_path)
    cams = imucam_cameras()
    cams[1]["camera_model"] = "omni"
    write(tmp_path / "calib" / "camchain-imucam.yaml", camchain_text(cams))
    rig = {"calibration": "calib/camchain-imucam.yaml"}
    write(tmp_path / "rig.yaml", yaml.safe_dump(rig))
    with pytest.raises(CalibrationError, match=r"camchain-imucam.yaml: key 'cam1': camera_model 'omni' with"):
        RigLayout(tmp_path)
