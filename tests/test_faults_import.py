"""Faults of the ROS bag importer and the rig layout's pose file: gaps in the odometry, 12-bit images in
16-bit messages, inputs the loader would refuse, corrupt messages, an uncalibrated CameraInfo, and
quaternions in the wrong order. Small ROS 2 bags built message by message with ``rosbags``."""

from __future__ import annotations

import logging
import math
import re
import shutil

import cv2
import numpy as np
import pytest
import yaml

from fisheyedepth.data import FisheyeDataModule
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.images import read_image

from conftest import quaternion_xyzw
from test_faults_data import write_tiny_rig
from test_rosbag import T0, body_pose

rosbags = pytest.importorskip("rosbags")

W, H = 32, 24
K = [20.0, 0, 15.5, 0, 20.0, 11.5, 0, 0, 1]
IMAGE, COMPRESSED, INFO = "/cam/image_raw", "/cam/image_raw/compressed", "/cam/camera_info"
MS = 1_000_000


class Bag:
    """A ROS 2 (sqlite3) bag of a camera ``cam``: add messages, then ``write``."""

    def __init__(self):
        from rosbags.typesys import Stores, get_typestore

        self.ts = get_typestore(Stores.ROS2_HUMBLE)
        self.T, self.messages = self.ts.types, []

    def header(self, stamp: int, frame: str = "cam"):
        time = self.T["builtin_interfaces/msg/Time"](sec=stamp // 10**9, nanosec=stamp % 10**9)
        return self.T["std_msgs/msg/Header"](stamp=time, frame_id=frame)

    def image(self, stamp: int, pixels: np.ndarray, encoding: str = "mono8", topic: str = IMAGE):
        data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
        self.messages.append((topic, stamp, self.T["sensor_msgs/msg/Image"](
            header=self.header(stamp), height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
            is_bigendian=0, step=data.size // pixels.shape[0], data=data,
        )))  # fmt: skip

    def compressed(self, stamp: int, data: bytes, topic: str = COMPRESSED):
        msg = self.T["sensor_msgs/msg/CompressedImage"](
            header=self.header(stamp), format="png", data=np.frombuffer(data, np.uint8)
        )
        self.messages.append((topic, stamp, msg))

    def info(self, width: int = W, height: int = H, k=K):
        roi = self.T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        )
        self.messages.append((INFO, T0, self.T["sensor_msgs/msg/CameraInfo"](
            header=self.header(T0), height=height, width=width, distortion_model="plumb_bob",
            d=np.zeros(5), k=np.array(k, float), r=np.eye(3).ravel(), p=np.zeros(12), binning_x=0,
            binning_y=0, roi=roi,
        )))  # fmt: skip

    def odometry(self, stamps, shift: float = 0.0, norm: float = 1.0):
        T = self.T
        zero, cov = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0), np.zeros(36)
        for stamp in stamps:
            M = body_pose(stamp)
            q = [v * norm for v in quaternion_xyzw(M[:3, :3])]
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=M[0, 3] + shift, y=M[1, 3], z=M[2, 3]),
                orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            )
            self.messages.append(("/odom", stamp, T["nav_msgs/msg/Odometry"](
                header=self.header(stamp, "odom"), child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=cov
                ),
            )))  # fmt: skip

    def write(self, path):
        from rosbags.rosbag2 import StoragePlugin, Writer

        with Writer(path, version=9, storage_plugin=StoragePlugin.SQLITE3) as writer:
            connections = {}
            for topic, stamp, msg in sorted(self.messages, key=lambda m: m[1]):
                if topic not in connections:
                    connections[topic] = writer.add_connection(topic, msg.__msgtype__, typestore=self.ts)
                writer.write(connections[topic], stamp, self.ts.serialize_cdr(msg, msg.__msgtype__))
        return path


def odometry_30hz(seconds: float, skip=lambda t: False) -> list[int]:
    return [T0 + round(k * 1e9 / 30) for k in range(round(seconds * 30) + 1) if not skip(k / 30)]


def grey(i: int) -> np.ndarray:
    return np.random.default_rng(i).integers(0, 256, (H, W), dtype=np.uint8)


def camera_bag(path, frames: int = 4, **images) -> Bag:
    """``frames`` grey mono8 images at 10 Hz from T0, their CameraInfo, odometry at 30 Hz over them."""
    bag = Bag()
    bag.info()
    for i in range(frames):
        bag.image(T0 + i * 100 * MS, grey(i), **images)
    bag.odometry(odometry_30hz((frames - 1) / 10))
    bag.write(path)
    return bag


def run(bag, out, **options):
    from fisheyedepth.data.rosbag import import_rosbag

    topic = options.pop("topic", IMAGE)
    return import_rosbag(bag, out, {"cam": topic}, info_topics={"cam": INFO},
                         extrinsics={"cam": np.eye(4)}, odometry="/odom", **options)  # fmt: skip


def cli(bag, out, topic, *options) -> int:
    from fisheyedepth.cli.import_rosbag import main

    extrinsics = bag.parent / "extrinsics.yaml"
    extrinsics.write_text(yaml.safe_dump({"cam": np.eye(4).tolist()}))
    return main([str(bag), "--out", str(out), "--camera", f"cam={topic}", "--camera-info", f"cam={INFO}",
                 "--odometry", "/odom", "--extrinsics", str(extrinsics), *options])  # fmt: skip


def leftovers(out) -> list[str]:
    """Hidden entries beside ``out``: what a failed or finished import would leave of its temporary folder."""
    return sorted(p.name for p in out.parent.iterdir() if p.name.startswith("."))


# 1. Gaps in the odometry ---------------------------------------------------------------------------------


def test_images_in_an_odometry_gap_are_dropped_and_counted_by_the_importer(tmp_path, caplog):
    """30 Hz odometry over 9.9 s with nothing between 2 s and 7 s; images at 10 Hz. The 49 images strictly
    inside the gap were given poses interpolated across 5 s."""
    bag = Bag()
    bag.info()
    for i in range(100):
        bag.image(T0 + i * 100 * MS, grey(i))
    bag.odometry(odometry_30hz(9.9, skip=lambda t: 2 < t < 7))
    bag.write(tmp_path / "run")
    with caplog.at_level(logging.WARNING):
        summary = run(tmp_path / "run", tmp_path / "rig")
    kept = sorted(int(p.stem) for p in (tmp_path / "rig" / "seq0" / "images" / "cam").glob("*.png"))
    assert len(kept) == 51 and T0 + 2000 * MS in kept and T0 + 7000 * MS in kept  # on a pose: exact, kept
    assert not any(T0 + 2000 * MS < t < T0 + 7000 * MS for t in kept)
    assert summary["pose_gaps"] == {"cam": 49} and summary["images"] == {"cam": 51}
    assert summary["max_pose_gap"] == pytest.approx(5 / 30, abs=1e-6)  # 5 median intervals of 30 Hz
    assert re.search(
        r"/cam/image_raw: 49 images lie in gaps of /odom longer than 0\.167 s.*5\.000 s", caplog.text
    )
    # a bound that covers the gap keeps them all, and rig.yaml tells the loader the same bound
    summary = run(tmp_path / "run", tmp_path / "wide", max_pose_gap=6.0)
    assert summary["pose_gaps"] == {"cam": 0} and summary["images"] == {"cam": 100}
    assert yaml.safe_load((tmp_path / "wide" / "rig.yaml").read_text())["max_pose_gap"] == 6.0
    assert len(RigLayout(tmp_path / "wide").frames("seq0", "cam")) == 100


def test_frames_in_a_gap_of_the_pose_file_are_left_out_by_the_rig_layout(tmp_path, caplog):
    """Poses at 10 Hz with none between 1.0 s and 2.5 s; images 50 ms after each 100 ms tick."""
    t0 = 10**18
    ticks = [*range(0, 11), *range(25, 31)]
    path = write_tiny_rig(tmp_path, [t0 + k * 10**8 for k in ticks], [0.1 * k for k in ticks],
                          [t0 + k * 10**8 + 5 * 10**7 for k in range(30)])  # fmt: skip
    with caplog.at_level(logging.WARNING):
        layout = RigLayout(tmp_path)
        frames = layout.frames("drive", "cam")
    assert len(frames) == 15 and len(layout.in_gaps[("drive", "cam")]) == 15
    assert layout.in_gaps[("drive", "cam")][0] == t0 + 1050 * MS
    assert f"{path.parent}: 15 images of cam lie in gaps of the poses longer than 0.500 s" in caplog.text
    assert len(RigLayout(tmp_path, max_pose_gap=2.0).frames("drive", "cam")) == 30
    data = FisheyeDataModule(tmp_path, layout="rig", max_pose_gap=2.0)  # data.datamodule.max_pose_gap
    assert len(data.layout.frames("drive", "cam")) == 30
    with pytest.raises(ValueError, match="max_pose_gap: only the rig layout"):
        FisheyeDataModule(tmp_path, layout="kitti360", max_pose_gap=2.0)
    rig = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump({**rig, "max_pose_gap": 2.0}))
    assert len(RigLayout(tmp_path).frames("drive", "cam")) == 30
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump({**rig, "max_pose_gap": -1}))
    with pytest.raises(ValueError, match=r"rig.yaml: key 'max_pose_gap': expected seconds > 0, got -1"):
        RigLayout(tmp_path)


# 2. 12 bits of data in 16-bit images -------------------------------------------------------------------


def test_twelve_bit_mono16_is_scaled_by_the_bit_depth_of_the_whole_topic(tmp_path):
    """A 12-bit camera's mono16 (at most 4095) read as 16 bits peaks at 6 % brightness. One dark frame
    (at most 100) must not decide the scaling: the depth is detected over the topic."""
    bag = Bag()
    bag.info()
    ramp = np.linspace(0, 4095, W * H).round().astype(np.uint16).reshape(H, W)
    for i in range(6):
        bag.image(T0 + i * 100 * MS, ramp if i else ramp // 41, "mono16")  # the first frame is dark
    bag.odometry(odometry_30hz(0.5))
    bag.write(tmp_path / "run")
    summary = run(tmp_path / "run", tmp_path / "rig")
    folder = tmp_path / "rig" / "seq0" / "images" / "cam"
    assert read_image(folder / f"{T0 + 100 * MS}.png").bgr.max() == 255  # what training reads (was 15)
    bright = cv2.imread(str(folder / f"{T0 + 100 * MS}.png"), cv2.IMREAD_UNCHANGED)
    dark = cv2.imread(str(folder / f"{T0}.png"), cv2.IMREAD_UNCHANGED)
    assert bright.dtype == np.uint16 and bright.max() == 65535
    assert np.array_equal(bright, np.rint(ramp * (65535 / 4095)).astype(np.uint16))
    assert dark.max() == 1584  # the same factor: 99 -> 1584 (99 * 65535 / 4095), not stretched to white
    assert summary["bit_depth"] == {"cam": 12} and summary["images"] == {"cam": 6}
    # given, it wins (16: the pixels as they are)
    assert cli(tmp_path / "run", tmp_path / "raw", IMAGE, "--bit-depth", "16") == 0
    raw = cv2.imread(
        str(tmp_path / "raw" / "seq0" / "images" / "cam" / f"{T0 + 100 * MS}.png"), cv2.IMREAD_UNCHANGED
    )
    assert np.array_equal(raw, ramp)


# 3. What the loader refuses is refused before anything is written ------------------------------------


def test_repeated_odometry_stamps_with_two_poses_are_refused_naming_bag_topic_and_stamp(tmp_path):
    from fisheyedepth.data.rosbag import RosbagError

    stamps = odometry_30hz(0.3)
    bag = camera_bag(tmp_path / "run")
    bag.odometry([stamps[4]], shift=1.0)  # the stamp again, with another pose
    bag.write(tmp_path / "clash")
    where = re.escape(str(tmp_path / "clash"))
    with pytest.raises(
        RosbagError,
        match=rf"^{where}: /odom: 1 stamps carry two different poses \(the first at {stamps[4]} ns",
    ):
        run(tmp_path / "clash", tmp_path / "rig")
    assert not (tmp_path / "rig").exists() and leftovers(tmp_path / "rig") == []
    bag.messages.pop()
    bag.odometry([stamps[4]])  # the same pose again, exactly: harmless, one is kept
    bag.write(tmp_path / "repeat")
    assert run(tmp_path / "repeat", tmp_path / "rig")["repeated_poses"] == 1
    assert len(RigLayout(tmp_path / "rig").frames("seq0", "cam")) == 4


@pytest.mark.parametrize(
    "index, wrong, said",
    [
        (5, {"norm": 2.0}, "quaternion of norm 2;"),  # a column gone wrong, not a rotation
        (3, {"shift": float("nan")}, "not a rigid transform: it holds a value that is not finite"),  # lost
    ],
)
def test_an_odometry_pose_that_is_no_rigid_motion_is_refused_naming_bag_topic_and_stamp(
    tmp_path, index, wrong, said
):
    from fisheyedepth.data.rosbag import RosbagError

    stamps = odometry_30hz(0.3)
    bag = Bag()
    bag.info()
    for i in range(4):
        bag.image(T0 + i * 100 * MS, grey(i))
    bag.odometry([s for s in stamps if s != stamps[index]])
    bag.odometry([stamps[index]], **wrong)
    bag.write(tmp_path / "bag")
    where = re.escape(str(tmp_path / "bag"))
    with pytest.raises(RosbagError, match=rf"^{where}: /odom: the pose at {stamps[index]} ns: {said}"):
        run(tmp_path / "bag", tmp_path / "rig")
    assert not (tmp_path / "rig").exists() and leftovers(tmp_path / "rig") == []


@pytest.mark.parametrize(
    "scale, said",
    [
        (float("nan"), r"/tf_static base_link -> cam_right: not a rigid transform: it holds a value that is not finite"),  # noqa: E501
        (1000.0, r"cameras 'left' and 'right' lie 1\d{3}(\.\d+)? m apart; .* \(extrinsics are in metres: millimetres\?\)"),  # noqa: E501
    ],
)  # fmt: skip
def test_static_transforms_must_be_rigid_and_in_metres(tmp_path, monkeypatch, kitti_data, scale, said):
    """/tf_static goes through the one rigid-transform check (a translation that is not finite named by
    its edge); a rig whose transforms are in millimetres is refused by the rig layout's bound before
    anything is written."""
    import cv2

    from fisheyedepth.data.rosbag import RosbagError, import_rosbag

    import test_rosbag
    from conftest import TRAIN_SEQ

    right = test_rosbag.T_BODY_RIGHT.copy()
    right[:3, 3] *= scale
    monkeypatch.setattr(test_rosbag, "T_BODY_RIGHT", right)
    src = sorted((kitti_data / "data_2d_raw" / TRAIN_SEQ / "image_02" / "data_rgb").glob("*.png"))[:6]
    test_rosbag.write_bag(tmp_path / "run", "ros2-sqlite3", [cv2.imread(str(p)) for p in src])
    with pytest.raises(RosbagError, match=said):
        cameras = {"left": "/left/image_raw", "right": "/right/image_raw/compressed"}
        import_rosbag(tmp_path / "run", tmp_path / "rig", cameras, odometry="/odom")
    assert not (tmp_path / "rig").exists() and leftovers(tmp_path / "rig") == []


@pytest.mark.parametrize("kind", ["Image", "CompressedImage"])
def test_camera_info_of_another_size_is_refused_naming_bag_topic_and_both_sizes(tmp_path, kind):
    """Same aspect ratio, twice the size: every image would be refused by the dataset's size check."""
    from fisheyedepth.data.rosbag import RosbagError

    bag = Bag()
    bag.info(width=2 * W, height=2 * H)
    for i in range(4):
        if kind == "Image":
            bag.image(T0 + i * 100 * MS, grey(i))
        else:
            bag.compressed(T0 + i * 100 * MS, cv2.imencode(".png", grey(i))[1].tobytes())
    bag.odometry(odometry_30hz(0.3))
    bag.write(tmp_path / "run")
    topic = IMAGE if kind == "Image" else COMPRESSED
    with pytest.raises(
        RosbagError,
        match=rf"^{re.escape(str(tmp_path / 'run'))}: {topic}: .*32x24, but the calibration.* is 64x48",
    ):
        run(tmp_path / "run", tmp_path / "rig", topic=topic)
    assert not (tmp_path / "rig").exists() and leftovers(tmp_path / "rig") == []


def test_an_import_the_rig_layout_would_refuse_is_not_moved_into_place(tmp_path):
    """An extrinsic that is not rigid: the finished import is opened with ``RigLayout`` first."""
    from fisheyedepth.data.rosbag import import_rosbag

    camera_bag(tmp_path / "run")
    sheared = np.eye(4)
    sheared[0, 1] = 0.1
    rig_yaml = re.escape(str(tmp_path / "rig" / "rig.yaml"))  # the file the import would have written
    message = (
        rf"run: the import would not load for training: {rig_yaml}: key 'cameras\[0\].cam_to_body': not a"
    )
    with pytest.raises(ValueError, match=message):
        import_rosbag(tmp_path / "run", tmp_path / "rig", {"cam": IMAGE}, extrinsics={"cam": sheared},
                      odometry="/odom")  # fmt: skip
    assert not (tmp_path / "rig").exists() and leftovers(tmp_path / "rig") == []


# 4. A corrupt message ----------------------------------------------------------------------------------


def test_a_corrupt_compressed_image_is_skipped_and_counted_or_refused_with_strict(tmp_path, caplog):
    """Frame 12 of 20 is garbage. It used to abort the import with 12 PNGs written, no rig.yaml, and a
    re-run that demanded --overwrite."""
    from fisheyedepth.data.rosbag import RosbagError

    bag = Bag()
    bag.info()
    for i in range(20):
        png = cv2.imencode(".png", grey(i))[1].tobytes()
        bag.compressed(T0 + i * 100 * MS, png if i != 12 else b"\x89PNG\r\n\x1a\n" + bytes(200))
    bag.odometry(odometry_30hz(1.9))
    bag.write(tmp_path / "run")
    bad = T0 + 1200 * MS
    with caplog.at_level(logging.WARNING):
        summary = run(tmp_path / "run", tmp_path / "rig", topic=COMPRESSED)
    assert len(RigLayout(tmp_path / "rig").frames("seq0", "cam")) == 19
    assert summary["corrupt"] == {"cam": 1} and summary["images"] == {"cam": 19}
    assert f"{COMPRESSED}: 1 corrupt image messages skipped, at {bad} ns" in caplog.text
    # --strict refuses it, and the failed import leaves nothing (the 12 images before it included)
    with pytest.raises(RosbagError, match=rf"run: {COMPRESSED}: the image at {bad} ns is corrupt"):
        run(tmp_path / "run", tmp_path / "strict", topic=COMPRESSED, strict=True)
    assert not (tmp_path / "strict").exists() and leftovers(tmp_path / "strict") == []
    assert cli(tmp_path / "run", tmp_path / "strict", COMPRESSED, "--strict") == 2
    assert not (tmp_path / "strict").exists() and leftovers(tmp_path / "strict") == []
    assert cli(tmp_path / "run", tmp_path / "strict", COMPRESSED) == 0  # the re-run needs no --overwrite


def test_overwrite_replaces_the_sequence_whole_and_keeps_the_other_files(tmp_path):
    camera_bag(tmp_path / "run", frames=6)
    out = tmp_path / "rig"
    run(tmp_path / "run", out)
    run(tmp_path / "run", out, sequence="seq1", overwrite=True)  # a second sequence beside the first
    (out / "seq0" / "images" / "cam" / f"{T0 + 1}.png").write_bytes(b"stale")
    (out / "masks").mkdir()
    (out / "masks" / "cam.png").write_bytes(b"mine")
    with pytest.raises(FileExistsError, match="rig.yaml exists"):
        run(tmp_path / "run", out)
    run(tmp_path / "run", out, overwrite=True)
    assert not (out / "seq0" / "images" / "cam" / f"{T0 + 1}.png").exists()
    assert (out / "masks" / "cam.png").read_bytes() == b"mine" and (out / "seq1" / "poses.txt").is_file()
    assert len(RigLayout(out).frames("seq0", "cam")) == 6 and leftovers(out) == []


# 5. An uncalibrated CameraInfo, and errors that name the bag ------------------------------------------


def test_camera_info_with_k_all_zero_names_the_topic_and_the_bag(tmp_path):
    from fisheyedepth.data.rosbag import RosbagError

    bag = camera_bag(tmp_path / "run")
    bag.messages = [m for m in bag.messages if m[0] != INFO]
    bag.info(k=[0.0] * 9)
    bag.write(tmp_path / "zero")
    with pytest.raises(
        RosbagError, match=rf"^{re.escape(str(tmp_path / 'zero'))}: {INFO}: the CameraInfo's K is all zeros"
    ):
        run(tmp_path / "zero", tmp_path / "rig")
    bag = camera_bag(tmp_path / "run2")
    bag.image(T0 + 150 * MS, grey(0), encoding="yuv422")
    bag.write(tmp_path / "yuv")
    with pytest.raises(
        RosbagError, match=rf"^{re.escape(str(tmp_path / 'yuv'))}: {IMAGE}: image encoding 'yuv422'"
    ):
        run(tmp_path / "yuv", tmp_path / "rig")
    assert not (tmp_path / "rig").exists()


# 6. Quaternions in w,x,y,z order ----------------------------------------------------------------------


def write_poses(path, trans, quats) -> None:
    t0 = 10**18
    rows = [
        f"{t0 + i * 10**8} " + " ".join(map(str, [*t, *q]))
        for i, (t, q) in enumerate(zip(trans, quats, strict=True))
    ]
    path.write_text("# timestamp_ns tx ty tz qx qy qz qw\n" + "\n".join(rows) + "\n")


@pytest.mark.parametrize("order", ["xyzw", "wxyz"])
def test_a_pose_file_in_wxyz_order_warns_once_naming_the_file(tmp_path, caplog, order):
    """A half circle of radius 2 m, the body's x axis along the motion. Read in the wrong order the body
    moves sideways, up and back by turns; in the right order always forward."""
    t0 = 10**18
    path = write_tiny_rig(tmp_path, [t0, t0 + 10**8], [0.0, 0.1], [t0 + k * 10**8 for k in range(40)])
    rig = yaml.safe_load((tmp_path / "rig.yaml").read_text())
    rig["cameras"].append({**rig["cameras"][0], "name": "cam2"})  # two cameras, one pose file
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    shutil.copytree(tmp_path / "drive" / "images" / "cam", tmp_path / "drive" / "images" / "cam2")
    yaw = np.linspace(0, math.pi, 40)
    trans = np.stack([2 * np.sin(yaw), 2 * (1 - np.cos(yaw)), 0 * yaw], axis=1)
    quats = np.stack([0 * yaw, 0 * yaw, np.sin(yaw / 2), np.cos(yaw / 2)], axis=1)
    write_poses(path, trans, quats if order == "xyzw" else quats[:, [3, 0, 1, 2]])
    with caplog.at_level(logging.WARNING):
        layout = RigLayout(tmp_path)
        assert [len(layout.frames("drive", name)) for name in ("cam", "cam2")] == [40, 40]
    warnings = [r.getMessage() for r in caplog.records if "w,x,y,z" in r.getMessage()]
    if order == "xyzw":
        assert warnings == []
    else:
        assert len(warnings) == 1 and warnings[0].startswith(f"{path}: the body's direction of motion")
        assert warnings[0].endswith("quaternions in w,x,y,z order? The file's order is x,y,z,w")


def test_an_identity_written_wxyz_warns_and_a_straight_drive_does_not(tmp_path, caplog):
    """(1, 0, 0, 0) in x,y,z,w is a 180-degree roll; on every row it is an identity in the wrong order.
    A car whose body is a few tenths of a degree off that roll (z down, the synthetic world's) is quiet."""
    t0 = 10**18
    path = write_tiny_rig(tmp_path, [t0, t0 + 10**8], [0.0, 0.1], [t0 + k * 10**8 for k in range(10)])
    trans = np.stack([np.arange(10) * 0.5, np.zeros(10), np.zeros(10)], axis=1)
    write_poses(path, trans, [[1.0, 0.0, 0.0, 0.0]] * 10)
    with caplog.at_level(logging.WARNING):
        RigLayout(tmp_path).frames("drive", "cam")
    assert f"{path}: every rotation is a 180-degree roll about x" in caplog.text
    caplog.clear()
    write_poses(path, trans, [[-1.0, 0.0, 0.002 * (k % 3), 0.0026] for k in range(10)])
    with caplog.at_level(logging.WARNING):
        RigLayout(tmp_path).frames("drive", "cam")
    assert "w,x,y,z" not in caplog.text
