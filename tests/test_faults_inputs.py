"""Faults of the inputs a user hands to the tools: each gets a clear error naming the file, or a count in the
summary, never a silent wrong answer, a silent loss, or an exhausted machine.

A still video taken for a body mask, two Aria frames with one capture time, Aria calibrations that the rig
layout would refuse once written (no pixel with a ray, a size of 512.7 pixels, a transform that is not
rigid, two poses at one time), a decompression bomb, a full disk while rendering, broken symbolic
links among the images to predict on, and an output folder that refuses writes.
"""

from __future__ import annotations

import errno
import json
import struct
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from fisheyedepth.cameras import CalibrationError, save_camera
from fisheyedepth.cli import run_command
from fisheyedepth.cli.estimate_mask import main as estimate_mask_main
from fisheyedepth.cli.import_aria import main as aria_main
from fisheyedepth.cli.predict import predict
from fisheyedepth.cli.synthetic import main as synthetic_main
from fisheyedepth.data.aria import CALIBRATION, POSES, aria_to_rig
from fisheyedepth.data.body_mask import estimate_body_mask
from fisheyedepth.images import MAX_PIXELS_VARIABLE, FrameSource, ImageError, read_image
from fisheyedepth.synthetic import WorldSpec, generate
from fisheyedepth.synthetic.folder import NoSpaceLeft

from conftest import aria_fisheye624, bare_module, kitti02
from test_faults_entrypoints import one_line_error, predict_cfg

SIZE = 64


def texture(seed: int, size: int = SIZE) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (size, size, 3), dtype=np.uint8)


# ------------------------------------------------------------------ a body mask from a still video
def still_rig(root: Path, frames: int = 20) -> Path:
    """A one-camera rig layout whose ``frames`` images are all the same picture, its body moving."""
    camera = kitti02().resize(SIZE, SIZE)
    images = root / "seq0" / "images" / "cam"
    images.mkdir(parents=True)
    for i in range(frames):
        cv2.imwrite(str(images / f"{1000 + i}.png"), texture(0))
    poses = [f"{1000 + i} {0.5 * i} 0 0 0 0 0 1" for i in range(frames)]
    (root / "seq0" / "poses.txt").write_text("\n".join(poses) + "\n")
    entry = {"name": "cam", "model": camera.to_dict(), "cam_to_body": np.eye(4).tolist()}
    (root / "rig.yaml").write_text(yaml.safe_dump({"cameras": [entry]}))
    return images


def test_a_body_mask_needs_frames_that_change(tmp_path, capsys):
    images = still_rig(tmp_path)
    args = ["--root", str(tmp_path), "--layout", "rig", "--sequence", "seq0", "--camera", "cam"]
    assert estimate_mask_main([*args, "--frames", "20"]) == 2
    out = capsys.readouterr().err.strip().replace("\r", "\n").splitlines()[-1:]  # after the progress bar
    assert out == [
        f"error: the 20 frames of camera 'cam' in {images} do not change over time (9 pixels in 10 vary "
        "by less than 1% of the mean brightness): a body mask needs a moving camera"
    ]
    assert not (tmp_path / "masks").exists()
    # one grey level of jitter (a re-encoded still) is no motion either; a changing world is
    camera, rng = kitti02().resize(SIZE, SIZE), np.random.default_rng(1)
    jitter = [np.clip(texture(0) + rng.integers(-1, 2, (SIZE, SIZE, 3)), 0, 255) for _ in range(20)]
    with pytest.raises(ValueError, match="^the 20 frames of the images do not change over time"):
        estimate_body_mask(jitter, camera, np.eye(4))
    mask = estimate_body_mask((texture(i) for i in range(20)), camera, np.eye(4), sky_elevation=90)
    assert mask.frames == 20


# ------------------------------------------------------------------ Aria exports
STAMPS = (7_385_791_599_584, 7_385_824_935_313, 7_385_858_266_822)


def aria_export(root: Path) -> Path:
    """A one-camera Aria export (module docstring of fisheyedepth.data.aria) of 64 x 64 images."""
    cam = aria_fisheye624().resize(SIZE, SIZE)
    params = [cam.fx, cam.cx, cam.cy, cam.k0, cam.k1, cam.k2, cam.k3, cam.k4, cam.k5]
    params += [cam.p0, cam.p1, cam.s0, cam.s1, cam.s2, cam.s3]
    entry = {
        "model": "FISHEYE624",
        "params": params,
        "size": [SIZE, SIZE],
        "T_device_camera": np.eye(4).tolist(),
    }
    calib = {"cam": entry}
    root.mkdir()
    (root / CALIBRATION).write_text(json.dumps(calib))
    (root / "cam").mkdir()
    for i, stamp in enumerate(STAMPS):
        cv2.imwrite(str(root / "cam" / f"{i:02d}_{stamp}.png"), texture(i))
    rows = ["tracking_timestamp_us,tx,ty,tz,qx,qy,qz,qw"]
    rows += [f"{t},{0.01 * i},0,0,0,0,0,1" for i, t in enumerate(range(7_385_790_000, 7_385_865_000, 5000))]
    (root / POSES).write_text("\n".join(rows) + "\n")
    return root


def edit_calibration(root: Path, key: str, value) -> None:
    calib = json.loads((root / CALIBRATION).read_text())
    if key == "f":
        calib["cam"]["params"][0] = value
    else:
        calib["cam"][key] = value
    (root / CALIBRATION).write_text(json.dumps(calib))


def test_an_aria_export_converts(tmp_path):
    src = aria_export(tmp_path / "src")
    summary = aria_to_rig(src, tmp_path / "rig")
    assert (
        summary["images"] == {"cam": 3} and summary["outside_poses"] == {"cam": 0} and summary["poses"] == 15
    )
    assert sorted(p.name for p in (tmp_path / "rig" / "seq0" / "images" / "cam").iterdir()) == [
        f"{t}.png" for t in STAMPS
    ]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig", "src"]  # no staging folder left


def test_an_aria_export_without_its_vio_poses_is_named(tmp_path, capsys):
    src = aria_export(tmp_path / "src")
    (src / POSES).unlink()
    assert aria_main(["--src", str(src), "--out", str(tmp_path / "rig")]) == 2
    assert (
        capsys.readouterr().err
        == f"error: {src / POSES}: Aria's VIO poses not found (the export's odometry)\n"
    )
    assert not (tmp_path / "rig").exists()


def test_aria_poses_of_another_unit_or_a_quaternion_not_of_norm_one_are_refused(tmp_path, capsys):
    """A VIO CSV in nanoseconds (no image within the poses' time range once read as microseconds) and a
    quaternion of norm 2 or 1e-6 are refused naming the file (and the line), and nothing is written."""
    from fisheyedepth.cli.import_aria import main

    src, out = aria_export(tmp_path / "src"), tmp_path / "rig"
    rows = (src / POSES).read_text().splitlines()
    in_ns = [rows[0], *(",".join([str(int(r.split(",")[0]) * 1000), *r.split(",")[1:]]) for r in rows[1:])]
    (src / POSES).write_text("\n".join(in_ns) + "\n")
    assert main(["--src", str(src), "--out", str(out)]) == 2
    assert f"error: {src / POSES}: no image lies within the poses' time range" in capsys.readouterr().err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["src"]
    for w in ("2", "1e-6"):
        (src / POSES).write_text(
            "\n".join([*rows[:3], rows[3].rsplit(",", 1)[0] + f",{w}", *rows[4:]]) + "\n"
        )
        assert main(["--src", str(src), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert (
            f"error: {src / POSES}:4: quaternion of norm {float(w):.6g}; a rotation is a unit quaternion"
            in err
        )
        assert not out.exists()


def test_two_aria_frames_with_one_capture_time_are_an_error(tmp_path, capsys):
    src = aria_export(tmp_path / "src")
    cv2.imwrite(str(src / "cam" / f"03_{STAMPS[1]}.png"), texture(9))
    out = tmp_path / "rig"
    with pytest.raises(ValueError) as info:
        aria_to_rig(src, out)
    assert str(info.value) == (
        f"{src / 'cam'}: 01_{STAMPS[1]}.png and 03_{STAMPS[1]}.png have one capture time, {STAMPS[1]} ns: "
        "one image would replace the other"
    )
    with pytest.raises(ValueError, match="one image would replace the other"):
        aria_to_rig(src, out, overwrite=True)  # where one image silently replaced the other
    assert not out.exists()
    from fisheyedepth.cli.import_aria import main

    assert main(["--src", str(src), "--out", str(out)]) == 2
    assert capsys.readouterr().err.strip() == f"error: {info.value}"


@pytest.mark.parametrize(
    "fault, message",
    [
        (("f", 1e-3), r"key 'cam': only 0\.0% of the 64x64 image has a ray"),
        (
            ("size", [64.7, 64]),
            r"key 'cam\.size': the width must be a positive whole number of pixels, got 64\.7",
        ),
        (
            ("size", [64, "64"]),
            r"key 'cam\.size': the height must be a positive whole number of pixels, got '64'",
        ),
        (
            ("T_device_camera", np.diag([2.0, 2, 2, 1]).tolist()),
            r"key 'cam\.T_device_camera': not a rigid transform",
        ),
    ],
    ids=["no-ray", "fractional-size", "size-as-text", "scaled-extrinsic"],
)
def test_an_aria_calibration_the_rig_layout_would_refuse_writes_nothing(tmp_path, fault, message):
    src = aria_export(tmp_path / "src")
    edit_calibration(src, *fault)
    with pytest.raises(CalibrationError, match=f"^{src / CALIBRATION}: {message}"):
        aria_to_rig(src, tmp_path / "rig")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src"]  # no rig, no staging folder


def test_aria_poses_and_images_the_rig_layout_would_refuse_write_nothing(tmp_path):
    src = aria_export(tmp_path / "src")
    with (src / POSES).open("a") as f:
        f.write("7385790000,9,9,9,0,0,0,1\n")  # the first row's time again
    with pytest.raises(
        ValueError, match=f"^{src / POSES}:17: timestamp 7385790000 us already has a pose on line 2"
    ):
        aria_to_rig(src, tmp_path / "rig")
    src = aria_export(tmp_path / "src2")
    small = src / "cam" / f"02_{STAMPS[2]}.png"
    cv2.imwrite(str(small), texture(2, 48))
    with pytest.raises(ImageError, match=f"^{small}: image is 48x48, camera cam of {CALIBRATION} is 64x64"):
        aria_to_rig(src, tmp_path / "rig")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["src", "src2"]


# ------------------------------------------------------------------ decompression bombs
def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_bomb(path: Path, side: int = 12000) -> Path:
    """A valid black ``side`` x ``side`` grey PNG, compressed row by row (bounded memory): 140 KB."""
    row, z = bytes(side + 1), zlib.compressobj(9)  # filter byte 0, then black pixels
    idat = b"".join(z.compress(row) for _ in range(side)) + z.flush()
    ihdr = struct.pack(">IIBBBBB", side, side, 8, 0, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", idat) + png_chunk(b"IEND", b"")
    )
    return path


def test_a_decompression_bomb_is_refused_before_decoding(tmp_path, monkeypatch):
    bomb = png_bomb(tmp_path / "bomb.png")
    assert bomb.stat().st_size < 200_000

    def no_decoding(*args, **kwargs):
        raise AssertionError("decoded a 144-megapixel image")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    with pytest.raises(ImageError) as info:
        read_image(bomb)
    assert str(info.value) == (
        f"{bomb}: an image of 12000x12000 pixels, over the limit of 64,000,000 (a decompression bomb?); "
        f"set {MAX_PIXELS_VARIABLE} to read larger images"
    )
    monkeypatch.undo()
    cv2.imwrite(str(tmp_path / "ok.png"), texture(0))
    frames = list(FrameSource(tmp_path))  # predict names and skips it
    assert [(f.name, f.error) for f in frames] == [("bomb", str(info.value)), ("ok", None)]


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".bmp", ".tif"])
def test_the_pixel_limit_is_an_option(tmp_path, monkeypatch, suffix):
    path = tmp_path / f"wide{suffix}"
    cv2.imwrite(str(path), texture(0)[:50])  # 64 x 50 = 3200 pixels
    assert read_image(path, max_pixels=3200).bgr.shape == (50, 64, 3)
    with pytest.raises(ImageError, match=f"^{path}: an image of 64x50 pixels, over the limit of 3,199 "):
        read_image(path, max_pixels=3199)
    monkeypatch.setenv(MAX_PIXELS_VARIABLE, "3199")
    with pytest.raises(ImageError, match=f"set {MAX_PIXELS_VARIABLE} to read larger images$"):
        read_image(path)
    monkeypatch.setenv(MAX_PIXELS_VARIABLE, "lots")
    with pytest.raises(ValueError, match=f"^{MAX_PIXELS_VARIABLE}='lots': expected a number of pixels >= 1$"):
        read_image(path)


# ------------------------------------------------------------------ a full disk while rendering
@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (Linux)")
def test_a_full_disk_while_rendering_is_named(tmp_path, monkeypatch, capsys):
    """The LiDAR scans hit the full disk first here, as in the run that reported only
    ``128556 requested and 67584 written`` (numpy's short write): the kernel's own ENOSPC, from /dev/full."""
    real_write = Path.write_bytes
    monkeypatch.setattr(
        Path, "write_bytes", lambda p, d: real_write(Path("/dev/full") if p.suffix == ".bin" else p, d)
    )
    out = tmp_path / "syn"
    with pytest.raises(NoSpaceLeft) as info:
        generate(out, WorldSpec("kitti360", frames=9, size=16, supersample=1), progress=False)
    assert isinstance(info.value, ValueError) and info.value.errno == errno.ENOSPC
    assert str(info.value).startswith(
        f"{out}: no space left on device while rendering the synthetic dataset (writing 0000000000.bin); "
        "the partial dataset was removed, "
    )
    assert list(tmp_path.iterdir()) == []  # neither the dataset nor its partial folder
    assert (
        synthetic_main(["--out", str(out), "--frames", "9", "--size", "16", "--supersample", "1", "--quiet"])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {out}: no space left on device")


# ------------------------------------------------------------------ broken symbolic links to predict on
def test_broken_and_looping_links_are_counted_as_skipped(tmp_path):
    images = tmp_path / "in"
    images.mkdir()
    cv2.imwrite(str(images / "a_good.png"), texture(0))
    (images / "b_gone.png").symlink_to(tmp_path / "deleted.png")
    (images / "c_loop.jpg").symlink_to(images / "c_loop.jpg")
    frames = list(FrameSource(images))
    gone, loop = images / "b_gone.png", images / "c_loop.jpg"
    assert [(f.name, f.error) for f in frames] == [
        ("a_good", None),
        (
            "b_gone",
            f"{gone}: a symbolic link to {tmp_path / 'deleted.png'} that leads nowhere (its target is gone)",
        ),
        ("c_loop", f"{loop}: a symbolic link to {loop} that loops back on itself"),
    ]

    torch.manual_seed(0)
    module = bare_module(net={"scales": (0, 1), "base_focal": 20.0}, input_size=(SIZE, SIZE))
    ckpt = tmp_path / "untrained.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, ckpt)
    calib = save_camera(kitti02().resize(SIZE, SIZE), tmp_path / "cam.yaml")
    out = tmp_path / "out"
    summary = predict(predict_cfg(ckpt_path=ckpt, input=images, camera=calib, output=out))
    assert summary["frames"] == 1 and summary["skipped"] == 2
    assert summary["unreadable"] == [str(gone), str(loop)]
    assert json.loads((out / "summary.json").read_text())["unreadable"] == summary["unreadable"]
    assert sorted(p.name for p in out.glob("*_distance.npy")) == ["a_good_distance.npy"]


# ------------------------------------------------------------------ an output folder that refuses writes
def read_only(monkeypatch, folder: Path) -> None:
    """Writes into ``folder`` fail as on a read-only mount (root ignores permission bits, so the kernel's
    answer is simulated where a file is created)."""
    real = tempfile.NamedTemporaryFile

    def refuse(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve().is_relative_to(folder.resolve()):
            raise OSError(errno.EROFS, "Read-only file system", str(Path(dir) / "x"))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "NamedTemporaryFile", refuse)


def test_predict_into_a_read_only_folder_is_refused_before_any_work(tmp_path, monkeypatch, capsys):
    from fisheyedepth.cli import predict as predict_module

    out = tmp_path / "ro"
    out.mkdir()
    read_only(monkeypatch, out)
    monkeypatch.setattr(predict_module, "load_runtime", lambda cfg: pytest.fail("the network was loaded"))
    cfg = predict_cfg(input=tmp_path / "in", camera=tmp_path / "cam.yaml", output=out)
    line = one_line_error(predict, cfg, capsys)
    assert line == f"error: output: {out}: cannot write there (Read-only file system)"
    # a folder still to be made is checked in its nearest existing parent, and is not made by the check
    read_only(monkeypatch, tmp_path)
    cfg = predict_cfg(input=tmp_path / "in", camera=tmp_path / "cam.yaml", output=tmp_path / "new" / "out")
    line = one_line_error(predict, cfg, capsys)
    assert line == f"error: output: {tmp_path / 'new' / 'out'}: cannot write there (Read-only file system)"
    assert not (tmp_path / "new").exists()


@pytest.mark.parametrize(
    ("code", "text"), [(errno.EROFS, "Read-only file system"), (errno.ENOSPC, "No space left on device")]
)
def test_a_refused_write_anywhere_in_a_command_is_one_line(code, text, tmp_path, capsys):
    target = tmp_path / "out" / "frame_distance.npy"

    def command(cfg):
        raise OSError(code, text, str(target))

    assert one_line_error(command, None, capsys) == f"error: {target}: cannot write there ({text})"


def test_an_os_error_that_is_no_refused_write_keeps_its_traceback(tmp_path):
    """An I/O error of the machine (EIO) is not the user's input: it is raised, not hidden in one line."""

    def command(cfg):
        raise OSError(errno.EIO, "Input/output error", str(tmp_path / "x"))

    with pytest.raises(OSError, match="Input/output error"):
        run_command(command, None)
