"""Scores on real photographs (``fisheyedepth.realworld.frames``, ``fisheyedepth.realworld.scores``,
``scripts/tools/real_world.py``): the real frames of ../shared/realdata (or FISHEYEDEPTH_REALDATA), skipped
when absent."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from fisheyedepth.cameras import CalibrationError
from fisheyedepth.data.kitti360 import OCCLUSION
from fisheyedepth.evaluation import PROTOCOLS, Evaluator
from fisheyedepth.images import read_image
from fisheyedepth.realworld import frames as rf
from fisheyedepth.realworld import scores as rs

from conftest import bare_module, load_script, realdata_dir

cv2 = pytest.importorskip("cv2")
ROOT = Path(__file__).resolve().parents[1]
FRAME_NAMES = [
    "kitti360", "scannetpp", "adt_left_0", "adt_left_1", "adt_right_0", "adt_right_1",
    "ddad_CAMERA_01", "ddad_CAMERA_05", "ddad_CAMERA_06",
]  # fmt: skip


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """The unprojection of a frame is many small element-wise kernels: on two cores shared with other
    work, one thread is several times faster than two."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def root() -> Path:
    path = realdata_dir()
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set FISHEYEDEPTH_REALDATA)")
    return path


@pytest.fixture(scope="module")
def frames(root) -> dict[str, rf.RealFrame]:
    loaded = rf.load_frames(root)
    assert [f.name for f in loaded] == FRAME_NAMES
    assert all(isinstance(f, rf.RealFrame) for f in loaded), [f for f in loaded if isinstance(f, rf.Missing)]
    return {f.name: f for f in loaded}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A randomly initialised full model at 64x64, saved as a checkpoint."""

    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1), "base_focal": 20.0}, input_size=(64, 64))
    path = tmp_path_factory.mktemp("realworld") / "tiny.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, path)
    return path


def cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def numbers(cell: str) -> list[float]:
    return [float(x) for x in re.findall(r"\d+\.\d+", cell)]


# ------------------------------------------------------------------ ground truth
@pytest.mark.realdata
def test_scannetpp_z_depth_becomes_distance_along_opencvs_ray(root, frames):
    """ScanNet++: distance = z |ray| / ray_z with the ray from ``cv2.fisheye.undistortPoints`` (which
    returns (x, y) on the plane z = 1), at pixels spread over the image; never below z anywhere."""
    folder = root / "scannetpp_frame"
    calib = json.loads((folder / "calibration.json").read_text())
    z = cv2.imread(str(folder / "depth_z_mm.png"), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000
    frame = frames["scannetpp"]
    distance = frame.distance.double().numpy()
    v, u = np.meshgrid(np.linspace(40, 1120, 9).round(), np.linspace(40, 1700, 11).round(), indexing="ij")
    u, v = u.ravel().astype(int), v.ravel().astype(int)
    pick = z[v, u] > 0
    u, v = u[pick], v[pick]
    assert len(u) > 60
    K = np.array([[calib["fx"], 0, calib["cx"]], [0, calib["fy"], calib["cy"]], [0, 0, 1]])
    D = np.array([calib[k] for k in ("k1", "k2", "k3", "k4")])
    xy = cv2.fisheye.undistortPoints(np.stack((u, v), -1)[None].astype(np.float64), K, D)[0]
    expected = z[v, u] * np.sqrt((xy**2).sum(-1) + 1)  # |(x, y, 1)| / 1
    assert np.allclose(distance[v, u], expected, rtol=2e-5), np.abs(distance[v, u] / expected - 1).max()
    assert expected.max() / z[v, u][expected.argmax()] > 1.5  # the periphery: far from z there
    known = z > 0
    assert (distance[known] >= z[known] * (1 - 1e-6)).all() and (distance[~known] == 0).all()
    assert 0.9 < (distance > 0).mean() <= known.mean()


@pytest.mark.realdata
def test_adt_z_depth_becomes_distance_whose_point_projects_back_to_its_pixel(frames):
    """Aria Digital Twin (Fisheye624): the point ``distance * ray`` has the file's z and projects
    (the model's forward map, not its Newton inverse) to the pixel it came from."""
    for name in ("adt_left_0", "adt_right_1"):
        frame = frames[name]
        z = cv2.imread(str(frame.files[2]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 1000
        rays = rf.RAYS.get(frame.camera)[0].double()  # the rays the distance was made with
        d = frame.distance.double()
        has = d > 0
        assert 0.9 < float(has.double().mean()) and bool(
            (d[has] >= torch.from_numpy(z)[has] * (1 - 1e-6)).all()
        )
        points = rays * d[..., None]
        assert torch.allclose(points[..., 2][has], torch.from_numpy(z)[has], rtol=1e-6)
        rows, cols = torch.nonzero(has, as_tuple=True)
        some = torch.arange(0, len(rows), 997)
        uv, ok = frame.camera.project(points[rows[some], cols[some]])
        assert bool(ok.all())
        pixel = torch.stack((cols[some], rows[some]), -1).double()
        assert float((uv - pixel).abs().max()) < 1e-3


def lidar_scored_by_numpy(frame: rf.RealFrame) -> np.ndarray:
    """The full protocol's pixels of a LiDAR frame (KITTI-360, DDAD): body mask, a ray, a return below
    80 m and not 10 % behind the nearest return within 3 pixels (a 7x7 minimum filter by OpenCV's
    erosion)."""
    d = frame.distance.numpy()
    near = cv2.erode(np.where(d > 0, d, np.inf).astype(np.float32), np.ones((7, 7), np.uint8))
    with np.errstate(over="ignore"):  # inf (no return nearby) times 1.1
        hidden = (d > 0) & (d > np.float32(1 + OCCLUSION) * near)
    valid = rf.RAYS.get(frame.camera)[1].numpy()
    return frame.mask.numpy() & valid & (d > 1e-3) & (d < 80) & ~hidden


@pytest.mark.realdata
def test_the_constant_map_scores_what_numpy_computes(frames):
    """Every pixel at the median of the scored ground truth: abs_rel, a1 and rmse as numpy computes
    them on the pixels each frame scores (found here without the library for every frame)."""
    for name, frame in frames.items():
        d = frame.distance.double().numpy()
        if frame.source == "lidar":
            scored = lidar_scored_by_numpy(frame)
        else:
            valid = rf.RAYS.get(frame.camera)[1].numpy()
            assert rs.protocols(frame)[0].cap[1] == np.floor(d[valid].max()) + 1
            scored = valid & (d > 1e-3) & (d < rs.protocols(frame)[0].cap[1])
        g = d[scored]
        median = np.median(g)
        constant = rs.constant_map(frame)
        assert constant["pixels"] == scored.sum() and constant["distance"] == pytest.approx(median, rel=1e-12)
        m = np.float64(np.float32(median))  # the map is float32, as every prediction
        ratio = np.maximum(g / m, m / g)
        assert constant["none"]["abs_rel"] == pytest.approx(np.mean(np.abs(g - m) / g), rel=1e-9), name
        assert constant["none"]["a1"] == pytest.approx(np.mean(ratio < 1.25), rel=1e-6), name  # float32
        assert constant["none"]["rmse"] == pytest.approx(np.sqrt(np.mean((g - m) ** 2)), rel=1e-9), name
        assert 0.05 < constant["none"]["abs_rel"] < 2 and 0 < constant["none"]["a1"] < 1


# ------------------------------------------------------------------ the KITTI-360 frame as before
def old_kitti360_score(runtime, folder: Path) -> dict:
    """What ``scripts/real_frame.py`` computed: the frame read as it read it, both protocols scored by
    one Evaluator each on the LiDAR points inside the body mask."""
    from fisheyedepth.cameras import load_camera

    camera = load_camera(folder / "image_02.yaml")
    bgr = read_image(folder / "image_02_rgb.png").bgr
    image = torch.from_numpy(np.ascontiguousarray(bgr[..., ::-1])).permute(2, 0, 1).float()[None] / 255.0
    mask = cv2.cvtColor(read_image(folder / "image_02_body_mask.png").bgr, cv2.COLOR_BGR2GRAY) > 127
    lidar = cv2.imread(str(folder / "image_02_lidar_distance.png"), cv2.IMREAD_UNCHANGED)
    lidar = torch.from_numpy(lidar.astype(np.float32) / 256.0)
    pred = runtime.distance(image, [camera]).float()[0, 0]
    results = {}
    for name in ("full", "kitti360"):
        evaluator = Evaluator(PROTOCOLS[name], ("none", "median"), rays=rf.RAYS)  # the rays, cached
        evaluator.update(pred, lidar.to(pred), torch.from_numpy(mask), camera, source="lidar")
        results[name] = evaluator.compute()
    return results


@pytest.mark.realdata
def test_kitti360_scores_what_real_frame_scored(root, frames, tiny):
    runtime = load_script("tools/real_world").load_model(tiny)
    new, pred = rs.score(runtime, frames["kitti360"])
    assert pred.shape == (1400, 1400)
    old = old_kitti360_score(runtime, root / "kitti360_frame")
    for protocol in ("full", "kitti360"):
        for scaling in ("none", "median"):
            assert new[protocol][scaling] == old[protocol][scaling], (protocol, scaling)


class ScaledLidar:
    """A runtime: the frame's LiDAR times ``factor`` where it has a return, 10 m elsewhere."""

    def __init__(self, lidar: torch.Tensor, factor: float):
        self.lidar, self.factor = lidar, factor

    def distance(self, images, cameras):
        assert images.shape[-2:] == self.lidar.shape and len(cameras) == 1
        d = torch.where(self.lidar > 0, self.lidar * self.factor, torch.full_like(self.lidar, 10.0))
        return d[None, None]


@pytest.mark.realdata
def test_kitti360_scores_the_lidar_points_as_they_are(frames):
    """A prediction equal to the scan scores 0; half of it abs_rel 0.5 unscaled, a1 0, and 0 after
    median scaling with the ratio 2, under both protocols."""
    frame = frames["kitti360"]
    assert (
        frame.image.shape == (1, 3, 1400, 1400)
        and 0 <= float(frame.image.min()) < float(frame.image.max()) <= 1
    )
    assert 0.02 < float((frame.distance > 0).float().mean()) < 0.03  # the README's 2.6 % of pixels
    exact, _ = rs.score(ScaledLidar(frame.distance, 1.0), frame)
    half, _ = rs.score(ScaledLidar(frame.distance, 0.5), frame)
    for protocol in ("full", "kitti360"):
        assert exact[protocol]["none"]["abs_rel"] == pytest.approx(0.0, abs=1e-7)
        assert exact[protocol]["none"]["a1"] == 1.0 and exact[protocol]["none"]["images"] == 1
        assert half[protocol]["none"]["abs_rel"] == pytest.approx(0.5, abs=1e-6)
        assert half[protocol]["none"]["a1"] == 0.0
        assert half[protocol]["median"]["scale_ratio"] == pytest.approx(2.0, rel=1e-6)
        assert half[protocol]["median"]["abs_rel"] == pytest.approx(0.0, abs=1e-6)


# ------------------------------------------------------------------ the command
@pytest.mark.realdata
def test_the_command_scores_a_checkpoint_on_every_frame(root, frames, tiny, tmp_path, capsys):
    script = load_script("tools/real_world")
    pictures, out = tmp_path / "pictures", tmp_path / "scores.json"
    args = [str(tiny), "--root", str(root), "--pictures", str(pictures), "--json", str(out), "--no-multiview"]
    assert script.main(args) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [cells(line) for line in lines if line.startswith(f"| {tiny.stem} |")]
    assert [r[1] for r in rows] == FRAME_NAMES
    record = json.loads(out.read_text())
    assert list(record["frames"]) == FRAME_NAMES and list(record["models"]) == [tiny.stem]
    scores = record["models"][tiny.stem]["frames"]
    assert list(scores) == FRAME_NAMES and set(scores["kitti360"]) == {"full", "kitti360"}
    for r in rows:
        frame = frames[r[1]]
        constant = record["frames"][r[1]]["constant_map"]
        result = scores[r[1]][rs.protocols(frame)[0].name]
        assert r[2] == f"{constant['pixels']:,}" and r[3] == f"{rs.protocols(frame)[0].cap[1]:g} m"
        assert numbers(r[4]) == [
            round(result["none"][k], n) for k, n in (("abs_rel", 3), ("a1", 3), ("rmse", 2))
        ]
        assert numbers(r[6])[:3] == [
            round(constant["none"][k], n) for k, n in (("abs_rel", 3), ("a1", 3), ("rmse", 2))
        ]
        assert result["none"]["abs_rel"] > 0 and 0 <= result["median"]["a1"] <= 1
        picture = cv2.imread(str(pictures / f"{tiny.stem}_{r[1]}.png"))
        H, W = frame.distance.shape
        assert picture.shape == (round(H * 350 / W), 4 * 350, 3)  # input | prediction | truth | error
    assert sorted(p.name for p in pictures.iterdir()) == sorted(f"{tiny.stem}_{n}.png" for n in FRAME_NAMES)
    assert "| Depth Any Camera | 0.149 | 0.822 |" in lines
    # nothing is replaced without --force, and nothing is scored before that is known
    assert script.main(args) == 2
    assert "scores.json exists; pass --force" in capsys.readouterr().err


@pytest.mark.realdata
def test_a_missing_frame_is_named_with_its_path(root, tiny, tmp_path, capsys):
    """No ScanNet++ folder and one ADT depth map fewer: both named in the table and the record, the
    other frames scored, exit status 1."""
    (tmp_path / "adt_slam").mkdir()
    for path in (root / "adt_slam").iterdir():
        if not path.name.startswith("depthskel_camera-slam-left_1_"):
            (tmp_path / "adt_slam" / path.name).symlink_to(path)
    out = tmp_path / "scores.json"
    args = [str(tiny), "--root", str(tmp_path), "--frames", "scannetpp", "adt", "--json", str(out),
            "--no-multiview"]  # fmt: skip
    assert load_script("tools/real_world").main(args) == 1
    captured = capsys.readouterr()
    rows = {r[1]: r for r in map(cells, captured.out.splitlines()) if r[0] == tiny.stem}
    assert list(rows) == ["scannetpp", "adt_left_0", "adt_left_1", "adt_right_0", "adt_right_1"]
    assert rows["scannetpp"][2] == f"missing: {tmp_path / 'scannetpp_frame'}"
    assert rows["adt_left_1"][2] == f"missing: {tmp_path / 'adt_slam' / 'depthskel_camera-slam-left_1_*.png'}"
    assert numbers(rows["adt_right_1"][4])  # scored
    assert "missing: scannetpp, adt_left_1" in captured.err
    record = json.loads(out.read_text())
    assert record["frames"]["scannetpp"] == {"missing": str(tmp_path / "scannetpp_frame")}
    assert record["models"][tiny.stem]["frames"]["adt_left_1"] == record["frames"]["adt_left_1"]


def test_the_command_needs_a_real_data_folder(tmp_path, monkeypatch, capsys):
    """Without ``--root`` and without FISHEYEDEPTH_REALDATA: one ``error: --root:`` line naming both,
    exit status 2, nothing read."""
    monkeypatch.delenv("FISHEYEDEPTH_REALDATA", raising=False)
    assert load_script("tools/real_world").main([str(tmp_path / "model.ckpt"), "--no-multiview"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --root: ") and "FISHEYEDEPTH_REALDATA" in err[0]


@pytest.mark.realdata
def test_malformed_files_are_named_with_the_field(root, tmp_path):
    for name in ("kitti360_frame", "scannetpp_frame", "adt_slam"):
        (tmp_path / name).mkdir()
        for path in (root / name).iterdir():
            (tmp_path / name / path.name).symlink_to(path)

    def replace(path: Path, write) -> None:
        path.unlink()
        write(path)

    calib = json.loads((root / "scannetpp_frame" / "calibration.json").read_text())
    calibration = tmp_path / "scannetpp_frame" / "calibration.json"
    replace(calibration, lambda p: p.write_text(json.dumps({k: v for k, v in calib.items() if k != "k3"})))
    with pytest.raises(CalibrationError, match=r"calibration.json: key 'k3': missing"):
        rf.load_frames(tmp_path, ["scannetpp"])
    calibration.write_text(json.dumps(calib | {"fy": "791"}))
    with pytest.raises(CalibrationError, match=r"calibration.json: key 'fy': expected a number, got '791'"):
        rf.load_frames(tmp_path, ["scannetpp"])
    calibration.write_text(json.dumps(calib))
    replace(
        tmp_path / "scannetpp_frame" / "depth_z_mm.png",
        lambda p: cv2.imwrite(str(p), np.zeros((1168, 1752), np.uint8)),
    )
    with pytest.raises(ValueError, match=r"depth_z_mm.png: expected a one-channel uint16 PNG \(millimetres"):
        rf.load_frames(tmp_path, ["scannetpp"])

    meta = json.loads((root / "adt_slam" / "adt_sample.json").read_text())
    meta["cameras"]["camera-slam-right"]["projection_params"] = meta["cameras"]["camera-slam-right"][
        "projection_params"
    ][:14]
    replace(tmp_path / "adt_slam" / "adt_sample.json", lambda p: p.write_text(json.dumps(meta)))
    with pytest.raises(
        CalibrationError,
        match=r"adt_sample.json: key 'cameras.camera-slam-right.projection_params': expected a list of 15 "
        r"numbers, got 14",
    ):
        rf.load_frames(tmp_path, ["adt"])

    replace(
        tmp_path / "kitti360_frame" / "image_02_body_mask.png",
        lambda p: cv2.imwrite(str(p), np.full((700, 700), 255, np.uint8)),
    )
    with pytest.raises(ValueError, match=r"body_mask.png: 700x700, but image_02.yaml says 1400x1400"):
        rf.load_frames(tmp_path, ["kitti360"])


# ------------------------------------------------------------------ the published anchors
def test_the_readme_prints_the_anchors_the_command_prints():
    """docs/real-data.md, "Real photographs": the published anchors, as the command prints them."""
    readme = (ROOT / "docs" / "real-data.md").read_text()
    section = readme.split("## Real photographs", 1)[1].split("\n## ", 1)[0]
    assert "\n".join(load_script("tools/real_world").anchors_table()) in section
    assert "python scripts/tools/real_world.py" in section and "constant map" in section
    assert "real_frame" not in readme


def test_model_names_are_short_and_unique():
    names = load_script("tools/real_world").model_names(
        [
            "a/tiny.onnx",
            "b/tiny.ckpt",
            "c/tiny.ckpt",
            "r/checkpoints/last.ckpt",
            "r/checkpoints/best-000.ckpt",
        ]
    )
    assert names == ["tiny", "tiny_ckpt", "tiny_ckpt_2", "r", "r_best-000"]
