"""The body-mask estimator against the synthetic world's exact masks, and its command's safety."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from fisheyedepth.cli.estimate_mask import main
from fisheyedepth.data import Kitti360Layout
from fisheyedepth.data.body_mask import estimate_body_mask, ray_elevation, sample_evenly
from fisheyedepth.data.kitti360 import kitti360_camera
from fisheyedepth.data.kitti360.presets import KITTI360_CAM_TO_POSE
from fisheyedepth.geometry import pose_from_3x4

from conftest import quaternion_xyzw

TRAIN, VAL = "2013_05_28_drive_0000_sync", "2013_05_28_drive_0001_sync"  # 24 and 3 frames
CAMERAS = ("image_02", "image_03")


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> tuple[Path, dict[str, np.ndarray]]:
    """A 128 x 128 kitti360 world (30 frames) whose exact body masks are moved aside, and those masks."""
    from fisheyedepth.synthetic import WorldSpec, generate

    spec = WorldSpec(
        "kitti360",
        frames=30,
        size=128,
        seed=5,
        supersample=1,  # one ray per pixel: body IoU 0.96-1.0 (0.96-0.99 with 2x2 rays), in 60 % of the time
    )
    root = generate(tmp_path_factory.mktemp("body") / "w", spec, progress=False, lidar=False)
    exact = {}
    for camera in CAMERAS:
        path = root / "calibration" / f"body_mask_{camera}.png"
        exact[camera] = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
        path.rename(root / f"exact_body_mask_{camera}.png")
    return root, exact


@pytest.fixture(scope="module")
def estimated(world) -> dict[str, Path]:
    """Each camera's mask, estimated through the command into the layout's default place."""
    root, _ = world
    for camera in CAMERAS:
        assert main(["--root", str(root), "--sequence", TRAIN, "--camera", camera]) == 0
    return {camera: root / "calibration" / f"body_mask_{camera}.png" for camera in CAMERAS}


def has_ray(root: Path, camera: str) -> np.ndarray:
    spec = Kitti360Layout(root, cameras=[camera]).cameras[camera]
    return ray_elevation(spec.camera, spec.cam_to_body, (0, 0, -1))[1]


def body_iou(usable: np.ndarray, exact_usable: np.ndarray, rays: np.ndarray) -> float:
    """IoU of the body over the pixels with a ray (the usable region's IoU is high whatever the body)."""
    a, b = ~usable & rays, ~exact_usable & rays
    return float((a & b).sum() / (a | b).sum())


def read_mask(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0


@pytest.mark.parametrize("camera", CAMERAS)
def test_estimate_matches_the_exact_body(world, estimated, camera):
    root, exact = world
    assert Kitti360Layout(root, cameras=[camera]).cameras[camera].mask == estimated[camera]  # read back
    raw = cv2.imread(str(estimated[camera]), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint8 and set(np.unique(raw)) == {0, 255}
    rays = has_ray(root, camera)
    usable = raw > 0
    assert usable[~rays].all()  # pixels without a ray are usable, as in the exact masks
    assert body_iou(usable, exact[camera], rays) >= 0.9


def test_prints_a_summary(world, estimated, capsys, tmp_path):
    root, _ = world
    out = tmp_path / "mask.png"
    assert main(["--root", str(root), "--sequence", TRAIN, "--camera", "image_02", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "% of the pixels with a ray are body" in printed and "threshold" in printed
    assert f"wrote {out}" in printed
    assert (read_mask(out) == read_mask(estimated["image_02"])).all()


def test_threshold_override(world, tmp_path):
    root, exact = world
    out = tmp_path / "mask.png"
    args = ["--root", str(root), "--sequence", TRAIN, "--camera", "image_02", "--out", str(out)]
    assert main([*args, "--threshold", "0"]) == 0
    assert read_mask(out).all()  # no std is below 0: nothing is body
    assert main([*args, "--threshold", "0.01", "--overwrite"]) == 0
    assert body_iou(read_mask(out), exact["image_02"], has_ray(root, "image_02")) >= 0.9


def test_refuses_to_overwrite(world, estimated, capsys):
    root, _ = world
    path = estimated["image_02"]
    before = path.read_bytes()
    path.write_bytes(b"not the estimate")
    assert main(["--root", str(root), "--sequence", TRAIN, "--camera", "image_02"]) == 2
    assert str(path) in capsys.readouterr().err
    assert path.read_bytes() == b"not the estimate"
    assert main(["--root", str(root), "--sequence", TRAIN, "--camera", "image_02", "--overwrite"]) == 0
    assert path.read_bytes() == before


def test_too_few_frames(world, tmp_path, capsys):
    root, _ = world
    out = tmp_path / "mask.png"
    assert main(["--root", str(root), "--sequence", VAL, "--camera", "image_02", "--out", str(out)]) == 2
    message = capsys.readouterr().err
    assert VAL in message and "3 frames" in message and "at least 10" in message
    assert main(["--root", str(root), "--sequence", TRAIN, "--camera", "image_02", "--frames", "5"]) == 2
    assert "at least 10" in capsys.readouterr().err
    assert not out.exists()


def as_rig(root: Path, out: Path) -> Path:
    """The training sequence of the synthetic world in the robot-rig layout (the pose frame as body)."""
    layout = Kitti360Layout(root, cameras=list(CAMERAS))
    entries, lines = [], []
    for camera, spec in layout.cameras.items():
        cam_to_body = spec.cam_to_body[:3].tolist()
        entries.append({"name": camera, "model": spec.camera.to_dict(), "cam_to_body": cam_to_body})
        images = out / "seq0" / "images" / camera
        images.mkdir(parents=True)
        for frame in layout.frames(TRAIN, camera):
            shutil.copy(layout.image(TRAIN, camera, frame), images / f"{1000 + frame.key}.png")
    for frame in layout.frames(TRAIN):
        t, q = frame.pose[:3, 3], quaternion_xyzw(frame.pose[:3, :3])
        lines.append(" ".join(str(v) for v in [1000 + frame.key, *t, *q]))
    (out / "rig.yaml").write_text(yaml.safe_dump({"cameras": entries}))
    (out / "seq0" / "poses.txt").write_text("\n".join(lines) + "\n")
    return out


def test_rig_layout(world, tmp_path, capsys):
    root, exact = world
    rig = as_rig(root, tmp_path / "rig")
    assert main(["--root", str(rig), "--layout", "rig", "--sequence", "seq0", "--camera", "image_03"]) == 0
    printed = capsys.readouterr().out
    up = [float(v) for v in re.search(r"up \[(.*?)\]", printed).group(1).split(",")]
    assert np.allclose(up, (0, 0, -1), atol=0.01)  # the world's z seen from the body: KITTI-360's z is down
    assert "mask: masks/image_03.png" in printed  # rig.yaml names no mask: say what to add
    usable = read_mask(rig / "masks" / "image_03.png")
    assert body_iou(usable, exact["image_03"], has_ray(root, "image_03")) >= 0.9

    victim = rig / "seq0" / "images" / "image_03" / "1010.png"
    victim.write_bytes(victim.read_bytes()[:100])  # truncated
    args = ["--root", str(rig), "--layout", "rig", "--sequence", "seq0", "--camera", "image_03"]
    assert main([*args, "--out", str(tmp_path / "m.png")]) == 2
    assert str(victim) in capsys.readouterr().err


def test_still_sky_is_not_body():
    """A still, smooth sky above the horizon has as little temporal variance as the body: the elevation
    of its rays, not its statistics, keeps it usable."""
    camera = kitti360_camera(2).resize(96, 96)
    cam_to_body = pose_from_3x4(np.asarray(KITTI360_CAM_TO_POSE["image_02"])).numpy()
    elevation, rays = ray_elevation(camera, cam_to_body, (0, 0, -1))
    sky = rays & (elevation > np.deg2rad(10))
    body = rays & (elevation < np.deg2rad(-40))
    rng = np.random.default_rng(0)
    sky_colour = 100 + 80 * np.sin(elevation.clip(0, None))  # depends on the elevation only

    def frames(count: int = 40):
        for _ in range(count):
            image = rng.uniform(20, 235, elevation.shape)  # the moving world
            image = np.where(sky, sky_colour, np.where(body, 15.0, image))
            yield np.clip(image * rng.uniform(0.8, 1.2), 0, 255).astype(np.uint8)  # and auto exposure

    mask = estimate_body_mask(frames(), camera, cam_to_body)
    assert mask.usable[sky].all()
    assert body_iou(mask.usable, ~body, rays) >= 0.95
    no_sky_rule = estimate_body_mask(frames(), camera, cam_to_body, sky_elevation=90)
    assert (~no_sky_rule.usable[sky]).mean() > 0.9  # without the elevation, the sky is taken for body


def test_sample_evenly():
    assert sample_evenly(1000, 5) == [0, 250, 500, 749, 999]
    assert sample_evenly(4, 200) == [0, 1, 2, 3]
