"""Names that become paths: a camera or sequence name from a bag's options, a ``rig.yaml``, a calibration
file, an Aria export, a split file or a KITTI-360 option is one plain file or folder name
(``fisheyedepth.files.path_name``), or the command stops with one line naming the file and the field;
nothing is read or written outside the dataset's folder. And the importers' writes: all or nothing,
never over an existing file without ``--overwrite``."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from fisheyedepth.data.aria import CALIBRATION, aria_to_rig
from fisheyedepth.data.dataset import parse_split
from fisheyedepth.data.kitti360 import Kitti360Layout
from fisheyedepth.data.layouts import RigLayout
from fisheyedepth.files import NAME_BYTES, move_into_place, path_name, staged_folder

from test_faults_data import write_tiny_rig

T0 = 1_700_000_000_000_000_000
PLAIN = ": it must be one plain file or folder name"


def tree(root: Path) -> dict[str, bytes | None]:
    """Every entry under ``root`` with a file's content (None for a folder)."""
    return {str(p.relative_to(root)): None if p.is_dir() else p.read_bytes() for p in sorted(root.rglob("*"))}


# 1. The one check -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name, why",
    [
        ("", "is empty"),
        (".", "is not a name but a folder (this one or its parent)"),
        ("..", "is not a name but a folder (this one or its parent)"),
        ("../../x", "contains a path separator ('/')"),
        ("left\\..\\..\\x", "contains a path separator ('\\\\')"),
        ("/etc/passwd", "is an absolute path"),
        ("\\\\server\\share", "is an absolute path"),
        ("cam\x00.png", "contains a control character ('\\x00')"),
        ("cam\nseq1 7", "contains a control character ('\\n')"),
        ("-rf", "starts with '-', which command-line tools read as an option"),
        ("x" * (NAME_BYTES + 1), f"is {NAME_BYTES + 1} bytes long, more than {NAME_BYTES}"),
        ("é" * (NAME_BYTES // 2 + 1), f"is {NAME_BYTES + 2} bytes long, more than {NAME_BYTES}"),  # UTF-8
    ],
)
def test_a_name_that_is_not_one_plain_file_name_is_refused_naming_source_field_and_name(name, why):
    with pytest.raises(ValueError) as info:
        path_name(name, "cameras[2].name", "data/rig/rig.yaml")
    assert str(info.value) == f"data/rig/rig.yaml: cameras[2].name {name!r} {why}{PLAIN}"
    assert "\n" not in str(info.value)  # one line, whatever the name holds


@pytest.mark.parametrize(
    "name", ["image_02", "slam-front-left", "cam0", ".hidden", "left cam", "x" * NAME_BYTES]
)
def test_plain_names_pass_unchanged(name):
    assert path_name(name, "camera", "--camera") == name


def test_a_name_that_is_not_a_string_is_refused():
    with pytest.raises(ValueError, match=r"^split: sequence 7 is not a name \(a string\)$"):
        path_name(7, "sequence", "split")


# 2. The ROS bag importer ------------------------------------------------------------------------------


@pytest.fixture
def bag(tmp_path) -> Path:
    """A four-image ROS 2 bag of camera topic /cam/image_raw (tests/test_faults_import.py's)."""
    pytest.importorskip("rosbags")
    from test_faults_import import camera_bag

    camera_bag(tmp_path / "bags" / "run")
    (tmp_path / "bags" / "extrinsics.yaml").write_text(yaml.safe_dump({"cam": np.eye(4).tolist()}))
    return tmp_path / "bags" / "run"


def import_main(bag: Path, out: Path, *options: str) -> int:
    from fisheyedepth.cli.import_rosbag import main

    return main([str(bag), "--out", str(out), "--odometry", "/odom", *options])


def test_a_camera_name_that_climbs_out_of_out_is_refused_and_nothing_is_written(bag, tmp_path, capsys):
    """``--camera ../../../x=TOPIC`` wrote ``calibration/../../../x.yaml`` from the staging folder beside
    ``out``: two folders above it, over a file there, without ``--overwrite``; and its images beside it."""
    from test_faults_import import IMAGE, INFO

    out = tmp_path / "work" / "rig"
    victim = tmp_path / "x.yaml"  # where the calibration landed
    victim.write_text("mine\n")
    extrinsics = bag.parent / "extrinsics.yaml"
    extrinsics.write_text(yaml.safe_dump({"../../../x": np.eye(4).tolist()}))  # the import went through
    before = tree(tmp_path)
    args = ["--camera-info", f"../../../x={INFO}", "--extrinsics", str(extrinsics)]
    assert import_main(bag, out, "--camera", f"../../../x={IMAGE}", *args) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        f"error: --camera: camera '../../../x' contains a path separator ('/'){PLAIN}"
    ]
    assert captured.out == ""
    assert tree(tmp_path) == before and victim.read_text() == "mine\n"  # no out, no staging, no x/


@pytest.mark.parametrize(
    "option, value, message",
    [
        ("--camera", "{abs}=/cam/image_raw", "--camera: camera '{abs}' is an absolute path"),
        (
            "--camera",
            "..=/cam/image_raw",
            "--camera: camera '..' is not a name but a folder (this one or its parent)",
        ),
        ("--sequence", "../seq0", "--sequence: sequence '../seq0' contains a path separator ('/')"),
        ("--sequence", "..", "--sequence: sequence '..' is not a name but a folder (this one or its parent)"),
    ],
)
def test_absolute_and_parent_names_of_the_importer_are_refused(bag, tmp_path, capsys, option, value, message):
    from test_faults_import import IMAGE

    outside = tmp_path / "elsewhere"
    value, message = value.format(abs=outside), message.format(abs=outside)
    out = tmp_path / "work" / "rig"
    options = [option, value] if option == "--camera" else ["--camera", f"cam={IMAGE}", option, value]
    before = tree(tmp_path)
    assert import_main(bag, out, *options, "--extrinsics", str(bag.parent / "extrinsics.yaml")) == 2
    assert capsys.readouterr().err.splitlines() == [f"error: {message}{PLAIN}"]
    assert tree(tmp_path) == before


def test_the_importer_reports_on_stderr_with_exit_2(bag, tmp_path, capsys):
    """One ``error:`` line on stderr and nothing on stdout, as every other command does; a NAME=VALUE
    option without '=' is such an error too (it ended the process with status 1)."""
    from test_faults_import import IMAGE

    out = tmp_path / "rig"
    assert import_main(bag, out, "--camera", "cam=/not/a/topic") == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [
        f"error: {bag}: topic /not/a/topic is not in the bag (it has ['/cam/camera_info', '/cam/image_raw', "
        "'/odom'])"
    ]
    assert import_main(bag, out, "--camera", "cam") == 2
    assert capsys.readouterr().err.splitlines() == ["error: --camera: expected NAME=VALUE, got 'cam'"]
    assert import_main(bag, out, "--camera", f"cam={IMAGE}", "--camera", "cam=/other") == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: --camera: cam given twice (cam={IMAGE} and cam=/other)"
    ]
    assert not out.exists()
    # and a good import still prints its summary on stdout
    assert (
        import_main(bag, out, "--camera", f"cam={IMAGE}", "--extrinsics", str(bag.parent / "extrinsics.yaml"))
        == 0
    )
    captured = capsys.readouterr()
    assert json.loads(captured.out)["images"] == {"cam": 4} and "error" not in captured.err


def test_a_failed_import_into_a_new_folder_leaves_no_folder_it_made(bag, tmp_path):
    """``--out a/b/rig`` with ``a`` missing: the failed import removes ``a/b`` as well as its staging."""
    from fisheyedepth.data.rosbag import RosbagError, import_rosbag

    with pytest.raises(RosbagError, match="topic /nope is not in the bag"):
        import_rosbag(bag, tmp_path / "a" / "b" / "rig", {"cam": "/nope"}, odometry="/odom")
    assert not (tmp_path / "a").exists()


# 3. The rig layout: rig.yaml, a calibration file, a sequence, a split file ---------------------------


@pytest.fixture
def rig(tmp_path) -> Path:
    """A one-camera rig two folders below ``tmp_path``, and, beside the rig, an ``elsewhere`` folder of
    images that ``drive/images/../../../../elsewhere`` reached."""
    root = tmp_path / "a" / "b" / "rig"
    write_tiny_rig(root, [T0, T0 + 10**8], [0.0, 0.1], [T0 + 5 * 10**7])
    (tmp_path / "a" / "elsewhere").mkdir()
    (tmp_path / "a" / "elsewhere" / f"{T0 + 5 * 10**7}.png").write_bytes(
        (root / "drive" / "images" / "cam" / f"{T0 + 5 * 10**7}.png").read_bytes()
    )
    return root


@pytest.mark.parametrize(
    "name, why",
    [
        ("../../../../elsewhere", "contains a path separator ('/')"),
        ("..", "is not a name but a folder (this one or its parent)"),
        ("/tmp/elsewhere", "is an absolute path"),
        ("", "is empty"),
    ],
)
def test_a_rig_camera_named_like_a_path_is_refused_naming_rig_yaml_and_the_field(rig, name, why):
    data = yaml.safe_load((rig / "rig.yaml").read_text())
    data["cameras"].append({**data["cameras"][0], "name": name})
    (rig / "rig.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ValueError) as info:
        RigLayout(rig)
    assert str(info.value) == f"{rig / 'rig.yaml'}: cameras[1].name {name!r} {why}{PLAIN}"


def test_a_camera_of_the_rig_that_climbs_out_is_refused_by_training_too(rig):
    from fisheyedepth.data import FisheyeDataModule

    data = yaml.safe_load((rig / "rig.yaml").read_text())
    data["cameras"][0]["name"] = "../../../../elsewhere"
    (rig / "rig.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(
        ValueError, match=re.escape(f"{rig / 'rig.yaml'}: cameras[0].name '../../../../elsewhere'")
    ):
        FisheyeDataModule(rig, layout="rig").setup("fit")


@pytest.mark.parametrize("sequence", ["../../../a/elsewhere", "..", str(Path("/tmp") / "drive")])
def test_a_sequence_named_like_a_path_is_refused_by_the_rig_layout(rig, sequence):
    layout = RigLayout(rig)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(rig))}: sequence {re.escape(repr(sequence))} "):
        layout.frames(sequence, "cam")
    with pytest.raises(ValueError, match=rf"^{re.escape(str(rig))}: camera '\.\./cam' contains a path"):
        layout.frames("drive", "../cam")
    assert [f.key for f in layout.frames("drive", "cam")] == [T0 + 5 * 10**7]


def test_a_split_file_names_its_line_for_a_sequence_or_camera_named_like_a_path(rig):
    split = rig / "split.txt"
    split.write_text(f"drive {T0 + 5 * 10**7}\n../../../a/elsewhere {T0 + 5 * 10**7}\n")
    layout = RigLayout(rig)
    with pytest.raises(ValueError) as info:
        parse_split(split, layout)
    assert str(info.value) == (
        f"{split}:2: sequence '../../../a/elsewhere' contains a path separator ('/'){PLAIN}"
    )
    split.write_text(f"drive {T0 + 5 * 10**7} ..\n")
    with pytest.raises(ValueError, match=rf"^{re.escape(str(split))}:1: camera '\.\.' is not a name"):
        parse_split(split, layout)
    with pytest.raises(ValueError, match=r"^split: sequence '\.\./x' contains a path separator"):
        parse_split([{"sequence": "../x"}], layout)
    assert parse_split([{"sequence": "drive"}], layout) == [("drive", slice(None, None), 1, None)]


# 4. KITTI-360 options, an Aria export, the body-mask command -------------------------------------------


def kitti_root(root: Path) -> Path:
    (root / "calibration").mkdir(parents=True)
    (root / "calibration" / "calib_cam_to_pose.txt").write_text("image_02: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return root


def test_kitti360_cameras_and_sequences_named_like_paths_are_refused(tmp_path):
    root = kitti_root(tmp_path / "kitti360")
    (tmp_path / "x.yaml").write_text("model: pinhole\n")  # what calibration/../../x.yaml read
    with pytest.raises(ValueError) as info:
        Kitti360Layout(root, cameras=["../../x"])
    assert str(info.value) == f"cameras: camera '../../x' contains a path separator ('/'){PLAIN}"
    with pytest.raises(ValueError, match=r"^cameras: camera '/etc/x' is an absolute path"):
        Kitti360Layout(root, cameras=["/etc/x"])
    layout = Kitti360Layout.__new__(Kitti360Layout)
    layout.root, layout._frames = root, {}
    with pytest.raises(ValueError, match=rf"^{re.escape(str(root))}: sequence '\.\./\.\./x' contains"):
        layout.frames("../../x")


def test_an_aria_camera_or_sequence_named_like_a_path_is_refused_and_nothing_is_written(tmp_path):
    src = tmp_path / "export"
    src.mkdir()
    (src / CALIBRATION).write_text(json.dumps({"..": {}, "cam": {}}))
    out = tmp_path / "rig"
    with pytest.raises(ValueError) as info:
        aria_to_rig(src, out)
    assert str(info.value) == (
        f"{src / CALIBRATION}: camera '..' is not a name but a folder (this one or its parent){PLAIN}"
    )
    (src / CALIBRATION).write_text(json.dumps({str(tmp_path / "elsewhere"): {}}))
    with pytest.raises(
        ValueError, match=rf"^{re.escape(str(src / CALIBRATION))}: camera .* is an absolute path"
    ):
        aria_to_rig(src, out)
    with pytest.raises(ValueError, match=r"^--sequence: sequence '\.\./seq0' contains a path separator"):
        aria_to_rig(src, out, sequence="../seq0")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export"]


@pytest.mark.parametrize("option, value", [("--camera", "../cam"), ("--sequence", "../drive")])
def test_the_body_mask_command_refuses_a_camera_or_sequence_named_like_a_path(rig, capsys, option, value):
    from fisheyedepth.cli.estimate_mask import main

    args = {"--camera": "cam", "--sequence": "drive", option: value}
    argv = ["--root", str(rig), "--layout", "rig", *(x for kv in args.items() for x in kv)]
    assert main(argv) == 2
    captured = capsys.readouterr()
    what = option.removeprefix("--")
    assert f"error: {option}: {what} {value!r} contains a path separator ('/'){PLAIN}" in (
        captured.out + captured.err
    )
    assert not (rig / "masks").exists() and not (rig.parent / "masks").exists()


# 5. Moving an import into place: never over a file without overwrite, all or nothing ------------------


def staged(tmp_path: Path, files: dict[str, str]) -> Path:
    staging = tmp_path / ".staging"
    for name, text in files.items():
        (staging / name).parent.mkdir(parents=True, exist_ok=True)
        (staging / name).write_text(text)
    return staging


def test_a_part_written_since_the_check_is_not_replaced_without_overwrite(tmp_path):
    out = tmp_path / "rig"
    (out / "seq1").mkdir(parents=True)
    (out / "rig.yaml").write_text("theirs\n")  # written by another command after the caller's check
    staging = staged(tmp_path, {"seq0/poses.txt": "mine\n", "rig.yaml": "mine\n"})
    with pytest.raises(FileExistsError, match=rf"^{re.escape(str(out / 'rig.yaml'))} exists; pass overwrite"):
        move_into_place(staging, out, [Path("seq0"), Path("rig.yaml")])
    assert (out / "rig.yaml").read_text() == "theirs\n" and not (out / "seq0").exists()
    move_into_place(staging, out, [Path("seq0"), Path("rig.yaml")], overwrite=True)
    assert (out / "rig.yaml").read_text() == "mine\n" and (out / "seq0" / "poses.txt").read_text() == "mine\n"


def test_a_part_that_cannot_be_moved_puts_back_what_was_there(tmp_path):
    """The second part's folder is a file in ``out``: the first part, already moved, is taken back and
    the file it replaced is put back."""
    out = tmp_path / "rig"
    (out / "seq0").mkdir(parents=True)
    (out / "seq0" / "poses.txt").write_text("old\n")
    (out / "calibration").write_text("a file where a folder should be\n")
    staging = staged(
        tmp_path, {"seq0/poses.txt": "new\n", "calibration/cam.yaml": "new\n", "rig.yaml": "new\n"}
    )
    before = tree(out)
    with pytest.raises(OSError):
        move_into_place(staging, out, [Path("seq0"), Path("calibration/cam.yaml"), Path("rig.yaml")], True)
    assert tree(out) == before
    assert (staging / "seq0" / "poses.txt").read_text() == "new\n"  # the part went back where it was


def test_a_part_that_names_a_path_outside_out_is_refused(tmp_path):
    out = tmp_path / "rig"
    (out / "seq1").mkdir(parents=True)
    staging = staged(tmp_path, {"x.yaml": "mine\n"})
    with pytest.raises(ValueError, match=r"\.\./x\.yaml lies outside"):
        move_into_place(staging, out, [Path("../x.yaml")])
    assert not (tmp_path / "x.yaml").exists()


def test_a_staged_folder_leaves_nothing_when_nothing_was_put_in_place(tmp_path):
    out = tmp_path / "a" / "b" / "rig"
    with pytest.raises(RuntimeError), staged_folder(out, "importing") as staging:
        (staging / "half.png").write_bytes(b"x")
        raise RuntimeError
    assert not (tmp_path / "a").exists()
    (tmp_path / "c").mkdir()
    with staged_folder(tmp_path / "c" / "d" / "rig", "importing") as staging:
        (staging / "rig.yaml").write_text("done\n")
        os.replace(staging, tmp_path / "c" / "d" / "rig")
    assert (tmp_path / "c" / "d" / "rig" / "rig.yaml").read_text() == "done\n"
