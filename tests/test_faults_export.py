"""Faults around exported files: metadata that would give wrong distances without an error, two export.py
writing one file at once, and an output folder that refuses writes.

An exported file's metadata scales every distance it gives (``depth_scale``, ``base_focal``) and fixes
its input size: a value of 0, -1, nan or inf there must stop predict.py and eval.py with one line naming
the file and the field, not give maps of 1e9 m or NaN. Two exports of one ``output=F`` take turns: one
writes F and its record whole, the other is refused (or, with ``overwrite=true``, replaces both); the
record's sha256 is the file's.
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import threading
from pathlib import Path

import pytest
from omegaconf import OmegaConf

import fisheyedepth.cli.export as export_module
import fisheyedepth.files as files_module
from fisheyedepth.cli.export import export
from fisheyedepth.cli.predict import predict
from fisheyedepth.runtimes import META, OnnxRuntime, add_metadata

from conftest import load_cfg
from test_faults_entrypoints import images_of, one_line_error, predict_cfg


def export_cfg(checkpoint, output: Path, size: int = 64, **values):
    cfg = load_cfg(
        "export",
        ckpt_path=checkpoint,
        size=[size, size],
        output=output,
        paths={"output_dir": str(output.parent)},
    )
    return OmegaConf.merge(cfg, values)


@pytest.fixture(scope="module")
def exported(checkpoint, tmp_path_factory) -> Path:
    """A float32 file export.py wrote from the tiny checkpoint, at 64x64 (base focal 20, depth_scale 1)."""
    pytest.importorskip("onnxruntime")
    path = tmp_path_factory.mktemp("exported") / "m.onnx"
    export(export_cfg(checkpoint, path))
    return path


def with_metadata(source: Path, path: Path, **fields: str) -> Path:
    """A copy of ``source`` at ``path`` whose metadata fields (without the ``fisheyedepth.`` prefix) are
    replaced by ``fields``."""
    path.write_bytes(add_metadata(source.read_bytes(), {META + k: v for k, v in fields.items()}))
    return path


BAD_METADATA = [
    ("depth_scale", "0.0", "a finite number > 0 (the file's paraxial focal / base focal)"),
    ("depth_scale", "-1.0", "a finite number > 0 (the file's paraxial focal / base focal)"),
    ("depth_scale", "nan", "a finite number > 0 (the file's paraxial focal / base focal)"),
    ("depth_scale", "inf", "a finite number > 0 (the file's paraxial focal / base focal)"),
    ("depth_scale", "one", "a finite number > 0 (the file's paraxial focal / base focal)"),
    ("base_focal", "-1.0", "'none' or a focal length in pixels, a finite number > 0"),
    ("base_focal", "inf", "'none' or a focal length in pixels, a finite number > 0"),
    ("base_focal", "0", "'none' or a focal length in pixels, a finite number > 0"),
    ("base_focal", "None", "'none' or a focal length in pixels, a finite number > 0"),
    ("input_size", "64", "'W,H', two whole numbers, each a multiple of 32"),
    ("input_size", "64,64,3", "'W,H', two whole numbers, each a multiple of 32"),
    ("input_size", "64.0,64", "'W,H', two whole numbers, each a multiple of 32"),
    ("input_size", "-64,64", "'W,H', two whole numbers, each a multiple of 32"),
    ("input_size", "100,64", "'W,H', two whole numbers, each a multiple of 32"),
    ("quantize", "int4", "one of none, int8"),
    ("quantize", "", "one of none, int8"),
]


def test_the_exported_files_metadata_is_read_as_written(exported, tmp_path):
    """The fields as export.py writes them, and ``base_focal`` none (depth_scale 1 for every camera)."""
    runtime = OnnxRuntime(exported)
    assert (runtime.input_size, runtime.file_scale, runtime.base_focal, runtime.quantize) == (
        (64, 64), 1.0, 20.0, "none",
    )  # fmt: skip
    unscaled = OnnxRuntime(
        with_metadata(exported, tmp_path / "none.onnx", base_focal="none", depth_scale="2.5")
    )
    assert (unscaled.base_focal, unscaled.file_scale) == (None, 2.5)


@pytest.mark.parametrize(("field", "value", "expected"), BAD_METADATA)
def test_metadata_that_would_scale_distances_wrongly_is_refused_by_name(
    exported, kitti_data, tmp_path, capsys, field, value, expected
):
    """Each bad value is refused when the file is opened, and predict.py ends with exit 2 and the one
    line that names the file and the field, before any frame is read."""
    bad = with_metadata(exported, tmp_path / "bad.onnx", **{field: value})
    message = f"{bad}: metadata field 'fisheyedepth.{field}' is {value!r}, not {expected}"
    with pytest.raises(ValueError) as info:
        OnnxRuntime(bad)
    assert str(info.value) == message
    images = images_of(kitti_data, tmp_path / "in", 1)
    calib = kitti_data / "calibration" / "image_02.yaml"
    cfg = predict_cfg(runtime="onnx", model_file=bad, input=images, camera=calib, output=tmp_path / "out")
    assert one_line_error(predict, cfg, capsys) == f"error: {message}"
    out = tmp_path / "out"
    assert not (out.exists() and any(out.iterdir()))  # no frame written


def test_add_metadata_replaces_a_field_instead_of_adding_a_second_one(exported):
    import onnx

    model = onnx.load_from_string(add_metadata(exported.read_bytes(), {META + "depth_scale": "3.0"}))
    entries = [(p.key, p.value) for p in model.metadata_props if p.key == META + "depth_scale"]
    assert entries == [(META + "depth_scale", "3.0")]
    assert len(model.metadata_props) == 4  # input_size, depth_scale, base_focal, quantize


# ------------------------------------------------------------------ two exports of one file
def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def pair_on_disk(path: Path) -> dict:
    """The record beside ``path``, checked to be the file's: its sha256 and its input size."""
    record = json.loads(Path(str(path) + ".json").read_text())
    assert record["sha256"] == sha256(path) and record["path"] == str(path)
    assert list(OnnxRuntime(path).input_size) == record["size"]
    return record


def hold_during_export(monkeypatch, during):
    """Run ``during()`` once the network is exported and checked, just before its file is placed (in
    the first export only)."""
    original, calls = export_module.exported, []

    def exported(*args, **kwargs):
        result = original(*args, **kwargs)
        calls.append(1)
        if len(calls) == 1:
            during()
        return result

    monkeypatch.setattr(export_module, "exported", exported)


def second_export_waiting(monkeypatch, cfg) -> tuple[threading.Thread, dict]:
    """Another export.py of ``cfg`` in a thread, started and left waiting at the output's lock; the
    dict gets its record or its error."""
    import fcntl

    waiting, result = threading.Event(), {}
    flock = fcntl.flock

    def noting_flock(fd, operation):
        if threading.current_thread() is not threading.main_thread():
            waiting.set()
        return flock(fd, operation)

    monkeypatch.setattr(fcntl, "flock", noting_flock)  # the writers' lock (files.take_lock)

    def run():
        try:
            result["record"] = export(cfg)
        except Exception as err:  # noqa: BLE001 - handed to the test
            result["error"] = err

    thread = threading.Thread(target=run)
    thread.start()
    assert waiting.wait(120), "the second export never reached the lock"
    thread.join(0.5)
    assert thread.is_alive(), "the second export did not wait for the first"
    return thread, result


@pytest.mark.parametrize("overwrite", [False, True])
def test_two_exports_of_one_file_take_turns_and_the_record_is_the_files(
    checkpoint, tmp_path, monkeypatch, overwrite
):
    """A 64 px export holds the output while a 128 px export of the same ``output=F`` starts. Without
    overwrite the second is refused once the first is done, and F and F.json are the first's; with it,
    the second replaces both, so F and F.json are the second's. Either way the record on disk is the
    file's, and no lock or temporary file is left."""
    out = tmp_path / "m.onnx"
    later: dict = {}

    def start_second():
        later["thread"], later["result"] = second_export_waiting(
            monkeypatch, export_cfg(checkpoint, out, 128, overwrite=overwrite)
        )

    hold_during_export(monkeypatch, start_second)
    first = export(export_cfg(checkpoint, out, 64, overwrite=overwrite))
    later["thread"].join(300)
    result = later["result"]
    on_disk = pair_on_disk(out)
    if overwrite:
        assert "error" not in result and result["record"]["size"] == [128, 128]
        assert on_disk == result["record"] and first["sha256"] != on_disk["sha256"]
    else:
        assert isinstance(result["error"], FileExistsError)
        assert str(result["error"]) == f"{out} exists; pass overwrite=true to replace it"
        assert on_disk == first and on_disk["size"] == [64, 64]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.onnx", "m.onnx.json"]


@pytest.mark.parametrize("appears", ["m.onnx", "m.onnx.json"])
def test_a_file_that_appears_while_exporting_is_not_replaced(
    checkpoint, tmp_path, monkeypatch, capsys, appears
):
    """Another program writes F (or F.json) after the export checked that F was free: without
    overwrite the export is refused with one line and leaves what appeared as it was; a file it placed
    already is taken back, so no file is left without its record."""
    out = tmp_path / "m.onnx"
    foreign = tmp_path / appears
    hold_during_export(monkeypatch, lambda: foreign.write_bytes(b"another program's file"))
    assert one_line_error(export, export_cfg(checkpoint, out), capsys) == (
        f"error: {foreign} exists; pass overwrite=true to replace it"
    )
    assert foreign.read_bytes() == b"another program's file"
    assert sorted(p.name for p in tmp_path.iterdir()) == [appears]


def test_a_record_left_without_its_file_needs_overwrite(checkpoint, tmp_path, capsys):
    out = tmp_path / "m.onnx"
    (tmp_path / "m.onnx.json").write_text("{}")
    assert one_line_error(export, export_cfg(checkpoint, out), capsys) == (
        f"error: {out}.json exists; pass overwrite=true to replace it"
    )
    assert not out.exists()
    record = export(export_cfg(checkpoint, out, overwrite=True))
    assert pair_on_disk(out) == record


# ------------------------------------------------------------------ an output folder that refuses writes
def test_an_output_folder_on_a_read_only_filesystem_is_one_line(checkpoint, tmp_path, monkeypatch, capsys):
    """The folder cannot be created (a read-only filesystem): refused before any export work."""
    folder = tmp_path / "ro"
    mkdir = Path.mkdir

    def read_only(self, *args, **kwargs):
        if self == folder:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(self))
        return mkdir(self, *args, **kwargs)

    monkeypatch.setattr(Path, "mkdir", read_only)
    monkeypatch.setattr(
        export_module, "exported", lambda *a, **k: pytest.fail("exported into a read-only folder")
    )
    assert one_line_error(export, export_cfg(checkpoint, folder / "m.onnx"), capsys) == (
        f"error: {folder / 'm.onnx'}: cannot be written (Read-only file system: {folder}); "
        "choose another output=FILE"
    )


def test_a_folder_that_refuses_the_file_is_one_line_and_leaves_nothing(
    checkpoint, tmp_path, monkeypatch, capsys
):
    """The folder takes the lock but refuses the file (it became read-only, or permission was taken
    away): one line naming the file, and no temporary, lock or record left."""
    out = tmp_path / "m.onnx"

    def refused(*args, dir=None, **kwargs):  # noqa: A002 - tempfile's keyword
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), dir)

    hold_during_export(monkeypatch, lambda: monkeypatch.setattr(files_module.tempfile, "mkstemp", refused))
    assert one_line_error(export, export_cfg(checkpoint, out), capsys) == (
        f"error: {out}: cannot be written (Permission denied: {tmp_path}); choose another output=FILE"
    )
    assert list(tmp_path.iterdir()) == []


def test_a_folder_without_write_permission_is_one_line(checkpoint, tmp_path, capsys):
    """The same with a real folder of mode 0555 (not for root, who writes there anyway)."""
    folder = tmp_path / "locked"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        if os.access(folder, os.W_OK):
            pytest.skip("this user writes into a folder of mode 0555 (root)")
        assert one_line_error(export, export_cfg(checkpoint, folder / "m.onnx"), capsys) == (
            f"error: {folder / 'm.onnx'}: cannot be written (Permission denied: {folder / '.m.onnx.lock'}); "
            "choose another output=FILE"
        )
    finally:
        folder.chmod(0o755)
