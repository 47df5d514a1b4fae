"""Calibration files: KITTI-360 OpenCV YAML, CamOdoCal Kannala-Brandt, the project's YAML, bad input."""

from __future__ import annotations

import pytest

from fisheyedepth.cameras import (
    CalibrationError,
    KannalaBrandtCamera,
    MeiCamera,
    PinholeCamera,
    load_camera,
    opencv_yaml,
    save_camera,
)

from conftest import KITTI_02, kitti02


def kitti_yaml(**override) -> str:
    """An image_02.yaml in KITTI-360's exact layout; ``override`` replaces or (None) removes lines."""
    values = {"model_type": "MEI", "image_width": 1400, "image_height": 1400, **KITTI_02}
    values.update(override)

    def line(key, indent=""):
        return "" if values.get(key) is None else f"{indent}{key}: {values[key]}\n"

    return (
        "%YAML:1.0\n---\n"
        + line("model_type")
        + "camera_name: image_02\n"
        + line("image_width")
        + line("image_height")
        + "mirror_parameters:\n"
        + line("xi", "   ")
        + "distortion_parameters:\n"
        + "".join(line(k, "   ") for k in ("k1", "k2", "p1", "p2"))
        + "projection_parameters:\n"
        + "".join(line(k, "   ") for k in ("gamma1", "gamma2", "u0", "v0"))
    )


def write(tmp_path, text, name="image_02.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_kitti360_yaml_ignores_tangential_by_default(tmp_path):
    path = write(tmp_path, kitti_yaml())
    cam = load_camera(path)
    assert cam == kitti02()
    assert cam.p1 == 0.0 and cam.p2 == 0.0
    kept = load_camera(path, keep_tangential=True)
    assert kept == kitti02(tangential=True)
    assert kept.p1 == pytest.approx(4.2223943394772046e-04)


def test_official_kitti360_files(realdata):
    cam = load_camera(realdata / "kitti360_frame" / "image_02.yaml")
    assert isinstance(cam, MeiCamera) and (cam.width, cam.height) == (1400, 1400)
    assert cam == kitti02()
    cam3 = load_camera(realdata / "kitti360_frame" / "image_03.yaml", keep_tangential=True)
    assert cam3.xi == pytest.approx(2.5535139132482758) and cam3.p2 == pytest.approx(-7.0340482615055284e-04)


def test_camodocal_kannala_brandt(tmp_path):
    text = (
        "%YAML:1.0\n---\nmodel_type: KANNALA_BRANDT\ncamera_name: cam0\nimage_width: 512\nimage_height: 512\n"
        "projection_parameters:\n   k2: 0.0034\n   k3: 0.0007\n   k4: -0.002\n   k5: 0.0002\n"
        "   mu: 190.9\n   mv: 190.8\n   u0: 254.9\n   v0: 256.8\n"
    )
    cam = load_camera(write(tmp_path, text))
    assert cam == KannalaBrandtCamera(
        width=512,
        height=512,
        fx=190.9,
        fy=190.8,
        cx=254.9,
        cy=256.8,
        k1=0.0034,
        k2=0.0007,
        k3=-0.002,
        k4=0.0002,
    )


def test_opencv_pinhole_without_distortion(tmp_path):
    text = (
        "%YAML:1.0\n---\nmodel_type: PINHOLE\nimage_width: 640\nimage_height: 480\n"
        "distortion_parameters:\n   k1: 0\n   k2: 0\n   p1: 0\n   p2: 0\n"
        "projection_parameters:\n   fx: 400.0\n   fy: 401.0\n   cx: 319.5\n   cy: 239.5\n"
    )
    assert load_camera(write(tmp_path, text)) == PinholeCamera(
        width=640, height=480, fx=400, fy=401, cx=319.5, cy=239.5
    )
    with pytest.raises(CalibrationError, match="distortion_parameters.k1"):
        load_camera(write(tmp_path, text.replace("k1: 0", "k1: 0.1"), "distorted.yaml"))


def test_project_yaml_round_trip(tmp_path, camera):
    path = save_camera(camera, tmp_path / "cam.yaml")
    assert load_camera(path) == camera
    assert not list(tmp_path.glob(".*.tmp"))  # the atomic write left no temporary file


def test_save_refuses_to_overwrite(tmp_path):
    path = save_camera(kitti02(), tmp_path / "cam.yaml")
    with pytest.raises(FileExistsError, match="overwrite"):
        save_camera(kitti02().resize(384, 384), path)
    assert load_camera(path) == kitti02()
    save_camera(kitti02().resize(384, 384), path, overwrite=True)
    assert load_camera(path).width == 384


@pytest.mark.parametrize(
    "override,key",
    [
        (dict(k2=None), "distortion_parameters.k2"),
        (dict(gamma1=None), "projection_parameters.gamma1"),
        (dict(xi=None), "mirror_parameters.xi"),
        (dict(image_width=None), "image_width"),
        (dict(model_type="SCARAMUZZA"), "model_type"),
        (dict(xi=-0.5), "mirror_parameters.xi"),
        (dict(gamma2=0.0), "projection_parameters.gamma2"),
        (dict(gamma1=-1336.0), "projection_parameters.gamma1"),
        (dict(k1=".nan"), "distortion_parameters.k1"),
        (dict(u0=".inf"), "projection_parameters.u0"),
        (dict(v0="abc"), "projection_parameters.v0"),
        (dict(image_height=-3), "image_height"),
    ],
)
def test_bad_kitti_file_names_file_and_key(tmp_path, override, key):
    path = write(tmp_path, kitti_yaml(**override), "bad_image_02.yaml")
    with pytest.raises(CalibrationError) as info:
        load_camera(path)
    assert info.value.key == key
    assert str(path) in str(info.value) and key in str(info.value)


@pytest.mark.parametrize(
    "text,key",
    [
        ("model: fisheye9000\nwidth: 10\nheight: 10\n", "model"),
        ("width: 10\nheight: 10\nfx: 1\nfy: 1\n", "model"),
        ("model: pinhole\nwidth: 10\nheight: 10\nfx: 1\n", "fy"),
        ("model: pinhole\nwidth: 10\nheight: 10\nfx: 1\nfy: 1\ncx: 1\ncy: 1\nxi: 2\n", "xi"),
        (
            "model: double_sphere\nwidth: 10\nheight: 10\nfx: 1\nfy: 1\ncx: 1\ncy: 1\nxi: 0\nalpha: 1.2\n",
            "alpha",
        ),
        ("model: mei\nwidth: 10\nheight: 10\nxi: -1\ngamma1: 1\ngamma2: 1\nu0: 1\nv0: 1\n", "xi"),
        ("model: kannala_brandt\nwidth: 10\nheight: 10\nfx: 1\nfy: 1\ncy: 1\n", "cx"),
    ],
)
def test_bad_project_yaml_names_file_and_key(tmp_path, text, key):
    path = write(tmp_path, text, "cam.yaml")
    with pytest.raises(CalibrationError) as info:
        load_camera(path)
    assert info.value.key == key and str(path) in str(info.value)


def test_unreadable_or_malformed_file(tmp_path):
    with pytest.raises(CalibrationError, match="missing.yaml"):
        load_camera(tmp_path / "missing.yaml")
    with pytest.raises(CalibrationError, match="not valid YAML"):
        load_camera(write(tmp_path, "model: [unclosed\n", "broken.yaml"))
    with pytest.raises(CalibrationError, match="mapping"):
        load_camera(write(tmp_path, "- a list\n", "list.yaml"))


def test_opencv_yaml_is_written_with_the_table_it_is_read_with(tmp_path):
    """One key table serves reading and writing: every OpenCV model round-trips exactly (MEI with its
    tangential terms when they are kept), and the MEI file has KITTI-360's exact layout."""
    mei = kitti02(tangential=True)
    assert mei.p1 != 0 and mei.p2 != 0
    kb = KannalaBrandtCamera(
        width=640, height=480, fx=300.5, fy=301.0, cx=320.2, cy=239.8, k1=0.01, k2=-0.002, k3=1e-4, k4=-1e-5
    )
    pin = PinholeCamera(width=320, height=240, fx=200.0, fy=201.0, cx=160.0, cy=120.0)
    for camera in (mei, kb, pin):
        path = write(tmp_path, opencv_yaml(camera, "cam"), f"{camera.model_name}.yaml")
        assert load_camera(path, keep_tangential=True) == camera
    assert load_camera(tmp_path / "mei.yaml") == kitti02()  # p1/p2 ignored by default, as KITTI-360 does
    official = kitti_yaml().splitlines()
    written = opencv_yaml(kitti02(), "image_02").splitlines()
    assert [line.split(":")[0] for line in written] == [line.split(":")[0] for line in official]
