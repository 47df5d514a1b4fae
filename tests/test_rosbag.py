"""ROS bag import: small ROS 1 and ROS 2 (sqlite3, mcap) bags written with ``rosbags`` itself, from known
poses, calibration, extrinsics and images; the imported rig must reproduce every one of them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from fisheyedepth.cameras import KannalaBrandtCamera, PinholeCamera, load_camera
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.geometry import make_pose

from conftest import TRAIN_SEQ, quaternion_xyzw

rosbags = pytest.importorskip("rosbags")

T0 = 1_700_000_000_000_000_000  # ns
KB = {
    "fx": 110.0,
    "fy": 111.0,
    "cx": 127.2,
    "cy": 128.9,
    "k1": 0.01,
    "k2": -0.003,
    "k3": 0.0005,
    "k4": -0.0001,
}
# body -> imu -> cam_left (a chain of two static transforms), body -> cam_right
T_BODY_IMU = make_pose(torch.eye(3, dtype=torch.float64), torch.tensor([0.1, 0.0, 1.2])).numpy()
R_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera z forward = body x
T_IMU_LEFT = make_pose(torch.from_numpy(R_CAM), torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64)).numpy()
T_BODY_RIGHT = make_pose(torch.from_numpy(R_CAM), torch.tensor([0.1, -0.3, 1.2], dtype=torch.float64)).numpy()


def body_pose(t_ns: int) -> np.ndarray:
    """The known trajectory: 0.5 m/s along x and 0.1 rad/s of yaw (exact under linear + slerp)."""
    t = (t_ns - T0) * 1e-9
    yaw = 0.1 * t
    R = np.array([[math.cos(yaw), -math.sin(yaw), 0], [math.sin(yaw), math.cos(yaw), 0], [0, 0, 1.0]])
    return make_pose(torch.from_numpy(R), torch.tensor([0.5 * t, 0.0, 0.0], dtype=torch.float64)).numpy()


def write_bag(path: Path, kind: str, frames: list[np.ndarray]) -> None:
    """Two cameras (rgb8 Image and PNG CompressedImage, 10 Hz from T0), their CameraInfo, /tf_static,
    and odometry at 20 Hz from T0 + 50 ms to T0 + 450 ms (the first and last images fall outside)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if "tf2_msgs/msg/TFMessage" not in ts.types:
        ts.register(
            get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
        )
    T = ts.types
    Time, Header = T["builtin_interfaces/msg/Time"], T["std_msgs/msg/Header"]

    def header(stamp: int, frame: str):
        time = Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
        return Header(seq=0, stamp=time, frame_id=frame) if ros1 else Header(stamp=time, frame_id=frame)

    def transform(M: np.ndarray):
        q = quaternion_xyzw(M[:3, :3])
        return T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
            rotation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )

    def stamped(M, parent, child, stamp):
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent), child_frame_id=child, transform=transform(M)
        )

    def info(frame, stamp, model, d, k):
        fields = {"D": np.array(d, float), "K": np.array(k, float), "R": np.eye(3).ravel(), "P": np.zeros(12)}
        if not ros1:
            fields = {key.lower(): value for key, value in fields.items()}
        roi = T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        return T["sensor_msgs/msg/CameraInfo"](
            header=header(stamp, frame), height=256, width=256, distortion_model=model,
            binning_x=0, binning_y=0, roi=roi, **fields,
        )  # fmt: skip

    messages = []  # (topic, msgtype, stamp, message)
    static = [stamped(T_BODY_IMU, "base_link", "imu", T0), stamped(T_IMU_LEFT, "imu", "cam_left", T0),
              stamped(T_BODY_RIGHT, "base_link", "cam_right", T0)]  # fmt: skip
    messages.append(
        ("/tf_static", "tf2_msgs/msg/TFMessage", T0, T["tf2_msgs/msg/TFMessage"](transforms=static))
    )
    k_left = [KB["fx"], 0, KB["cx"], 0, KB["fy"], KB["cy"], 0, 0, 1]
    d_left = [KB["k1"], KB["k2"], KB["k3"], KB["k4"]]
    k_right = [90.0, 0, 127.5, 0, 90.0, 127.5, 0, 0, 1]
    info_type = "sensor_msgs/msg/CameraInfo"
    messages.append(("/left/camera_info", info_type, T0, info("cam_left", T0, "equidistant", d_left, k_left)))
    messages.append(
        ("/right/camera_info", info_type, T0, info("cam_right", T0, "plumb_bob", [0.0] * 5, k_right))
    )
    for i, bgr in enumerate(frames):
        stamp = T0 + i * 100_000_000
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        image = T["sensor_msgs/msg/Image"](
            header=header(stamp, "cam_left"), height=256, width=256, encoding="rgb8", is_bigendian=0,
            step=256 * 3, data=rgb.ravel(),
        )  # fmt: skip
        messages.append(("/left/image_raw", "sensor_msgs/msg/Image", stamp, image))
        png = np.frombuffer(cv2.imencode(".png", bgr)[1].tobytes(), np.uint8)
        compressed = T["sensor_msgs/msg/CompressedImage"](
            header=header(stamp, "cam_right"), format="png", data=png
        )
        messages.append(("/right/image_raw/compressed", "sensor_msgs/msg/CompressedImage", stamp, compressed))
    for j in range(9):
        stamp = T0 + 50_000_000 + j * 50_000_000
        M = body_pose(stamp)
        q = quaternion_xyzw(M[:3, :3])
        pose = T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=M[0, 3], y=M[1, 3], z=M[2, 3]),
            orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
        )
        cov = np.zeros(36)
        odom = T["nav_msgs/msg/Odometry"](
            header=header(stamp, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](
                    linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                ),
                covariance=cov,
            ),
        )  # fmt: skip
        messages.append(("/odom", "nav_msgs/msg/Odometry", stamp, odom))
        tf = T["tf2_msgs/msg/TFMessage"](transforms=[stamped(M, "odom", "base_link", stamp)])
        messages.append(("/tf", "tf2_msgs/msg/TFMessage", stamp, tf))
    messages.sort(key=lambda m: m[2])
    if ros1:
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), ts.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "ros2-mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=9, storage_plugin=plugin), ts.serialize_cdr
    with writer:
        connections = {}
        for topic, msgtype, stamp, msg in messages:
            if topic not in connections:
                connections[topic] = writer.add_connection(topic, msgtype, typestore=ts)
            writer.write(connections[topic], stamp, serialize(msg, msgtype))


@pytest.fixture(scope="module")
def frames(kitti_data):
    src = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))[:6]
    return [cv2.imread(str(p)) for p in src]


@pytest.mark.parametrize("kind", ["ros1", "ros2-sqlite3", "ros2-mcap"])
@pytest.mark.parametrize("poses", ["odometry", "tf"])
def test_an_imported_bag_reproduces_poses_stamps_calibration_and_pixels(kind, poses, frames, tmp_path):
    from fisheyedepth.data.rosbag import import_rosbag

    bag = tmp_path / ("run.bag" if kind == "ros1" else "run")
    write_bag(bag, kind, frames)
    out = tmp_path / "rig"
    source = {"odometry": "/odom"} if poses == "odometry" else {"tf_poses": ("odom", "base_link")}
    summary = import_rosbag(
        bag, out, {"left": "/left/image_raw", "right": "/right/image_raw/compressed"}, **source
    )
    # images at T0 and T0 + 500 ms lie outside the poses (T0 + 50 ms .. T0 + 450 ms): dropped, counted
    assert summary["images"] == {"left": 4, "right": 4}
    assert summary["outside_poses"] == {"left": 2, "right": 2} and summary["poses"] == 9
    assert summary["duplicate_stamps"] == {"left": 0, "right": 0}
    layout = RigLayout(out)
    assert load_camera(out / "calibration" / "left.yaml") == KannalaBrandtCamera(width=256, height=256, **KB)
    assert layout.cameras["right"].camera == PinholeCamera(
        width=256, height=256, fx=90.0, fy=90.0, cx=127.5, cy=127.5
    )
    assert np.allclose(layout.cameras["left"].cam_to_body, T_BODY_IMU @ T_IMU_LEFT, atol=1e-12)
    assert np.allclose(layout.cameras["right"].cam_to_body, T_BODY_RIGHT, atol=1e-12)
    assert layout.topics == {"left": "/left/image_raw", "right": "/right/image_raw/compressed"}
    assert layout.frame_ids == {"left": "cam_left", "right": "cam_right"}  # what a bag of its outputs names
    for name in ("left", "right"):
        kept = layout.frames("seq0", name)
        assert [f.key for f in kept] == [T0 + i * 100_000_000 for i in range(1, 5)]
        for i, frame in enumerate(kept, start=1):
            assert np.allclose(frame.pose, body_pose(frame.key), atol=1e-9)  # interpolated at the stamp
            pixels = cv2.imread(str(layout.image("seq0", name, frame)))
            assert np.array_equal(pixels, frames[i])  # lossless, in BGR order, for both encodings
    with pytest.raises(FileExistsError, match="rig.yaml exists"):
        import_rosbag(bag, out, {"left": "/left/image_raw"}, odometry="/odom")


@pytest.mark.parametrize("kind", ["ros1", "ros2-mcap"])
def test_a_bag_in_and_a_bag_out(kind, frames, tmp_path, capsys):
    """``fisheyedepth-multiview`` reads a bag as the importer does (its options), leaves no folder of its
    import behind, and writes its outputs as a bag under the input's topics and frames, at its stamps."""
    from fisheyedepth.cli.multiview import main

    from test_rosout import read_back

    bag = tmp_path / ("run.bag" if kind == "ros1" else "run")
    write_bag(bag, kind, frames)
    out, bag_out = tmp_path / "out", tmp_path / "distance.mcap"
    cameras = ["--camera", "left=/left/image_raw", "--camera", "right=/right/image_raw/compressed"]
    args = [str(bag), "--out", str(out), *cameras, "--odometry", "/odom", "--bag-out", str(bag_out),
            "--max-distance", "20", "--quiet"]  # fmt: skip
    assert main(args) in (0, 1)  # 1: ran, but one scene seen by two cameras keeps no pixel
    summary = json.loads((out / "summary.json").read_text())
    assert summary["root"] == str(bag) and len(summary["images"]) == 8
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([bag.name, "out", "distance.mcap"])
    found = read_back(bag_out)
    stamps = [T0 + i * 100_000_000 for i in range(1, 5)]  # the imported images: those within the poses
    for ns, frame in (("/left", "cam_left"), ("/right", "cam_right")):
        for what in ("distance", "confidence", "camera_info", "points"):
            assert [s for s, _, _ in found[f"{ns}/{what}"]] == stamps, (ns, what)
        assert {msg.header.frame_id for _, _, msg in found[f"{ns}/distance"]} == {frame}
    assert found["/left/camera_info"][0][2].distortion_model == "equidistant"
    assert found["/right/camera_info"][0][2].distortion_model == "plumb_bob"
    static = {t.child_frame_id for t in found["/tf_static"][0][2].transforms}
    assert static == {"cam_left", "cam_right"}
    assert len(found["/tf"]) == 4  # one body pose an instant
    assert main([str(bag), "--out", str(tmp_path / "o2"), "--quiet"]) == 2  # a bag needs its topics
    assert "a ROS bag; name its cameras and poses" in capsys.readouterr().err
    rig = tmp_path / "rig"
    from fisheyedepth.data.rosbag import import_rosbag

    import_rosbag(bag, rig, {"left": "/left/image_raw"}, odometry="/odom")
    assert main([str(rig), "--out", str(tmp_path / "o3"), "--odometry", "/odom", "--quiet"]) == 2
    assert "--odometry: options of a ROS bag given as" in capsys.readouterr().err


def camera_info(ros: str, model: str, D, K, width=640, height=480):
    """A ``sensor_msgs/CameraInfo`` of ROS 1 (fields D, K, R, P) or ROS 2 (d, k, r, p), as in rosbags."""
    from rosbags.typesys import Stores, get_typestore

    T = get_typestore(Stores.ROS1_NOETIC if ros == "ros1" else Stores.ROS2_HUMBLE).types
    stamp = T["builtin_interfaces/msg/Time"](sec=0, nanosec=0)
    header = (
        {"stamp": stamp, "frame_id": "c"} if ros == "ros2" else {"seq": 0, "stamp": stamp, "frame_id": "c"}
    )
    roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    P = np.zeros(12)
    P[[0, 2, 5, 6, 10]] = [K[0], K[2], K[4], K[5], 1.0]  # the rectified image's: ignored
    fields = {"D": np.array(D, float), "K": np.array(K, float), "R": np.eye(3).ravel(), "P": P}
    fields = {(k if ros == "ros1" else k.lower()): v for k, v in fields.items()}
    return T["sensor_msgs/msg/CameraInfo"](
        header=T["std_msgs/msg/Header"](**header), height=height, width=width, distortion_model=model,
        binning_x=0, binning_y=0, roi=roi, **fields,
    )  # fmt: skip


@pytest.mark.parametrize("ros", ["ros1", "ros2"])
def test_camera_info_distortion_models(ros):
    """plumb_bob (5) and rational_polynomial (8) become the opencv model, projecting as
    ``cv2.projectPoints``; equidistant (4) Kannala-Brandt as ``cv2.fisheye``; no distortion a pinhole;
    anything else is refused with the topic, the model and the coefficient count."""
    from fisheyedepth.cameras import CAMERA_MODELS
    from fisheyedepth.data.rosbag import RosbagError, camera_from_info

    K = [612.4, 0.0, 318.7, 0.0, 611.9, 242.1, 0.0, 0.0, 1.0]
    K3 = np.array(K).reshape(3, 3)
    points = np.array([[0.3, -0.2, 1.0], [-0.45, 0.31, 1.4], [0.02, 0.5, 2.2], [0.0, 0.0, 3.0]])

    def uv(camera):
        out, valid = camera.project(torch.from_numpy(points))
        assert bool(valid.all())
        return out.numpy()

    plumb_bob = [-0.2834, 0.0739, 0.00019, 1.76e-05, -0.0121]  # k1 k2 p1 p2 k3
    camera = camera_from_info(camera_info(ros, "plumb_bob", plumb_bob, K), "/cam/camera_info")
    assert isinstance(camera, CAMERA_MODELS["opencv"]) and (camera.width, camera.height) == (640, 480)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (612.4, 611.9, 318.7, 242.1)
    assert [camera.k1, camera.k2, camera.p1, camera.p2, camera.k3] == plumb_bob
    assert (camera.k4, camera.k5, camera.k6) == (0, 0, 0)
    expected = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K3, np.array(plumb_bob))[0].reshape(-1, 2)
    assert np.allclose(uv(camera), expected, atol=1e-6)

    rational = [0.41, -0.023, 0.0003, -0.0002, 0.0011, 0.77, 0.052, 0.0019]  # k1 k2 p1 p2 k3 k4 k5 k6
    camera = camera_from_info(camera_info(ros, "rational_polynomial", rational, K), "/cam/camera_info")
    assert camera.model_name == "opencv"
    names = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
    assert [getattr(camera, name) for name in names] == rational
    expected = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K3, np.array(rational))[0].reshape(-1, 2)
    assert np.allclose(uv(camera), expected, atol=1e-6)

    equidistant = [0.0103, -0.0021, 0.0006, -0.0001]
    camera = camera_from_info(camera_info(ros, "equidistant", equidistant, K), "/cam/camera_info")
    assert camera == KannalaBrandtCamera(width=640, height=480, fx=612.4, fy=611.9, cx=318.7, cy=242.1,
                                         k1=0.0103, k2=-0.0021, k3=0.0006, k4=-0.0001)  # fmt: skip
    expected = cv2.fisheye.projectPoints(points[:, None], np.zeros((3, 1)), np.zeros((3, 1)), K3,
                                         np.array(equidistant))[0].reshape(-1, 2)  # fmt: skip
    assert np.allclose(uv(camera), expected, atol=1e-6)

    for model, D in (("plumb_bob", [0.0] * 5), ("rational_polynomial", [0.0] * 8), ("", [])):
        camera = camera_from_info(camera_info(ros, model, D, K), "/cam/camera_info")
        assert camera == PinholeCamera(width=640, height=480, fx=612.4, fy=611.9, cx=318.7, cy=242.1)

    for model, D, count in (
        ("plumb_bob", [0.1, 0.0, 0.0, 0.0], 4),  # one short
        ("rational_polynomial", [0.1, 0.0, 0.0, 0.0, 0.0], 5),  # plumb_bob's count under the other name
        ("equidistant", [0.01, 0.0, 0.0, 0.0, 0.0], 5),
        ("fisheye", [0.01, 0.0, 0.0, 0.0], 4),
        ("", [0.1, 0.0, 0.0, 0.0, 0.0], 5),  # distortion without a model
    ):
        with pytest.raises(RosbagError) as info:
            camera_from_info(camera_info(ros, model, D, K), "/cam/camera_info")
        message = str(info.value)
        assert message.startswith(f"/cam/camera_info: distortion model {model!r} with {count} coefficients")
        assert "is not supported (expected plumb_bob with 5" in message

    with pytest.raises(
        RosbagError, match=r"/cam/camera_info: CameraInfo 640x480, distortion 'plumb_bob'.*fx"
    ):
        camera_from_info(camera_info(ros, "plumb_bob", plumb_bob, [-612.4, *K[1:]]), "/cam/camera_info")


def test_unsupported_input_is_named(frames, tmp_path):
    from fisheyedepth.cli.import_rosbag import main
    from fisheyedepth.data.rosbag import RosbagError, import_rosbag

    bag = tmp_path / "run"
    write_bag(bag, "ros2-sqlite3", frames)
    with pytest.raises(RosbagError, match=r"topic /front/image_raw is not in the bag"):
        import_rosbag(bag, tmp_path / "a", {"front": "/front/image_raw"}, odometry="/odom")
    with pytest.raises(ValueError, match="exactly one of odometry=TOPIC or tf_poses"):
        import_rosbag(bag, tmp_path / "b", {"left": "/left/image_raw"})
    # a problem with the second camera stops the import before anything is written
    with pytest.raises(ValueError, match="missing.yaml: cannot read calibration file"):
        import_rosbag(
            bag, tmp_path / "e", {"left": "/left/image_raw", "right": "/right/image_raw/compressed"},
            calibrations={"right": tmp_path / "missing.yaml"}, odometry="/odom",
        )  # fmt: skip
    assert not (tmp_path / "e").exists()
    # the console script: one error line, exit 2; a good run prints the summary
    assert main([str(bag), "--out", str(tmp_path / "c"), "--camera", "x=/nope", "--odometry", "/odom"]) == 2
    assert (
        main(
            [
                str(bag),
                "--out",
                str(tmp_path / "d"),
                "--camera",
                "left=/left/image_raw",
                "--odometry",
                "/odom",
            ]
        )
        == 0
    )
    assert (tmp_path / "d" / "rig.yaml").is_file()


def test_given_calibration_and_extrinsics_replace_the_bags(frames, tmp_path):
    """``--calibration NAME=FILE`` and ``--extrinsics FILE.yaml`` take the place of CameraInfo and
    /tf_static (a bag without them, or with wrong ones)."""
    import yaml

    from fisheyedepth.cameras import save_camera
    from fisheyedepth.cli.import_rosbag import main

    bag = tmp_path / "run.bag"
    write_bag(bag, "ros1", frames)
    mine = KannalaBrandtCamera(width=256, height=256, fx=99.0, fy=98.0, cx=128.0, cy=127.0, k1=0.02)
    save_camera(mine, tmp_path / "mine.yaml")
    given = np.eye(4)
    given[:3, 3] = [0.5, 0.25, 1.0]
    (tmp_path / "extrinsics.yaml").write_text(yaml.safe_dump({"left": given.tolist()}))
    args = [
        str(bag),
        "--out",
        str(tmp_path / "rig"),
        "--camera",
        "left=/left/image_raw",
        "--odometry",
        "/odom",
    ]
    args += [
        "--calibration",
        f"left={tmp_path / 'mine.yaml'}",
        "--extrinsics",
        str(tmp_path / "extrinsics.yaml"),
    ]
    assert main(args) == 0
    layout = RigLayout(tmp_path / "rig")
    assert layout.cameras["left"].camera == mine
    assert np.allclose(layout.cameras["left"].cam_to_body, given)
    assert main(args) == 2  # the second run would overwrite: refused
    assert main([*args, "--overwrite"]) == 0
