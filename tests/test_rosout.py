"""Distance written back for a robot's tools (fisheyedepth.rosout): ROS 2 messages, bags and MCAP files read
back with ``rosbags`` and with the ``mcap`` reader; camera models as CameraInfo and back; the multi-view
command's ``--bag-out``."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import (
    DoubleSphereCamera,
    Fisheye624Camera,
    KannalaBrandtCamera,
    OpenCVCamera,
    PinholeCamera,
)
from fisheyedepth.geometry.se3 import (
    axis_angle_to_matrix,
    make_pose,
    matrix_to_quaternion,
    quaternion_to_matrix,
)
from stereo_world import ROOM, pose, render, texture_volume

from conftest import kitti02

pytest.importorskip("rosbags")
from fisheyedepth.data.rosbag import camera_from_info  # noqa: E402
from fisheyedepth.rosout import BagRecorder, BagWriter, check_bag_out  # noqa: E402
from fisheyedepth.rosout import messages as m  # noqa: E402

T0 = 1_700_000_000_123_456_789


def test_quaternions_of_any_rotation_turn_back_into_it():
    """Shepperd's method at every angle, half turns about each axis included (where a trace-only formula
    divides by zero)."""
    g = torch.Generator().manual_seed(0)
    axes = [torch.randn(3, generator=g, dtype=torch.float64) for _ in range(40)]
    angles = [float(a) for a in torch.rand(40, generator=g, dtype=torch.float64) * math.pi]
    cases = [a / a.norm() * angle for a, angle in zip(axes, angles, strict=True)]
    cases += [torch.tensor(v, dtype=torch.float64) * math.pi for v in np.eye(3)]  # half turns
    cases += [torch.zeros(3, dtype=torch.float64)]
    for axis_angle in cases:
        R = axis_angle_to_matrix(axis_angle).numpy()
        q = matrix_to_quaternion(R)
        assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0
        assert np.abs(quaternion_to_matrix(torch.from_numpy(q)).numpy() - R).max() < 1e-12


SMALL = {"width": 64, "height": 48, "fx": 50.0, "fy": 51.0, "cx": 31.5, "cy": 23.5}
CAMERAS = {
    "pinhole": (PinholeCamera(**SMALL), "plumb_bob"),
    "plumb_bob": (OpenCVCamera(**SMALL, k1=-0.1, k2=0.01, p1=0.001, p2=-0.002, k3=0.001), "plumb_bob"),
    "rational": (
        OpenCVCamera(**SMALL, k1=-0.1, k2=0.01, k3=0.001, k4=0.02, k5=0.001, k6=0.0001),
        "rational_polynomial",
    ),
    "kannala_brandt": (
        KannalaBrandtCamera(
            width=64, height=64, fx=20.0, fy=20.5, cx=31.2, cy=32.1, k1=0.01, k2=-0.003, k3=0.0005, k4=-0.0001
        ),
        "equidistant",
    ),  # fmt: skip
    "mei": (kitti02().resize(64, 64), "fisheyedepth/mei"),
    "double_sphere": (
        DoubleSphereCamera(width=64, height=64, fx=18.0, fy=18.2, cx=31.7, cy=32.2, xi=-0.2, alpha=0.59),
        "fisheyedepth/double_sphere",
    ),  # fmt: skip
    "fisheye624": (
        Fisheye624Camera(
            width=64, height=64, fx=20.0, fy=20.0, cx=32.0, cy=31.0, k0=0.4, k1=-0.5, k2=0.1, p0=1e-4, s0=2e-4
        ),
        "fisheyedepth/fisheye624",
    ),  # fmt: skip
}


@pytest.mark.parametrize("case", sorted(CAMERAS))
def test_every_camera_model_is_a_camera_info_and_comes_back(case):
    """ROS's own distortion models where ROS has one, the project's model named ``fisheyedepth/<model>``
    otherwise; what the bag importer reads back is the same camera, parameter for parameter."""
    camera, model = CAMERAS[case]
    store = m.typestore()
    info = m.camera_info(store, camera, T0, "cam")
    assert info.distortion_model == model and (info.width, info.height) == (camera.width, camera.height)
    assert info.header.stamp.sec * 10**9 + info.header.stamp.nanosec == T0 and info.header.frame_id == "cam"
    assert np.array_equal(info.r, np.eye(3).ravel()) and info.p[[0, 5, 10]].tolist() == [
        *camera.paraxial_focal(),
        1,
    ]
    decoded = store.deserialize_cdr(store.serialize_cdr(info, info.__msgtype__), info.__msgtype__)
    back = camera_from_info(decoded, "/cam/camera_info")
    if case == "pinhole":  # plumb_bob without distortion reads as the pinhole it is
        assert back == camera
        return
    assert type(back) is type(camera) and back.to_dict().keys() == camera.to_dict().keys()
    for key, value in camera.to_dict().items():
        assert back.to_dict()[key] == (
            value if isinstance(value, str) else pytest.approx(value, abs=1e-12)
        ), key


def test_topics_follow_the_image_topic():
    assert m.topics("/front/image_raw", "front")["distance"] == "/front/distance"
    assert m.topics("/rig/left/image_raw/compressed", "left")["camera_info"] == "/rig/left/camera_info"
    assert m.topics(None, "cam_2")["points"] == "/cam_2/points"
    assert m.topics("image_raw", "solo")["confidence"] == "/solo/confidence"  # no namespace: the camera's


def room_views(size: int = 48):
    """Two cameras on a body inside the tests' room, the body at a known pose: their images and exact
    distance maps, and the transforms."""
    camera = kitti02().resize(size, size)
    rig = {"left": pose(-30.0, (-0.2, 0.0, 0.0)).numpy(), "right": pose(40.0, (0.2, 0.1, 0.0)).numpy()}
    body = make_pose(axis_angle_to_matrix(torch.tensor([0.0, 0.3, 0.1], dtype=torch.float64)),
                     torch.tensor([0.5, 0.2, -0.4], dtype=torch.float64)).numpy()  # fmt: skip
    views = {}
    for name, E in rig.items():
        image, distance = render(camera, torch.from_numpy(body @ E), texture_volume(0))
        grey = (image[0, 0].numpy() * 255).round().astype(np.uint8)
        views[name] = (np.repeat(grey[..., None], 3, 2), distance[0].numpy())
    return camera, rig, body, views


def on_a_wall(points_world: np.ndarray) -> np.ndarray:
    """Each point's distance (metres) to the nearest of the room's six walls."""
    bounds = ROOM.numpy()
    gaps = np.abs(points_world[:, :, None] - bounds.T[None])  # [N, 3, 2]
    return gaps.reshape(len(points_world), -1).min(1)


def read_back(path):
    """Every message of a bag or an MCAP file, as ``{topic: [(stamp, msgtype, message)]}``, through
    ``rosbags``' reader."""
    from rosbags.highlevel import AnyReader

    store = m.typestore()
    found: dict[str, list] = {}
    with AnyReader([path], default_typestore=store) as reader:
        for connection, stamp, raw in reader.messages():
            found.setdefault(connection.topic, []).append(
                (stamp, connection.msgtype, reader.deserialize(raw, connection.msgtype))
            )
    return found


def pose_of(tf_message) -> tuple[np.ndarray, str, str]:
    (t,) = tf_message.transforms
    q, p = t.transform.rotation, t.transform.translation
    R = quaternion_to_matrix(torch.tensor([q.x, q.y, q.z, q.w], dtype=torch.float64)).numpy()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [p.x, p.y, p.z]
    return T, t.header.frame_id, t.child_frame_id


@pytest.mark.parametrize("kind", ["mcap", "folder"])
def test_a_room_written_as_a_bag_reads_back_on_its_walls(tmp_path, kind):
    """Distance and confidence images (32FC1, the stamp, the camera's frame), camera infos, the kept
    points in the body frame, the rig on /tf_static and the body on /tf: read back, the points carried into
    the world by the transforms from the bag itself lie on the room's walls within a centimetre."""
    camera, rig, body, views = room_views()
    path = tmp_path / ("room.mcap" if kind == "mcap" else "room_bag")
    confidence = {name: np.where(d > 0, 0.25 + 0.5 * (d > 3), 0).astype(np.float32) for name, (_, d) in
                  views.items()}  # fmt: skip
    with BagWriter(path) as writer:
        recorder = BagRecorder(writer, {n: camera for n in rig}, rig, {"left": "/rig/left/image_raw"},
                               {"left": "cam_left"})  # fmt: skip
        for i, (name, (image, distance)) in enumerate(views.items()):
            kept = distance.copy()
            kept[:, : 8 * (i + 1)] = 0  # a strip of "nothing kept": 0 in the image, no point in the cloud
            recorder.add(name, T0, image, kept, confidence[name], body)
    assert path.is_file() if kind == "mcap" else (path / "metadata.yaml").is_file()
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # nothing left beside it
    found = read_back(path)
    assert set(found) == {"/tf_static", "/tf", "/rig/left/distance", "/rig/left/confidence",
                          "/rig/left/camera_info", "/rig/left/points", "/right/distance", "/right/confidence",
                          "/right/camera_info", "/right/points"}  # fmt: skip
    assert {stamp for messages in found.values() for stamp, _, _ in messages} == {T0}
    static = {t.child_frame_id: t for t in found["/tf_static"][0][2].transforms}
    assert set(static) == {"cam_left", "right"} and {t.header.frame_id for t in static.values()} == {
        "base_link"
    }
    T_world_body, parent, child = pose_of(found["/tf"][0][2])
    assert (parent, child) == ("odom", "base_link") and np.abs(T_world_body - body).max() < 1e-9
    for i, (name, (_, distance)) in enumerate(views.items()):
        ns, frame = ("/rig/left", "cam_left") if name == "left" else ("/right", "right")
        (_, msgtype, image), = found[f"{ns}/distance"]  # fmt: skip
        assert msgtype == "sensor_msgs/msg/Image" and image.encoding == "32FC1" and image.is_bigendian == 0
        assert image.header.frame_id == frame and image.step == 4 * image.width
        values = np.frombuffer(image.data.tobytes(), "<f4").reshape(image.height, image.width)
        strip = 8 * (i + 1)
        assert (values[:, :strip] == 0).all() and np.array_equal(values[:, strip:], distance[:, strip:])
        (_, _, sure), = found[f"{ns}/confidence"]  # fmt: skip
        sure = np.frombuffer(sure.data.tobytes(), "<f4").reshape(values.shape)
        assert ((sure > 0) == (values > 0)).all() and set(np.unique(sure)) <= {0.0, 0.25, 0.75}
        (_, _, info), = found[f"{ns}/camera_info"]  # fmt: skip
        assert info.distortion_model == "fisheyedepth/mei" and info.header.frame_id == frame
        (_, _, cloud), = found[f"{ns}/points"]  # fmt: skip
        assert cloud.header.frame_id == "base_link" and [f.name for f in cloud.fields] == list(m.POINT_FIELDS)
        table = np.frombuffer(cloud.data.tobytes(), "<f4").reshape(cloud.width, len(m.POINT_FIELDS))
        assert cloud.width == (values > 0).sum() > 500 and cloud.is_dense
        body_frame = table[:, :3].astype(np.float64)
        world = body_frame @ T_world_body[:3, :3].T + T_world_body[:3, 3]
        assert on_a_wall(world).max() < 0.01  # float32 points of the exact distance: on the walls
        packed = table[:, 4].view("<u4")
        assert ((packed >> 16) == (packed & 0xFF)).all()  # grey images: r = b for every point
        assert set(np.unique(table[:, 3])) <= {0.25, 0.75}


def test_an_mcap_file_reads_in_the_mcap_library(tmp_path):
    """The file as Foxglove opens it: ROS 2 message schemas, CDR, one channel a topic, every message."""
    mcap_reader = pytest.importorskip("mcap.reader")
    camera, rig, body, views = room_views(32)
    path = tmp_path / "run.mcap"
    with BagWriter(path) as writer:
        recorder = BagRecorder(writer, {n: camera for n in rig}, rig)
        for name, (image, distance) in views.items():
            recorder.add(name, T0, image, distance, (distance > 0).astype(np.float32), body)
    with path.open("rb") as f:
        reader = mcap_reader.make_reader(f)
        seen = [(schema.name, schema.encoding, channel.topic, channel.message_encoding, message.log_time)
                for schema, channel, message in reader.iter_messages()]  # fmt: skip
    assert len(seen) == writer.count == 2 + 2 * 4
    assert (
        {s[1] for s in seen} == {"ros2msg"}
        and {s[3] for s in seen} == {"cdr"}
        and {s[4] for s in seen} == {T0}
    )
    schemas = {topic: schema for schema, _, topic, _, _ in seen}
    assert (
        schemas["/left/points"] == "sensor_msgs/msg/PointCloud2"
        and schemas["/tf"] == "tf2_msgs/msg/TFMessage"
    )
    assert schemas["/right/distance"] == "sensor_msgs/msg/Image"


def test_a_bag_is_never_overwritten_without_asking_and_a_failure_leaves_nothing(tmp_path):
    camera, rig, body, views = room_views(32)
    path = tmp_path / "run.mcap"
    path.write_bytes(b"an earlier bag")
    with pytest.raises(FileExistsError, match="run.mcap exists; pass --overwrite"):
        BagWriter(path)
    (tmp_path / "folder.mcap").mkdir()
    with pytest.raises(FileExistsError, match="folder.mcap exists and is not an MCAP file"):
        check_bag_out(tmp_path / "folder.mcap", overwrite=True)
    (tmp_path / "notabag").mkdir()
    with pytest.raises(FileExistsError, match="notabag exists and is not a ROS 2 bag folder"):
        check_bag_out(tmp_path / "notabag", overwrite=True)
    with pytest.raises(RuntimeError, match="stopped"), BagWriter(path, overwrite=True) as writer:
        BagRecorder(writer, {n: camera for n in rig}, rig).add(
            "left", T0, *views["left"], views["left"][1], body
        )
        raise RuntimeError("stopped")
    assert path.read_bytes() == b"an earlier bag"  # the failed run replaced nothing
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.mcap", "notabag", "run.mcap"]
    with BagWriter(path, overwrite=True) as writer:
        BagRecorder(writer, {n: camera for n in rig}, rig).add(
            "left", T0, *views["left"], views["left"][1], None
        )
    assert set(read_back(path)) == {"/tf_static", "/left/distance", "/left/confidence", "/left/camera_info",
                                    "/left/points"}  # no odometry given: no /tf  # fmt: skip
    bag = tmp_path / "bag"
    for _ in range(2):  # a bag folder replaced by a bag folder
        with BagWriter(bag, overwrite=True) as writer:
            BagRecorder(writer, {"left": camera}, rig).add("left", T0, *views["left"], views["left"][1], body)
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]
    with pytest.raises(ValueError, match="--bag-out: .*cannot write there"):
        check_bag_out(tmp_path / "run.mcap" / "inside.mcap", overwrite=False)


def test_the_multiview_command_writes_its_outputs_as_a_bag(tmp_path, capsys):
    """``fisheyedepth-multiview --bag-out``: every matched image's distance equal to its .npy, stamped with
    the image's timestamp; the body's pose from the odometry on /tf; refused before any work where the
    bag exists, and inside the recording."""
    from fisheyedepth.cli.multiview import main

    from test_multiview import write_room_rig

    rig = write_room_rig(tmp_path / "rec", size=192)
    out, bag = tmp_path / "out", tmp_path / "run.mcap"
    args = [str(tmp_path / "rec"), "--out", str(out), "--min-distance", "0.5", "--max-distance", "20",
            "--threads", "1", "--quiet", "--bag-out", str(bag)]  # fmt: skip
    assert main(args) == 0
    summary = json.loads((out / "summary.json").read_text())
    found = read_back(bag)
    images = [r["image"] for r in summary["images"]]
    assert summary["bag_out"] == {"path": str(bag), "messages": sum(len(v) for v in found.values())}
    for camera in ("left", "right"):
        stamps = [int(name.split("/")[-1]) for name in images if name.split("/")[1] == camera]
        messages = found[f"/{camera}/distance"]
        assert [s for s, _, _ in messages] == sorted(stamps) == list(rig["stamps"])
        for stamp, _, image in messages:
            values = np.frombuffer(image.data.tobytes(), "<f4").reshape(image.height, image.width)
            assert np.array_equal(values, np.load(out / "seq" / "distance" / camera / f"{stamp}.npy"))
    poses = [pose_of(msg)[0] for _, _, msg in found["/tf"]]
    assert [round(float(T[2, 3]), 9) for T in poses] == [0.0, 0.15, 0.3]  # the odometry: 0.15 m a frame
    assert main([*args, "--overwrite"]) == 0  # replaced with --overwrite
    assert main([*args[:2], str(tmp_path / "out2"), *args[3:]]) == 2  # the bag exists: refused at once
    assert (
        capsys.readouterr().err.strip().endswith(f"--bag-out: {bag} exists; pass --overwrite to replace it")
    )
    assert not (tmp_path / "out2").exists()
    inside = [*args[:-1], str(tmp_path / "rec" / "out.mcap")]
    assert main([*inside[:2], str(tmp_path / "out3"), *inside[3:]]) == 2
    assert "--bag-out" in capsys.readouterr().err and not (tmp_path / "rec" / "out.mcap").exists()


def test_a_foxglove_client_on_localhost_receives_images_and_points():
    """The live server (foxglove-sdk's WebSocket protocol) advertises each camera's topics; a client on
    127.0.0.1 that subscribes receives the distance image and the point cloud, their bytes as logged."""
    import asyncio
    import struct
    import threading

    aiohttp = pytest.importorskip("aiohttp")
    pytest.importorskip("foxglove")
    from fisheyedepth.rosout.foxglove import FoxgloveLive

    camera, rig, body, views = room_views(32)
    image, distance = views["left"]
    subscribed = threading.Event()
    done = threading.Event()

    async def client(port: int) -> dict:
        received: dict[str, bytes] = {}
        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(f"ws://127.0.0.1:{port}", protocols=["foxglove.sdk.v1"]) as ws:
                channels = {}
                while not {"/left/distance", "/left/points"} <= set(received):
                    message = await ws.receive(timeout=20)
                    if message.type == aiohttp.WSMsgType.TEXT:
                        data = json.loads(message.data)
                        if data["op"] == "advertise":
                            channels.update({c["id"]: c for c in data["channels"]})
                            wanted = [{"id": i, "channelId": i} for i in channels]
                            await ws.send_str(json.dumps({"op": "subscribe", "subscriptions": wanted}))
                            subscribed.set()
                    elif message.type == aiohttp.WSMsgType.BINARY:
                        opcode, subscription, _ = struct.unpack_from("<BIQ", message.data)
                        assert opcode == 1  # message data
                        received[channels[subscription]["topic"]] = message.data[13:]
                    else:
                        raise AssertionError(f"the server closed the connection: {message}")
        return {"received": received, "schemas": {c["topic"]: c["schemaName"] for c in channels.values()}}

    with FoxgloveLive({"left": camera}, {"left": rig["left"]}, port=0) as live:
        assert live.port > 0

        def produce():  # until the client has both (a client sees only what is logged after it subscribes)
            subscribed.wait(20)
            while not done.is_set():
                live.add("left", T0, image, distance, (distance > 0).astype(np.float32), body)
                done.wait(0.05)

        thread = threading.Thread(target=produce, daemon=True)
        thread.start()
        try:
            found = asyncio.run(client(live.port))
        finally:
            done.set()
            thread.join(10)
    assert found["schemas"]["/left/distance"] == "foxglove.RawImage"
    assert found["schemas"]["/left/points"] == "foxglove.PointCloud"
    assert {"/left/image", "/left/confidence", "/left/camera_info", "/tf"} <= set(found["schemas"])
    assert distance.astype("<f4").tobytes() in found["received"]["/left/distance"]  # the metres, as logged
    rows, cols = np.nonzero(distance > 0)
    assert len(found["received"]["/left/points"]) > 20 * len(rows)  # 20 bytes a kept pixel, and the fields


def test_the_live_rig_serves_foxglove_and_writes_a_bag_of_its_instants(tmp_path, capsys):
    pytest.importorskip("foxglove")
    from conftest import load_script
    from test_multiview import write_room_rig

    rig = write_room_rig(tmp_path / "rec", size=128, half_baseline=0.3)
    live_rig = load_script("tools/live_rig")
    bag = tmp_path / "live.mcap"
    args = [str(tmp_path / "rec"), "--no-record", "--min-distance", "0.5", "--max-distance", "20",
            "--threads", "1", "--foxglove", "0", "--bag-out", str(bag), "--quiet"]  # fmt: skip
    assert live_rig.main(args) == 0
    assert "serving to Foxglove on ws://127.0.0.1:" in capsys.readouterr().err
    found = read_back(bag)
    for camera in ("left", "right"):
        assert [s for s, _, _ in found[f"/{camera}/distance"]] == list(rig["stamps"])
        assert sum(msg.width for _, _, msg in found[f"/{camera}/points"]) > 1000
    assert [round(float(pose_of(msg)[0][2, 3]), 9) for _, _, msg in found["/tf"]] == [0.0, 0.15, 0.3]
    assert live_rig.main(args) == 2  # the bag exists
    assert f"--bag-out: {bag} exists" in capsys.readouterr().err
    assert live_rig.main([*args[:-3], "--foxglove", "70000", "--quiet"]) == 2
    assert "--foxglove: port 70000" in capsys.readouterr().err


def test_predict_writes_its_frames_as_a_bag(kitti_data, checkpoint, tmp_path):
    """``predict.py bag_out=``: each frame's distance (0 where NaN: no ray) and its points, at the frame's
    time, the camera's calibration resized to the frame; no confidence topic (the network gives none);
    refused before any frame where the bag exists."""
    from fisheyedepth.cli.predict import predict
    from test_inference import frames_folder

    from conftest import load_cfg

    images = frames_folder(kitti_data, tmp_path / "in", corrupt=False)
    calib = kitti_data / "calibration" / "image_02.yaml"
    out, bag = tmp_path / "out", tmp_path / "frames.mcap"
    summary = predict(load_cfg("predict", ckpt_path=checkpoint, input=images, camera=calib, output=out,
                               bag_out=str(bag)))  # fmt: skip
    assert summary["bag_out"] == str(bag) and summary["frames"] == 3
    found = read_back(bag)
    assert set(found) == {"/tf_static", "/camera/distance", "/camera/camera_info", "/camera/points"}
    assert [s for s, _, _ in found["/camera/distance"]] == [0, 100_000_000, 200_000_000]
    first = np.load(out / f"{sorted(images.iterdir())[0].stem}_distance.npy")
    image, info, cloud = (found[f"/camera/{what}"][0][2] for what in ("distance", "camera_info", "points"))
    values = np.frombuffer(image.data.tobytes(), "<f4").reshape(image.height, image.width)
    assert np.array_equal(values, np.nan_to_num(first, nan=0.0).astype(np.float32))
    assert (info.width, info.height) == (
        image.width,
        image.height,
    ) and info.distortion_model == "fisheyedepth/mei"
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "rgb"] and cloud.width == int((values > 0).sum())
    with pytest.raises(FileExistsError, match="frames.mcap exists"):
        predict(load_cfg("predict", ckpt_path=checkpoint, input=images, camera=calib, output=tmp_path / "o2",
                         bag_out=str(bag)))  # fmt: skip
    assert not (tmp_path / "o2").exists() or not any((tmp_path / "o2").iterdir())
