"""Calibrations that cannot be a real camera's, and files that cannot be parsed.

A focal length of 1e30 px gives every pixel a ray (along the optical axis), so "5 % of the pixels have a
ray" let it through; a ROS ``CameraInfo`` written column-major read cx = cy = 0; a file nested thousands of
levels deep stopped the parser with a RecursionError. Each reader must refuse them with one line naming
the file (or topic) and the field, by one rule (:func:`fisheyedepth.cameras.base.check_plausible`), and
every real camera the project reads must pass that rule."""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fisheyedepth.cameras import (
    CalibrationError,
    CameraModel,
    CameraParameterError,
    DoubleSphereCamera,
    Fisheye624Camera,
    KannalaBrandtCamera,
    MeiCamera,
    OpenCVCamera,
    PinholeCamera,
    check_plausible,
    load_camera,
    load_json,
    load_yaml,
    presets,
    read_basalt,
    read_calibration,
    read_kalibr,
    save_camera,
)
from fisheyedepth.cameras.base import MAX_FOCAL_SIZES, MIN_FIELD_OF_VIEW, MIN_FOCAL_SIZES
from fisheyedepth.data.kitti360.presets import kitti360_camera
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.data.rosbag import RosbagError, camera_from_info

from conftest import KITTI_02, all_cameras, aria_fisheye624, load_script

TOPIC = "/front/camera_info"
K = [612.4, 0.0, 318.7, 0.0, 611.9, 242.1, 0.0, 0.0, 1.0]  # a 640 x 480 USB camera, row-major
PLUMB_BOB = [-0.2834, 0.0739, 0.00019, 1.76e-05, -0.0121]
# Deeper than either parser can descend (Python's recursion limit is 1000 calls)
DEEP_JSON = '{"value0": ' + "[" * 100_000
DEEP_YAML_FLOW = "[" * 50_000
DEEP_YAML_BLOCK = "a:\n" + "".join(" " * depth + f"k{depth}:\n" for depth in range(1, 1000))
TOO_DEEP = "nested too deeply to be a calibration"
TOO_DEEP_LINE = f"{TOO_DEEP} (lists or mappings hundreds of levels deep)"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def refused(call, *args) -> str:
    """The one-line message of the CalibrationError ``call(*args)`` raises."""
    with pytest.raises(CalibrationError) as info:
        call(*args)
    message = str(info.value)
    assert "\n" not in message
    return message


# ------------------------------------------------------------------------------ the project's readers
def opencv_pinhole_yaml(fx="612.4", cx="318.7") -> str:
    return (
        "%YAML:1.0\n---\nmodel_type: PINHOLE\ncamera_name: front\nimage_width: 640\nimage_height: 480\n"
        f"projection_parameters:\n   fx: {fx}\n   fy: 611.9\n   cx: {cx}\n   cy: 242.1\n"
    )


def kitti_yaml(**override) -> str:
    """KITTI-360's image_02.yaml layout (OpenCV YAML, MEI) with ``override``'s values."""
    v = {**KITTI_02, **override}
    groups = {
        "distortion_parameters": ("k1", "k2", "p1", "p2"),
        "projection_parameters": ("gamma1", "gamma2", "u0", "v0"),
    }
    text = "%YAML:1.0\n---\nmodel_type: MEI\ncamera_name: image_02\nimage_width: 1400\nimage_height: 1400\n"
    text += f"mirror_parameters:\n   xi: {v['xi']}\n"
    for group, keys in groups.items():
        text += f"{group}:\n" + "".join(f"   {k}: {v[k]}\n" for k in keys)
    return text


def test_fx_1e30_in_an_opencv_yaml_is_refused_naming_the_file_and_the_field(tmp_path):
    path = write(tmp_path / "calib.yaml", opencv_pinhole_yaml(fx="1e30"))
    assert refused(load_camera, path) == (
        f"{path}: key 'projection_parameters.fx': 1e+30 px gives a field of view of 3.7e-26 degrees across "
        "the 640 px image width (a focal length of at most 100 times the image width, 64000 px, expected): "
        "a wrong unit or a corrupt value?"
    )
    # the project's own YAML, and the focal along v
    own = "{model: pinhole, width: 640, height: 480, fx: 612.4, fy: 1.0e+30, cx: 318.7, cy: 242.1}"
    path = write(tmp_path / "own.yaml", own)
    assert refused(load_camera, path).startswith(
        f"{path}: key 'fy': 1e+30 px gives a field of view of 2.8e-26 degrees across the 480 px image height"
    )
    # the file is fine with a real focal
    assert load_camera(write(tmp_path / "ok.yaml", opencv_pinhole_yaml())).fx == 612.4


def test_mei_gamma1_6e30_is_refused_by_its_paraxial_focal(tmp_path):
    path = write(tmp_path / "image_02.yaml", kitti_yaml(gamma1="6.1e30"))
    paraxial = 6.1e30 / (1 + KITTI_02["xi"])
    assert f"{paraxial:g}" == "1.8983e+30"
    assert refused(load_camera, path).startswith(
        f"{path}: key 'projection_parameters.gamma1': 6.1e+30 px (a paraxial focal length of 1.8983e+30 px) "
        "gives a field of view of 4.2e-26 degrees across the 1400 px image width"
    )
    assert load_camera(write(tmp_path / "ok.yaml", kitti_yaml())) == kitti360_camera(2)


def kalibr_text(intrinsics: str, resolution: str = "[752, 480]") -> str:
    return (
        "cam0:\n  camera_model: pinhole\n  distortion_model: equidistant\n"
        f"  intrinsics: {intrinsics}\n  distortion_coeffs: [0.0034, 0.0007, -0.002, 0.0002]\n"
        f"  resolution: {resolution}\n  rostopic: /cam0/image_raw\n"
    )


def test_kalibr_fu_fv_1e300_is_refused(tmp_path):
    path = write(tmp_path / "camchain.yaml", kalibr_text("[1.0e+300, 1.0e+300, 376.0, 240.0]"))
    for read in (read_kalibr, read_calibration):
        assert refused(read, path).startswith(
            f"{path}: key 'cam0.intrinsics[0] (fu)': 1e+300 px gives a field of view of 4.3e-296 degrees "
            "across the 752 px image width"
        )
    ok = write(tmp_path / "ok.yaml", kalibr_text("[190.97, 190.97, 254.93, 256.90]", "[512, 512]"))
    assert read_kalibr(ok)[0].camera.fx == 190.97


def test_basalt_fx_1e30_is_refused(tmp_path):
    intrinsics = {"fx": 1e30, "fy": 190.97, "cx": 254.93, "cy": 256.9}
    intrinsics.update(k1=0.0034, k2=0.0007, k3=-0.002, k4=0.0002)
    pose = {"px": 0, "py": 0, "pz": 0, "qx": 0, "qy": 0, "qz": 0, "qw": 1}
    tree = {
        "value0": {
            "T_imu_cam": [pose],
            "intrinsics": [{"camera_type": "kb4", "intrinsics": intrinsics}],
            "resolution": [[512, 512]],
        }
    }
    path = write(tmp_path / "calib.json", json.dumps(tree))
    for read in (read_basalt, read_calibration):
        assert refused(read, path).startswith(
            f"{path}: key 'value0.intrinsics[0].intrinsics.fx': 1e+30 px gives a field of view of 2.9e-26 "
            "degrees across the 512 px image width"
        )


OUTSIDE = "the principal point's {} px lies outside the {} px image {} (-0.5 to {})"


@pytest.mark.parametrize(
    "override, key, message",
    [
        ({"cx": "5000.0"}, "cx", OUTSIDE.format(5000, 640, "width", 639.5)),
        ({"cx": "-0.6"}, "cx", OUTSIDE.format(-0.6, 640, "width", 639.5)),
        ({"cy": "480.0"}, "cy", OUTSIDE.format(480, 480, "height", 479.5)),
        (
            {"fx": "20.0", "k1": "0.0"},
            "fx",
            "20 px is less than 1/20 of the 640 px image width (at least 32 px expected; a pinhole of this "
            "focal would see 173 degrees across it)",
        ),
        # a sane focal whose distortion squeezes the image into a sliver: the rays say so
        (
            {"k1": "1.0e+12"},
            None,
            "the opencv model sees 0.0092 degrees across the 640 px image width (at least 1 degree "
            "expected): an impossible distortion coefficient?",
        ),
    ],
    ids=["cx-far-right", "cx-left-of-the-edge", "cy-below-the-edge", "focal-too-short", "fov-by-distortion"],
)
def test_the_project_yaml_refuses_each_rule_naming_the_field(tmp_path, override, key, message):
    values = {"model": "opencv", "width": 640, "height": 480, "fx": "612.4", "fy": "611.9"}
    values.update({"cx": "318.7", "cy": "242.1", "k1": "-0.28", **override})
    path = write(tmp_path / "cam.yaml", "".join(f"{k}: {v}\n" for k, v in values.items()))
    where = f"{path}" if key is None else f"{path}: key '{key}'"
    assert refused(load_camera, path).startswith(f"{where}: {message}")


def test_the_bounds_are_where_the_rule_says():
    """The principal point may sit on the image's outer edge; a pinhole passes up to 1 degree across its
    image (57 image sizes), and its focal between 1/20 and 100 image sizes."""
    base = dict(width=640, height=480, fx=600.0, fy=600.0, cx=319.5, cy=239.5)
    for cx in (-0.5, 639.5):
        assert check_plausible(PinholeCamera(**{**base, "cx": cx})).cx == cx
    narrowest = 320 / math.tan(math.radians(MIN_FIELD_OF_VIEW / 2))  # 36667 px: 1 degree across 640 px
    assert check_plausible(PinholeCamera(**{**base, "fx": narrowest * 0.999})).field_of_view()[0] > 1.0
    with pytest.raises(
        CameraParameterError, match=r"^the pinhole model sees 0\.99 degrees across the 640 px"
    ):
        check_plausible(PinholeCamera(**{**base, "fx": narrowest * 1.01}))
    with pytest.raises(CameraParameterError, match="at most 100 times the image width") as info:
        check_plausible(PinholeCamera(**{**base, "fx": MAX_FOCAL_SIZES * 640 * 1.01}))
    assert info.value.key == "fx"
    short = check_plausible(PinholeCamera(**{**base, "fy": MIN_FOCAL_SIZES * 480 * 1.01}))
    assert short.fy == pytest.approx(24.24)
    with pytest.raises(CameraParameterError, match="less than 1/20 of the 480 px image height") as info:
        check_plausible(PinholeCamera(**{**base, "fy": MIN_FOCAL_SIZES * 480 * 0.99}))
    assert info.value.key == "fy"


# -------------------------------------------------------------------------- the other readers of cameras
def test_fisheye624_from_aria_refuses_an_implausible_focal(tmp_path):
    cam = aria_fisheye624()
    params = [1e30, cam.cx, cam.cy, cam.k0, cam.k1, cam.k2, cam.k3, cam.k4, cam.k5, cam.p0, cam.p1]
    params += [cam.s0, cam.s1, cam.s2, cam.s3]
    entry = {"model": "FISHEYE624", "params": params, "size": [512, 512]}
    path = write(tmp_path / "calib.json", json.dumps({"cam": entry}))
    assert refused(Fisheye624Camera.from_aria, path, "cam").startswith(
        f"{path}: key 'cam.fx': 1e+30 px gives a field of view of 2.9e-26 degrees across the 512 px image"
    )
    with pytest.raises(CameraParameterError, match=r"^cx: the principal point's 600 px lies outside"):
        Fisheye624Camera.from_aria_params([250.0, 600.0, *params[2:]], (512, 512))


def test_rig_yaml_cameras_are_checked(tmp_path):
    """A rig.yaml camera given inline, by its own calibration file, or from a camchain."""
    model = {
        "model": "pinhole",
        "width": 640,
        "height": 480,
        "fx": 1e30,
        "fy": 611.9,
        "cx": 318.7,
        "cy": 242.1,
    }
    entry = {"name": "front", "model": model, "cam_to_body": np.eye(4).tolist()}
    write(tmp_path / "a" / "rig.yaml", json.dumps({"cameras": [entry]}))
    assert refused(RigLayout, tmp_path / "a").startswith(
        f"{tmp_path / 'a' / 'rig.yaml'} (cameras[0].model): key 'fx': 1e+30 px gives a field of view"
    )
    calib = write(tmp_path / "b" / "calib" / "front.yaml", opencv_pinhole_yaml(cx="-20.0"))
    entry = {"name": "front", "calibration": "calib/front.yaml", "cam_to_body": np.eye(4).tolist()}
    write(tmp_path / "b" / "rig.yaml", json.dumps({"cameras": [entry]}))
    assert refused(RigLayout, tmp_path / "b").startswith(
        f"{calib}: key 'projection_parameters.cx': the principal point's -20 px"
    )
    camchain = write(
        tmp_path / "c" / "calib" / "camchain.yaml", kalibr_text("[1.0e+300, 1.0e+300, 376.0, 240.0]")
    )
    write(tmp_path / "c" / "rig.yaml", "calibration: calib/camchain.yaml\n")
    assert refused(RigLayout, tmp_path / "c").startswith(
        f"{camchain}: key 'cam0.intrinsics[0] (fu)': 1e+300 px"
    )


def test_opencv_from_ros_refuses_a_k_that_is_not_row_major_and_an_implausible_focal():
    column_major = [612.4, 0.0, 0.0, 0.0, 611.9, 0.0, 318.7, 242.1, 1.0]
    for matrix, key, message in (
        (
            column_major,
            "K",
            "written column-major: cx = K[6] = 318.7 and cy = K[7] = 242.1 where K[2] = K[5]",
        ),
        ([*K[:8], 0.0], "K[8]", "must be 1 (K = [fx 0 cx 0 fy cy 0 0 1]), got 0"),
        ([1e30, *K[1:]], "fx", "1e+30 px gives a field of view of 3.7e-26 degrees across the 640 px image"),
    ):
        with pytest.raises(CameraParameterError) as info:
            OpenCVCamera.from_ros(640, 480, matrix, PLUMB_BOB)
        assert info.value.key == key and str(info.value).startswith(f"{key}: {message}")
    assert OpenCVCamera.from_ros(640, 480, K, PLUMB_BOB).cx == 318.7


def camera_info(matrix=K, D=PLUMB_BOB, binning=(0, 0), roi=(0, 0, 0, 0)):
    """A 640 x 480 ROS 1 ``sensor_msgs/CameraInfo`` (plumb_bob) as a plain object: the fields
    camera_from_info reads."""
    x, y, w, h = roi
    return SimpleNamespace(
        K=list(matrix),
        D=list(D),
        distortion_model="plumb_bob",
        width=640,
        height=480,
        binning_x=binning[0],
        binning_y=binning[1],
        roi=SimpleNamespace(x_offset=x, y_offset=y, width=w, height=h, do_rectify=False),
    )


INSTEAD = "give the calibration of the images as they are in the bag instead (--calibration NAME=FILE)"
OUTSIDE_K = [612.4, 0.0, 1318.7, 0.0, 611.9, 242.1, 0.0, 0.0, 1.0]


@pytest.mark.parametrize(
    "info, message",
    [
        (
            camera_info([612.4, 0.0, 0.0, 0.0, 611.9, 0.0, 318.7, 242.1, 1.0]),
            "the CameraInfo's K: written column-major: cx = K[6] = 318.7 and cy = K[7] = 242.1 where "
            "K[2] = K[5] = 0; K is row-major, [fx 0 cx 0 fy cy 0 0 1]",
        ),
        (camera_info([*K[:8], 0.0]), "the CameraInfo's K[8]: must be 1 (K = [fx 0 cx 0 fy cy 0 0 1]), got 0"),
        (
            camera_info([*K[:6], 0.0, 3.0, 1.0]),
            "the CameraInfo's K[7]: must be 0 (K = [fx 0 cx 0 fy cy 0 0 1])",
        ),
        (
            camera_info(binning=(2, 2)),
            "the CameraInfo's binning_x is 2: its K and D describe the 640x480 sensor before binning, not "
            f"the binned images, and this import does not rescale them; {INSTEAD}",
        ),
        (camera_info(binning=(1, 4)), "the CameraInfo's binning_y is 4: its K and D describe the 640x480"),
        (
            camera_info(roi=(10, 20, 320, 240)),
            "the CameraInfo's roi (x_offset 10, y_offset 20, width 320, height 240) crops the 640x480 "
            "calibrated image: its K and D describe the whole image, not the crop, and this import does "
            f"not shift them; {INSTEAD}",
        ),
        (
            camera_info(roi=(0, 0, 320, 240)),
            "the CameraInfo's roi (x_offset 0, y_offset 0, width 320, height",
        ),
        (camera_info(roi=(8, 0, 0, 0)), "the CameraInfo's roi (x_offset 8, y_offset 0, width 0, height 0)"),
        (
            camera_info([1e30, *K[1:]]),
            f"CameraInfo 640x480, distortion 'plumb_bob', K {[1e30, *K[1:]]}, D {PLUMB_BOB}: fx: 1e+30 px "
            "gives a field of view of 3.7e-26 degrees across the 640 px image width",
        ),
        (
            camera_info(OUTSIDE_K, D=[0.0] * 5),
            f"CameraInfo 640x480, distortion 'plumb_bob', K {OUTSIDE_K}, D [0.0, 0.0, 0.0, 0.0, 0.0]: cx: "
            "the principal point's 1318.7 px lies outside the 640 px image width",
        ),
    ],
    ids=[
        "column-major",
        "k8-zero",
        "k7",
        "binning",
        "binning-y",
        "roi",
        "roi-size",
        "roi-offset",
        "fx-1e30",
        "cx-outside",
    ],
)
def test_camera_info_faults_are_refused_naming_the_topic_and_the_field(info, message):
    with pytest.raises(RosbagError) as err:
        camera_from_info(info, TOPIC)
    assert str(err.value).startswith(f"{TOPIC}: {message}") and "\n" not in str(err.value)


def test_camera_info_without_binning_or_roi_imports():
    """binning 0 or 1 and a roi of zeros or of the whole image all mean the full image (ROS's convention)."""
    for info in (camera_info(), camera_info(binning=(1, 1), roi=(0, 0, 640, 480))):
        camera = camera_from_info(info, TOPIC)
        assert (camera.fx, camera.fy, camera.cx, camera.cy) == (612.4, 611.9, 318.7, 242.1)
        assert (camera.width, camera.height) == (640, 480) and camera.model_name == "opencv"


# -------------------------------------------------------------------------------- deeply nested files
def test_load_yaml_and_load_json_name_the_file_of_a_deep_nesting():
    for text in (DEEP_YAML_FLOW, DEEP_YAML_BLOCK, "- " * 5000 + "1\n", "{a: " * 50_000):
        assert refused(load_yaml, text, "x.yaml") == f"x.yaml: {TOO_DEEP_LINE}"
    for text in ("[" * 100_000, '{"a": ' * 100_000, DEEP_JSON, DEEP_JSON.encode()):
        assert refused(load_json, text, "x.json") == f"x.json: {TOO_DEEP_LINE}"
    assert load_json(b'{"a": [1, 2.5e3]}', "x.json") == {"a": [1, 2500.0]}
    assert refused(load_json, b"\xff\xfe\x00", "x.json").startswith("x.json: not valid JSON")
    # a few levels, as calibrations nest, are fine
    nested = load_yaml("a:\n  b:\n    c: [[1, 2], {d: 1e-3}]\n", "x.yaml")
    assert nested == {"a": {"b": {"c": [[1, 2], {"d": 1e-3}]}}}


@pytest.mark.parametrize(
    "name, text",
    [
        ("flow.yaml", DEEP_YAML_FLOW),
        ("opencv.yaml", "%YAML:1.0\n---\nmodel_type: MEI\n" + DEEP_YAML_BLOCK),
        ("block.yaml", DEEP_YAML_BLOCK),
    ],
)
def test_load_camera_refuses_a_deep_file(tmp_path, name, text):
    path = write(tmp_path / name, text)
    assert refused(load_camera, path) == f"{path}: {TOO_DEEP_LINE}"


def test_calibration_files_refuse_a_deep_file(tmp_path):
    yaml_path = write(tmp_path / "camchain.yaml", "cam0:\n" + DEEP_YAML_BLOCK.replace("a:\n", "", 1))
    json_path = write(tmp_path / "calib.json", DEEP_JSON)
    for read, path in (
        (read_kalibr, yaml_path),
        (read_basalt, json_path),
        (read_calibration, yaml_path),
        (read_calibration, json_path),
    ):
        assert refused(read, path) == f"{path}: {TOO_DEEP_LINE}"


def test_rig_yaml_and_its_calibrations_refuse_a_deep_file(tmp_path):
    write(tmp_path / "a" / "rig.yaml", "cameras:\n  " + DEEP_YAML_FLOW)
    assert refused(RigLayout, tmp_path / "a") == f"{tmp_path / 'a' / 'rig.yaml'}: {TOO_DEEP_LINE}"
    write(tmp_path / "b" / "rig.yaml", "calibration: calib.json\n")
    write(tmp_path / "b" / "calib.json", DEEP_JSON)
    assert refused(RigLayout, tmp_path / "b") == f"{tmp_path / 'b' / 'calib.json'}: {TOO_DEEP_LINE}"
    write(tmp_path / "c" / "rig.yaml", "cameras:\n  - {name: front, calibration: front.yaml}\n")
    write(tmp_path / "c" / "front.yaml", DEEP_YAML_BLOCK)
    assert refused(RigLayout, tmp_path / "c") == f"{tmp_path / 'c' / 'front.yaml'}: {TOO_DEEP_LINE}"


def test_aria_and_real_world_json_refuse_a_deep_file(tmp_path):
    from fisheyedepth.data.aria import CALIBRATION, aria_to_rig
    from fisheyedepth.realworld.frames import adt_camera, scannetpp_camera

    records_table = load_script("tools/real_world").records_table

    path = write(tmp_path / "calib.json", '{"cam": ' + "[" * 100_000)
    assert refused(Fisheye624Camera.from_aria, path, "cam") == f"{path}: {TOO_DEEP_LINE}"
    assert refused(adt_camera, path, "cam") == f"{path}: {TOO_DEEP_LINE}"
    assert refused(scannetpp_camera, path) == f"{path}: {TOO_DEEP_LINE}"
    assert refused(records_table, [path]) == f"{path}: {TOO_DEEP_LINE}"
    src = tmp_path / "src"
    write(src / CALIBRATION, path.read_text())
    assert refused(aria_to_rig, src, tmp_path / "rig") == f"{src / CALIBRATION}: {TOO_DEEP_LINE}"
    assert not (tmp_path / "rig").exists()


def test_rosbag_extrinsics_refuse_a_deep_file(tmp_path, capsys):
    from fisheyedepth.cli.import_rosbag import main

    path = write(tmp_path / "extrinsics.yaml", DEEP_YAML_BLOCK)
    argv = [str(tmp_path / "no.bag"), "--out", str(tmp_path / "out"), "--camera", "front=/front/image_raw"]
    assert main([*argv, "--odometry", "/odom", "--extrinsics", str(path)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [f"error: {path}: {TOO_DEEP_LINE}"]


def test_predict_refuses_a_deep_or_implausible_camera_file(tmp_path, capsys, checkpoint, kitti_data):
    """``predict.py camera=FILE``: one ``error:`` line naming the file, exit status 2, nothing written."""
    import shutil

    from omegaconf import OmegaConf

    from fisheyedepth.cli import EXIT_USAGE, run_command
    from fisheyedepth.cli.predict import predict

    from conftest import ROOT, TRAIN_SEQ

    images = tmp_path / "in"
    images.mkdir()
    frame = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))[0]
    shutil.copy(frame, images / frame.name)
    base = OmegaConf.load(ROOT / "conf" / "predict.yaml")
    for hydra_only in ("defaults", "hydra"):
        base.pop(hydra_only, None)
    for name, text, message in (
        ("deep.yaml", DEEP_YAML_FLOW, TOO_DEEP_LINE),
        ("fx.yaml", opencv_pinhole_yaml(fx="1e30"), "key 'projection_parameters.fx': 1e+30 px gives a field"),
    ):
        calib = write(tmp_path / name, text)
        values = {"ckpt_path": str(checkpoint), "input": str(images), "camera": str(calib)}
        cfg = OmegaConf.merge(
            base, {"paths": {"output_dir": "unused"}, "output": str(tmp_path / "out"), **values}
        )
        with pytest.raises(SystemExit) as exit_info:
            run_command(predict, cfg)
        assert exit_info.value.code == EXIT_USAGE
        err = capsys.readouterr().err.strip().replace("\r", "\n").splitlines()  # after any progress bar
        assert err[-1].startswith(f"error: {calib}: {message}") and "Traceback" not in "\n".join(err)
        assert not [p for p in (tmp_path / "out").rglob("*") if p.is_file()]  # no prediction, no summary


# ------------------------------------------------------------------------------- every real camera passes
def shipped_cameras() -> dict[str, CameraModel]:
    """The cameras of the test suite, the presets, the synthetic rigs' cameras (fixed and drawn), and
    what resizing and flipping make of them."""
    from fisheyedepth.synthetic.rig import FAMILIES, make_rig, random_camera

    cameras = dict(all_cameras())
    cameras.update(tumvi_kb=presets.tumvi_kannala_brandt(), tumvi_ds=presets.tumvi_double_sphere())
    for index in (2, 3):
        for tangential in (False, True):
            cameras[f"kitti360_{index}_{tangential}"] = kitti360_camera(index, tangential)
    for name, camera in make_rig("surround4", 256).cameras.items():
        cameras[f"surround4_{name}"] = camera
    rng = np.random.default_rng(5)
    for family in FAMILIES:
        for size in (64, 384):
            cameras[f"random_{family}_{size}"] = random_camera(rng, family, size)
    for name, camera in list(cameras.items()):
        cameras[f"{name}_half"] = camera.resize(camera.width // 2, camera.height // 2)
        cameras[f"{name}_flipped"] = camera.flip()
    return cameras


def test_every_shipped_camera_passes_the_rule():
    cameras = shipped_cameras()
    assert len(cameras) == 3 * (15 + 2 + 4 + 4 + 16)
    for name, camera in cameras.items():
        assert check_plausible(camera) is camera, name
        assert CameraModel.from_dict(camera.to_dict()) == camera, name  # the readers' path
        fov = camera.field_of_view()
        assert 40 < min(fov) and max(fov) < 210, (name, fov)


def real_cameras(realdata: Path) -> dict[str, CameraModel]:
    """Every camera of ../shared/realdata, through the project's readers where it has one."""
    from fisheyedepth.realworld.frames import adt_camera, scannetpp_camera

    cameras = {f"kitti360 {i}": load_camera(realdata / "kitti360_frame" / f"image_0{i}.yaml") for i in (2, 3)}
    gen2 = realdata / "aria_gen2_rig" / "calib_slam_fisheye624.json"
    cameras.update({f"gen2 {n}": Fisheye624Camera.from_aria(gen2, n) for n in json.loads(gen2.read_text())})
    adt = realdata / "adt_slam" / "adt_sample.json"
    adt_cameras = json.loads(adt.read_text())["cameras"]
    cameras.update({f"adt {n}": adt_camera(adt, n) for n in adt_cameras})
    cameras["scannetpp"] = scannetpp_camera(realdata / "scannetpp_frame" / "calibration.json")
    device = json.loads((realdata / "aria_gen2_rig" / "device_calibration.json").read_text())
    kb_names = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4")
    for entry in device["CameraCalibrations"]:
        size = (entry["ConfigData"]["ImageWidth"], entry["ConfigData"]["ImageHeight"])
        params = entry["Projection"]["Params"]
        if entry["Projection"]["Name"] == "FisheyeRadTanThinPrism":
            cameras[f"device {entry['Label']}"] = Fisheye624Camera.from_aria_params(params, size)
        else:  # KannalaBrandtK3: fx fy cx cy k0..k3
            kb = dict(zip(kb_names, params, strict=True))
            cameras[f"device {entry['Label']}"] = KannalaBrandtCamera(width=size[0], height=size[1], **kb)
    fits = json.loads((realdata / "adt_slam" / "fitted_models.json").read_text())
    mei_names = ("gamma1", "gamma2", "u0", "v0", "xi", "k1", "k2", "p1", "p2")
    for name, fit in fits.items():
        w, h = adt_cameras[name]["image_size"]
        kb = dict(zip(kb_names, fit["KB4_opencv_fisheye"]["params"], strict=True))
        cameras[f"fit kb {name}"] = KannalaBrandtCamera(width=w, height=h, **kb)
        mei = dict(zip(mei_names, fit["mei_ucm_radtan"]["params"], strict=True))
        cameras[f"fit mei {name}"] = MeiCamera(width=w, height=h, **mei)
        ds = dict(zip(("fx", "fy", "cx", "cy", "xi", "alpha"), fit["double_sphere"]["params"], strict=True))
        if -1 < ds["xi"] <= 1:  # the RGB camera's fit diverged (xi 350, fx 2e5): the model refuses it itself
            cameras[f"fit ds {name}"] = DoubleSphereCamera(width=w, height=h, **ds)
    return cameras


def test_every_real_calibration_passes_the_rule(realdata):
    """And sits well inside its bounds: the evidence the bounds were chosen from."""
    cameras = real_cameras(realdata)
    assert len(cameras) == 25
    for name, camera in cameras.items():
        assert check_plausible(camera) is camera, name
        fu, fv = camera.paraxial_focal()
        assert 0.15 < fu / camera.width < 1.5 and 0.15 < fv / camera.height < 1.5, name
        cu, cv = camera.principal_point
        assert abs((cu + 0.5) / camera.width - 0.5) < 0.03, name
        assert abs((cv + 0.5) / camera.height - 0.5) < 0.03, name
        assert 80 < min(camera.field_of_view()) and max(camera.field_of_view()) < 205, name


def test_the_rule_is_the_one_every_reader_applies(tmp_path):
    """from_dict (every file reader, a CameraInfo), from_ros and from_aria_params refuse the same camera
    with the same reason; a camera built by code is not checked until it is read."""
    camera = dataclasses.replace(kitti360_camera(2), u0=-3.0)
    reason = "the principal point's -3 px lies outside the 1400 px image width (-0.5 to 1399.5)"
    with pytest.raises(CameraParameterError, match=re.escape(reason)) as info:
        check_plausible(camera)
    assert info.value.key == "u0"
    with pytest.raises(CameraParameterError, match=re.escape(reason)):
        CameraModel.from_dict(camera.to_dict())
    path = save_camera(camera, tmp_path / "cam.yaml")  # written by code, unchecked; read back, refused
    assert refused(load_camera, path).startswith(f"{path}: key 'u0': {reason}")
    reason = "the principal point's -3 px lies outside the 640 px image width (-0.5 to 639.5)"
    with pytest.raises(CameraParameterError, match=f"^cx: {re.escape(reason)}"):
        OpenCVCamera.from_ros(640, 480, [612.4, 0.0, -3.0, 0.0, 611.9, 242.1, 0.0, 0.0, 1.0], PLUMB_BOB)
    aria = aria_fisheye624()
    params = [aria.fx, -3.0, aria.cy, *(getattr(aria, k) for k in Fisheye624Camera.param_names()[4:])]
    with pytest.raises(CameraParameterError, match=f"^cx: {re.escape(reason)}"):
        Fisheye624Camera.from_aria_params(params, (640, 480))
