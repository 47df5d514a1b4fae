"""DDAD scenes (TRI's dgp scene format) into the rig layout (``fisheyedepth.data.ddad``,
``fisheyedepth-import-ddad``): a small scene written here, checked to the millimetre, its bad variants
refused by file and field; then the real ``ddad_scene01`` of ../shared/realdata (or
FISHEYEDEPTH_REALDATA), skipped when absent, through the multi-view command and train.py."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from fisheyedepth.cameras import PinholeCamera, RayCache
from fisheyedepth.cli import import_ddad
from fisheyedepth.data import ddad
from fisheyedepth.data.layouts import RigLayout

from conftest import realdata_dir

ROOT = Path(__file__).resolve().parents[1]
W, H = 64, 48
INTRINSICS = {
    "CAMERA_01": {"fx": 60.0, "fy": 58.0, "cx": 31.5, "cy": 23.25, "skew": 0.0},
    "CAMERA_05": {"fx": 45.0, "fy": 46.0, "cx": 32.0, "cy": 24.0, "skew": 0.0},
}
CAM_AXES = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # camera x right, y down, z forward
ORIGIN = "2463-05-15T00:38:58.203752Z"  # DDAD's clock: 1.5569e19 ns, beyond int64
ORIGIN_NS = 15569195938203752 * 1000
CAMERA_DELAY_NS = 50_000_000  # the cameras of a sample 50 ms after its sweep
WALL = 8.0  # metres along CAMERA_01's optical axis


def pose(R: np.ndarray, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def yaw(degrees: float) -> np.ndarray:
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


EXTRINSICS = {  # sensor -> vehicle
    "LIDAR": np.eye(4),
    "CAMERA_01": pose(CAM_AXES, [1.6, 0.25, 1.35]),
    "CAMERA_05": pose(yaw(35) @ CAM_AXES, [1.6, 0.4, 1.36]),
}


def vehicle(stamp_ns: int) -> np.ndarray:
    """The vehicle -> world pose at ``stamp_ns`` (since the origin): 10 m/s along a heading turning
    10 degrees a second."""
    s = stamp_ns * 1e-9
    return pose(yaw(30 + 10 * s), [400 + 10 * s * math.cos(math.radians(30)), -260 + 8 * s, 12.5])


def ddad_pose(T: np.ndarray, scale: float = 1.0) -> dict:
    x, y, z, w = Rotation.from_matrix(T[:3, :3]).as_quat() * scale
    return {
        "rotation": {"qw": w, "qx": x, "qy": y, "qz": z},
        "translation": dict(zip("xyz", T[:3, 3].tolist(), strict=True)),
    }


def iso(stamp_ns: int) -> str:
    us = (ORIGIN_NS + stamp_ns) // 1000
    seconds, micro = divmod(us, 10**6)
    days, rest = divmod(seconds, 86400)
    import datetime

    date = datetime.date.fromordinal(datetime.date(1970, 1, 1).toordinal() + days)
    return f"{date.isoformat()}T{rest // 3600:02d}:{rest // 60 % 60:02d}:{rest % 60:02d}.{micro:06d}Z"


def ray(camera: str, u: float, v: float) -> np.ndarray:
    k = INTRINSICS[camera]
    return np.array([(u - k["cx"]) / k["fx"], (v - k["cy"]) / k["fy"], 1.0])


GRID = [(u, v) for v in range(4, H, 8) for u in range(4, W, 8)]  # CAMERA_01's pixels on the wall
NEAR_SAME_PIXEL = (12, 12)  # a point 3 m away on the ray of a wall pixel: the nearest wins
NEAR_BESIDE = (30, 20)  # a point 3 m away 2 px right of the wall pixel (28, 20): hides it
BEHIND = (16, 16)  # a point 5 m behind CAMERA_01 on the ray of this off-grid pixel: dropped


def points_in_camera_01() -> np.ndarray:
    """The sweep's points in CAMERA_01's frame at its image's time (x, y, z)."""
    wall = [ray("CAMERA_01", u, v) * WALL for u, v in GRID]
    near = [ray("CAMERA_01", *NEAR_SAME_PIXEL) * 3, ray("CAMERA_01", *NEAR_BESIDE) * 3]
    return np.array([*wall, *near, ray("CAMERA_01", *BEHIND) * -5])


def write_scene(folder: Path, samples: int = 3, edit=None) -> Path:
    """A DDAD scene of ``samples`` samples, 100 ms apart: a sweep each (the wall and the three points
    above, in the LiDAR's frame at the sweep's time), and each camera 50 ms later. ``edit(scene,
    calibration)`` changes the JSON before it is written."""
    rng = np.random.default_rng(0)
    data, sample_list = [], []
    key = iter(f"{i:040x}" for i in range(1, 1000))
    for s in range(samples):
        t_lidar = s * 100_000_000
        t_camera = t_lidar + CAMERA_DELAY_NS
        T_world_lidar = vehicle(t_lidar) @ EXTRINSICS["LIDAR"]
        T_world_cam1 = vehicle(t_camera) @ EXTRINSICS["CAMERA_01"]
        X = points_in_camera_01()
        P = (np.linalg.inv(T_world_lidar) @ T_world_cam1 @ np.c_[X, np.ones(len(X))].T).T[:, :3]
        sweep = f"point_cloud/LIDAR/{(ORIGIN_NS + t_lidar) // 1000}.npz"
        (folder / sweep).parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(folder / sweep, data=np.c_[P, rng.uniform(0, 1, len(P))])
        keys = [next(key)]
        data.append({
            "datum": {"point_cloud": {"filename": sweep, "pose": ddad_pose(T_world_lidar),
                                      "point_format": ["X", "Y", "Z", "INTENSITY"], "annotations": {}}},
            "id": {"name": "LIDAR", "timestamp": iso(t_lidar), "index": "0", "log": ""}, "key": keys[0],
        })  # fmt: skip
        for camera in INTRINSICS:
            image = f"rgb/{camera}/{(ORIGIN_NS + t_camera) // 1000}.jpg"
            (folder / image).parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(folder / image), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
            keys.append(next(key))
            T = vehicle(t_camera) @ EXTRINSICS[camera]
            data.append({
                "datum": {"image": {"filename": image, "pose": ddad_pose(T), "width": W, "height": H,
                                    "channels": 3, "annotations": {}}},
                "id": {"name": camera, "timestamp": iso(t_camera), "index": "0", "log": ""}, "key": keys[-1],
            })  # fmt: skip
        sample_list.append({"calibration_key": "c" * 40, "datum_keys": keys,
                            "id": {"timestamp": iso(t_lidar), "index": "0", "log": ""}})  # fmt: skip
    scene = {"data": data, "samples": sample_list, "description": "written by tests/test_ddad.py"}
    calibration = {
        "names": ["LIDAR", *INTRINSICS],
        "intrinsics": [{"fx": 0.0, "fy": 0.0, "cx": 0.0, "cy": 0.0, "skew": 0.0}, *INTRINSICS.values()],
        "extrinsics": [ddad_pose(EXTRINSICS[n]) for n in ["LIDAR", *INTRINSICS]],
    }
    calibration = json.loads(json.dumps(calibration))  # an edit changes this scene only
    if edit is not None:
        edit(scene, calibration)
    (folder / "calibration").mkdir(parents=True, exist_ok=True)
    (folder / "calibration" / f"{'c' * 40}.json").write_text(json.dumps(calibration))
    (folder / f"scene_{'a' * 40}.json").write_text(json.dumps(scene))
    return folder


def expected_distance(camera: str, stamp: int) -> np.ndarray:
    """What the camera's ground truth must be, computed here with numpy: each point into the camera by
    the datums' poses, onto the nearest pixel, the nearest point of a pixel, then a point 10 % behind the
    nearest within 3 px dropped (a 7 x 7 minimum filter)."""
    X = points_in_camera_01()
    T = np.linalg.inv(vehicle(stamp) @ EXTRINSICS[camera]) @ vehicle(stamp) @ EXTRINSICS["CAMERA_01"]
    P = X @ T[:3, :3].T + T[:3, 3]
    k = INTRINSICS[camera]
    d = np.zeros((H, W))
    for x, y, z in P:
        if z <= 0:
            continue
        u, v = round(k["fx"] * x / z + k["cx"]), round(k["fy"] * y / z + k["cy"])
        r = math.sqrt(x * x + y * y + z * z)
        if 0 <= u < W and 0 <= v < H and (d[v, u] == 0 or r < d[v, u]):
            d[v, u] = r
    near = cv2.erode(np.where(d > 0, d, np.inf).astype(np.float32), np.ones((7, 7), np.uint8))
    with np.errstate(over="ignore"):  # inf (no point nearby) times 1.1
        d[(d > 0) & (d > 1.1 * near)] = 0
    return d


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    folder = write_scene(tmp_path_factory.mktemp("ddad") / "scene")
    out = folder.parent / "rig"
    return folder, out, ddad.ddad_to_rig(folder, out)


# ------------------------------------------------------------------ a scene written here
def test_the_import_keeps_intrinsics_extrinsics_poses_and_timestamps(synthetic):
    folder, out, summary = synthetic
    assert summary["cameras"] == ["CAMERA_01", "CAMERA_05"] and summary["samples"] == 3
    assert summary["images"] == {"CAMERA_01": 3, "CAMERA_05": 3} and summary["poses"] == 6
    assert summary["time_origin"] == ORIGIN and summary["lidar"] == "LIDAR"
    layout = RigLayout(out)
    stamps = [s * 100_000_000 + CAMERA_DELAY_NS for s in range(3)]  # ns since the origin
    for name, k in INTRINSICS.items():
        spec = layout.cameras[name]
        assert spec.camera == PinholeCamera(width=W, height=H, fx=k["fx"], fy=k["fy"], cx=k["cx"], cy=k["cy"])
        assert np.allclose(spec.cam_to_body, EXTRINSICS[name], atol=1e-12)
        frames = layout.frames("seq0", name)
        assert [f.key for f in frames] == stamps
        for frame in frames:  # the vehicle where the scene put it, at the image's own time
            assert np.allclose(frame.pose, vehicle(frame.key), atol=1e-9)
            jpg = cv2.imread(str(folder / f"rgb/{name}/{(ORIGIN_NS + frame.key) // 1000}.jpg"))
            assert np.array_equal(
                cv2.imread(str(layout.image("seq0", name, frame))), jpg
            )  # decoded, lossless
    rows = np.loadtxt(out / "seq0" / "poses.txt")
    assert rows[:, 0].astype(np.int64).tolist() == sorted([*stamps, *(s - CAMERA_DELAY_NS for s in stamps)])
    for row in rows:
        T = vehicle(int(row[0]))
        assert np.allclose(row[1:4], T[:3, 3], atol=1e-9)
        assert np.allclose(Rotation.from_quat(row[4:]).as_matrix(), T[:3, :3], atol=1e-12)
    assert (out / "rig.yaml").read_text().count(ORIGIN) == 1


def test_the_lidar_lands_as_distance_along_each_pixels_ray(synthetic):
    """CAMERA_01: the wall 8 m ahead at 8 |ray| / ray_z on its grid pixels, to the millimetre; the nearer
    point of a shared pixel wins; a point 2 px beside a wall pixel and 3 m away hides it; a point behind
    the camera is dropped. CAMERA_05 (another camera, 35 degrees round) sees what numpy computes."""
    _, out, summary = synthetic
    layout = RigLayout(out)
    for frame in layout.frames("seq0", "CAMERA_01"):
        d = np.load(layout.distance("seq0", "CAMERA_01", frame))
        assert d.dtype == np.float32 and d.shape == (H, W)
        for u, v in GRID:
            r = ray("CAMERA_01", u, v)
            if (u, v) == NEAR_SAME_PIXEL:
                assert d[v, u] == pytest.approx(3 * np.linalg.norm(r), abs=1e-3)
            elif (u, v) == (NEAR_BESIDE[0] - 2, NEAR_BESIDE[1]):
                assert d[v, u] == 0
            else:
                assert d[v, u] == pytest.approx(WALL * np.linalg.norm(r), abs=1e-3), (u, v)
        assert d[NEAR_BESIDE[1], NEAR_BESIDE[0]] == pytest.approx(
            3 * np.linalg.norm(ray("CAMERA_01", *NEAR_BESIDE))
        )
        assert d[BEHIND[1], BEHIND[0]] == 0 and (d > 0).sum() == len(GRID)  # 48 - 1 hidden + 1 beside
        assert np.abs(d - expected_distance("CAMERA_01", frame.key)).max() < 1e-3
    assert summary["lidar_pixels"]["CAMERA_01"] == [48, 48, 48]
    for frame in layout.frames("seq0", "CAMERA_05"):
        d = np.load(layout.distance("seq0", "CAMERA_05", frame))
        want = expected_distance("CAMERA_05", frame.key)
        assert (want > 0).sum() >= 10 and np.array_equal(d > 0, want > 0)
        assert np.abs(d - want).max() < 1e-3
    # every stored distance is a point's: distance times the pixel's ray lies on the wall (z = 8 m in
    # CAMERA_01) or is one of the two near points (z = 3 m), within the half pixel (diagonal) the rounding
    # moves it across the ray
    spec, frame = layout.cameras["CAMERA_05"], layout.frames("seq0", "CAMERA_05")[1]
    rays, _ = RayCache().get(spec.camera, dtype=torch.float64)
    d = torch.from_numpy(np.load(layout.distance("seq0", "CAMERA_05", frame))).double()
    X = (rays * d[..., None])[d > 0].numpy()
    T = np.linalg.inv(EXTRINSICS["CAMERA_01"]) @ EXTRINSICS["CAMERA_05"]  # one instant: one vehicle pose
    z = (X @ T[:3, :3].T + T[:3, 3])[:, 2]
    off = np.minimum(np.abs(z - WALL), np.abs(z - 3))
    assert np.all(off < np.linalg.norm(X, axis=1) * math.atan(math.sqrt(0.5) / 45)), off.max()


def test_a_body_mask_keeps_the_ground_truth_off_the_body(tmp_path, synthetic):
    folder, _, _ = synthetic
    mask = np.full((H, W), 255, np.uint8)
    mask[24:, :] = 0  # the lower half: the hood
    cv2.imwrite(str(tmp_path / "hood.png"), mask)
    out = tmp_path / "rig"
    hood = f"CAMERA_01={tmp_path / 'hood.png'}"
    assert import_ddad.main(["--src", str(folder), "--out", str(out), "--mask", hood]) == 0
    layout = RigLayout(out)
    assert layout.cameras["CAMERA_01"].mask == out / "masks" / "CAMERA_01.png"
    assert layout.cameras["CAMERA_05"].mask is None
    frame = layout.frames("seq0", "CAMERA_01")[0]
    d = np.load(layout.distance("seq0", "CAMERA_01", frame))
    assert (d[24:] == 0).all() and (d[:24] > 0).sum() == sum(v < 24 for _, v in GRID)  # 24 of 48
    assert np.array_equal(cv2.imread(str(out / "masks" / "CAMERA_01.png"), cv2.IMREAD_GRAYSCALE), mask)


def test_an_existing_rig_is_kept_without_overwrite_and_replaced_whole_with_it(tmp_path, synthetic, capsys):
    folder, _, _ = synthetic
    out = tmp_path / "rig"
    args = ["--src", str(folder), "--out", str(out)]
    assert import_ddad.main(args) == 0
    stale = out / "seq0" / "images" / "CAMERA_01" / "7.png"
    stale.write_bytes(b"an image of an earlier import")
    capsys.readouterr()
    assert import_ddad.main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {out / 'rig.yaml'} exists; pass overwrite=True (--overwrite) to replace it"]
    assert stale.is_file()
    assert import_ddad.main([*args, "--overwrite"]) == 0
    assert not stale.exists() and len(RigLayout(out).frames("seq0", "CAMERA_01")) == 3
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no staging folder left


def refused(tmp_path, capsys, edit, match: str, **kw) -> str:
    """The scene edited by ``edit``: ``fisheyedepth-import-ddad`` exits 2 with one ``error:`` line that
    matches ``match``, and writes nothing."""
    folder = write_scene(tmp_path / "scene", edit=edit, **kw)
    out = tmp_path / "rig"
    capsys.readouterr()
    assert import_ddad.main(["--src", str(folder), "--out", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line and not line.startswith("ddad -> ")]
    assert len(err) == 1 and err[0].startswith("error: "), err  # beside the progress bar, one line
    assert re.search(match, err[0]), err[0]
    assert not out.exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    return err[0]


def test_a_missing_key_is_named_by_file_and_field(tmp_path, capsys):
    def edit(scene, calibration):
        del scene["data"][2]["datum"]["image"]["pose"]["rotation"]["qw"]

    refused(
        tmp_path, capsys, edit, r"scene_a+\.json: key 'data\[2\]\.datum\.image\.pose\.rotation\.qw': missing$"
    )


def test_a_quaternion_of_norm_2_is_refused(tmp_path, capsys):
    def edit(scene, calibration):
        calibration["extrinsics"][2] = ddad_pose(EXTRINSICS["CAMERA_05"], scale=2.0)

    line = refused(
        tmp_path, capsys, edit, r"c{40}\.json: key 'extrinsics\[2\]\.rotation': quaternion of norm 2;"
    )
    assert "norm within 0.001 of 1" in line

    def edit_pose(scene, calibration):
        q = scene["data"][0]["datum"]["point_cloud"]["pose"]["rotation"]
        q.update({k: v * 2 for k, v in q.items()})

    refused(
        tmp_path / "2", capsys, edit_pose,
        r"scene_a+\.json: key 'data\[0\]\.datum\.point_cloud\.pose\.rotation': quaternion of norm 2;",
    )  # fmt: skip


def test_names_and_intrinsics_of_different_counts_are_refused(tmp_path, capsys):
    def edit(scene, calibration):
        calibration["intrinsics"].pop()

    refused(
        tmp_path, capsys, edit, r"c{40}\.json: key 'intrinsics': 2 entries, but 'names' has 3: one per name$"
    )

    def unnamed(scene, calibration):
        calibration["names"][2] = "CAMERA_09"

    refused(tmp_path / "2", capsys, unnamed,
            r"key 'data\[2\]\.id\.name': 'CAMERA_05' has no calibration in c{40}\.json")  # fmt: skip


def test_a_calibration_that_does_not_fit_the_poses_is_refused(tmp_path, capsys):
    """CAMERA_05's extrinsic turned by 1 degree: its datums and CAMERA_01's, at one timestamp, place the
    vehicle 1 degree apart."""

    def edit(scene, calibration):
        calibration["extrinsics"][2] = ddad_pose(pose(yaw(1), [0, 0, 0]) @ EXTRINSICS["CAMERA_05"])

    line = refused(
        tmp_path, capsys, edit, r"share the timestamp 2463-05-15T00:38:58\.253752Z but place the vehicle"
    )
    assert " 1 degrees apart" in line and "the calibration does not fit the scene's poses" in line


def test_skew_and_an_image_of_another_size_are_refused(tmp_path, capsys):
    def edit(scene, calibration):
        calibration["intrinsics"][1]["skew"] = 0.5

    refused(tmp_path, capsys, edit, r"key 'intrinsics\[1\]\.skew': 0\.5; the pinhole model has no skew$")

    def size(scene, calibration):
        for entry in scene["data"]:
            if "image" in entry["datum"]:
                entry["datum"]["image"]["width"] = 80

    refused(tmp_path / "2", capsys, size, r"\.jpg: image is 64x48, scene_a+\.json data\[1\] says 80x48$")


def test_a_mask_of_another_size_and_an_unknown_camera_are_refused(tmp_path, synthetic, capsys):
    folder, _, _ = synthetic
    cv2.imwrite(str(tmp_path / "small.png"), np.full((24, 32), 255, np.uint8))
    out = tmp_path / "rig"
    for mask, message in (
        (
            f"CAMERA_05={tmp_path / 'small.png'}",
            "small.png: body mask of 32x24 pixels, but camera CAMERA_05 is 64x48",
        ),
        (f"CAMERA_07={tmp_path / 'small.png'}", "--mask: ['CAMERA_07'] are not cameras of the import"),
        ("CAMERA_05", "--mask: expected CAMERA=FILE, got 'CAMERA_05'"),
    ):
        capsys.readouterr()
        assert import_ddad.main(["--src", str(folder), "--out", str(out), "--mask", mask]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], err
        assert not out.exists()


def test_the_real_frames_read_a_ddad_scene_as_the_import_does(tmp_path):
    """``realworld.frames.load_frames(root, ["ddad"])``: each camera of the first sample, its LiDAR
    ground truth what numpy computes, scored as a LiDAR frame; without the folder, one missing frame
    named by it."""
    from fisheyedepth.realworld import frames as rf
    from fisheyedepth.realworld import scores as rs

    assert rf.load_frames(tmp_path, ["ddad"]) == [rf.Missing("ddad", tmp_path / "ddad_scene01")]
    write_scene(tmp_path / "ddad_scene01")
    frames = rf.load_frames(tmp_path, ["ddad"])
    assert [f.name for f in frames] == ["ddad_CAMERA_01", "ddad_CAMERA_05"]
    for frame in frames:
        camera = frame.name.removeprefix("ddad_")
        want = expected_distance(camera, CAMERA_DELAY_NS)
        assert np.abs(frame.distance.numpy() - want).max() < 1e-3 and frame.source == "lidar"
        assert frame.image.shape == (1, 3, H, W) and bool(frame.mask.all())
        assert [p.name for p in frame.files[2:]] == [
            f"{(ORIGIN_NS + CAMERA_DELAY_NS) // 1000}.jpg",
            f"{ORIGIN_NS // 1000}.npz",
        ]
    constant = rs.constant_map(frames[0])
    scored = frames[0].distance[frames[0].distance > 0].double().numpy()  # under 80 m, none hidden again
    assert constant["pixels"] == len(GRID) and constant["distance"] == pytest.approx(np.median(scored))


# ------------------------------------------------------------------ the real DDAD scene
@pytest.fixture(scope="module")
def real(tmp_path_factory):
    src = realdata_dir() / "ddad_scene01"
    if not src.is_dir():
        pytest.skip(f"real data not found at {src} (set FISHEYEDEPTH_REALDATA)")
    out = tmp_path_factory.mktemp("ddad_real") / "rig"
    return src, out, ddad.ddad_to_rig(src, out)


@pytest.mark.realdata
def test_the_real_scene_imports_with_its_lidar_in_every_camera(real):
    """Three cameras, three samples, the sweep in each image: 4.7-4.8 k pixels with ground truth in the
    front camera (fx 2168, a narrow view), 9.1-9.9 k in the side ones (fx 1060); the ground 1.2-1.5 m
    below the cameras, level with the vehicle frame within 3 degrees (a wrong quaternion order or
    direction would tilt it)."""
    from test_real_recordings import fit_plane_ransac

    src, out, summary = real
    assert summary["cameras"] == ["CAMERA_01", "CAMERA_05", "CAMERA_06"]
    assert summary["images"] == dict.fromkeys(summary["cameras"], 3) and summary["poses"] == 6
    pixels = summary["lidar_pixels"]
    assert all(4000 < n < 6000 for n in pixels["CAMERA_01"]), pixels
    assert all(8000 < n < 12000 for n in pixels["CAMERA_05"] + pixels["CAMERA_06"]), pixels
    layout = RigLayout(out)
    for name in ("CAMERA_01", "CAMERA_05"):
        spec = layout.cameras[name]
        frame = layout.frames("seq0", name)[0]
        d = torch.from_numpy(np.load(layout.distance("seq0", name, frame))).double()
        rays, _ = RayCache().get(spec.camera, dtype=torch.float64)
        X = (rays * d[..., None])[d > 0]
        V = X @ torch.from_numpy(spec.cam_to_body[:3, :3]).T + torch.from_numpy(spec.cam_to_body[:3, 3])
        n, offset, inliers = fit_plane_ransac(V)
        if n[2] < 0:
            n, offset = -n, -offset
        height = float(n @ torch.from_numpy(spec.cam_to_body[:3, 3]) + offset)
        assert math.degrees(math.acos(float(n[2]))) < 3 and 1.2 < height < 1.5, (name, n, height)
        assert float(inliers.double().mean()) > 0.15
        assert 3 < float(d[d > 0].min()) and float(d.max()) < 250  # DDAD's LiDAR reaches 250 m


@pytest.mark.realdata
def test_the_multiview_command_scores_the_real_scene_against_its_lidar(real, tmp_path):
    """``fisheyedepth-multiview --sources rig`` on the imported scene's first instant: its three cameras
    matched with each other, each scored against the imported LiDAR where a partner matched it."""
    from fisheyedepth.cli.multiview import main

    _, root, _ = real
    out = tmp_path / "multiview"
    code = main([str(root), "--out", str(out), "--sources", "rig", "--max-images", "3", "--quiet"])
    assert code == 0
    summary = json.loads((out / "summary.json").read_text())
    images = {record["image"]: record for record in summary["images"]}
    assert sorted(images) == [f"seq0/{c}/211478000" for c in ("CAMERA_01", "CAMERA_05", "CAMERA_06")]
    assert all("checked" in record for record in images.values())  # the folder has ground truth
    scored = [r for r in images.values() if r["checked"]["pixels"] > 0]
    assert scored, images
    for record in scored:
        checked = record["checked"]
        assert 0 < checked["abs_rel"] < 2 and 0 <= checked["a1"] <= 1 and checked["constant_abs_rel"] > 0
    assert len(list((out / "seq0" / "distance").rglob("*.npy"))) == 3


@pytest.mark.realdata
def test_train_py_loads_and_trains_a_step_on_the_real_scene(real, tmp_path, caplog):
    """``train.py data=rig data.datamodule.root=<imported>``: three samples a camera, so sources at -1 and
    +1; the car stands still (1e-6 m between samples), so min_translation=0 keeps the middle sample of
    each camera: 3 samples, one step."""
    import logging

    from hydra import compose, initialize_config_dir

    from fisheyedepth.cli.train import train

    _, root, _ = real
    overrides = [
        "data=rig", f"data.datamodule.root={root}", "data.datamodule.min_translation=0",
        "model.objective.source_offsets=[-1,1]", "data.datamodule.size=[96,64]",
        "data.datamodule.num_workers=0", "data.datamodule.batch_size=3", "data.datamodule.pin_memory=false",
        "trainer.fast_dev_run=true",
        "model.compile_kernels=false", "logger=none", "callbacks.progress=null", f"paths.data_dir={tmp_path}",
        f"paths.output_dir={tmp_path / 'run'}",
    ]  # fmt: skip
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("train", overrides)
    caplog.set_level(logging.INFO)
    train(cfg)
    assert "3 samples kept" in caplog.text
    assert "`Trainer.fit` stopped: `max_steps=1` reached" in caplog.text


@pytest.mark.realdata
def test_the_real_frames_score_ddad_beside_the_constant_map(real):
    """``realworld.frames.load_frames(root, ["ddad"])`` (``make realscore``): each camera of the first sample
    with the same ground truth the import wrote, scored by the LiDAR protocol beside its constant map."""
    from fisheyedepth.realworld import frames as rf
    from fisheyedepth.realworld import scores as rs

    src, out, _ = real
    frames = rf.load_frames(src.parent, ["ddad"])
    assert [f.name for f in frames] == ["ddad_CAMERA_01", "ddad_CAMERA_05", "ddad_CAMERA_06"]
    layout = RigLayout(out)
    for frame in frames:
        camera = frame.name.removeprefix("ddad_")
        first = layout.frames("seq0", camera)[0]
        assert np.array_equal(frame.distance.numpy(), np.load(layout.distance("seq0", camera, first)))
        assert frame.source == "lidar" and frame.image.shape == (1, 3, 1216, 1936)
        constant = rs.constant_map(frame)
        assert 4000 < constant["pixels"] < 12000 and 5 < constant["distance"] < 30
        assert 0.2 < constant["none"]["abs_rel"] < 1.0, (frame.name, constant)
