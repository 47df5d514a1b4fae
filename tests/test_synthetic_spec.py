"""WorldSpec, what a synthetic dataset is: checked when made (each error names its option, as an argument
or as configured), equal whatever spelling of the same parameters, recorded in ``synthetic.json`` and
read back to the same spec, and compared with a finished dataset's record before it is reused."""

from __future__ import annotations

import dataclasses
import json
import pickle

import pytest

from fisheyedepth.synthetic import (
    DatasetMismatch,
    WorldSpec,
    ensure_dataset,
    ensure_datasets,
    generate,
    is_complete,
)
from fisheyedepth.synthetic.spec import UNWRITTEN

TINY = {"frames": 9, "size": 16, "supersample": 1}
QUIET = {"lidar": False, "progress": False}
DENSITY = r"\(0: no traffic, 1: a busy street\)"


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"traffic": 9}, rf"^traffic: 9 is not a number in \[0, 8\] {DENSITY}$"),
        ({"frames": 5}, r"^frames: 5 is not a whole number >= 9 \(3 per split\)$"),
        ({"seed": -1}, r"^seed: -1 is not a whole number >= 0$"),
        ({"supersample": 0}, r"^supersample: 0 is not a whole number >= 1$"),
        ({"random_cameras": "maybe"}, r"^random_cameras: 'maybe' is not a boolean \(true or false\)$"),
        ({"effects": [{"noise": -1}]}, r"^effects\[0\]: \{'noise': -1\} is not one of exposure, "),
        ({"effects": ["fog"]}, r"^effects\[0\]: 'fog' is not one of exposure, "),
        ({"size": 20}, r"^size must be a multiple of 8 and at least 16, got 20$"),
        ({"rig": "fisheye"}, r"^unknown rig 'fisheye'; one of \('kitti360', 'surround4', 'stereo'\)$"),
        ({"lane": "centre"}, r"^lane must be one of \{'right': 1\.75, 'left': -1\.75\}, got 'centre'$"),
        ({"scene": "garden"}, r"^scene must be one of \('street', 'indoor'\), got 'garden'$"),
    ],
)
def test_a_parameter_not_of_its_kind_is_refused_by_name(options, message):
    with pytest.raises(ValueError, match=message):
        WorldSpec(**{**TINY, **options})


def test_from_config_names_the_configured_key():
    traffic = rf"^data\.generate\.traffic: 9 is not a number in \[0, 8\] {DENSITY}$"
    with pytest.raises(ValueError, match=traffic):
        WorldSpec.from_config({**TINY, "traffic": 9})
    with pytest.raises(ValueError, match=r"^data\.generate\.colour: not an option of the synthetic dataset"):
        WorldSpec.from_config({**TINY, "colour": "red"})
    with pytest.raises(ValueError, match=r"^--frames: 5 is not a whole number >= 9"):
        WorldSpec.from_config({"frames": 5}, prefix="--")
    # the rendering options are of a config's data.generate too, but not of the spec; checked all the same
    config = {**TINY, **QUIET, "workers": 2, "seed": 4, "effects": "noise"}
    assert WorldSpec.from_config(config) == WorldSpec(**TINY, seed=4, effects=["noise"])
    with pytest.raises(ValueError, match=r"^data\.generate\.workers: -1 is not a whole number >= 0$"):
        WorldSpec.from_config({**TINY, "workers": -1})


def test_the_same_parameters_make_equal_specs():
    spec = WorldSpec(**TINY, traffic=1, effects=["noise", "exposure", "noise"])
    same = WorldSpec(**TINY, traffic=1.0, effects=("exposure", "noise"))
    assert spec == same and hash(spec) == hash(same) and spec.effects == ("exposure", "noise")
    assert WorldSpec(effects="noise").effects == ("noise",)  # one effect alone, as a config may name it
    assert spec != WorldSpec(**TINY, traffic=1.0, effects=["exposure"])
    assert pickle.loads(pickle.dumps(spec)) == spec  # what the worker processes are given
    with pytest.raises(dataclasses.FrozenInstanceError):
        spec.seed = 1


@pytest.mark.parametrize(
    "spec",
    [
        WorldSpec(),
        WorldSpec("surround4", frames=30, size=64, seed=7, supersample=1, lane="left"),
        WorldSpec("stereo", scene="indoor", random_cameras=True, seed=3),
        WorldSpec(traffic=2.5, effects=["motion_blur", "vignetting"]),
    ],
)
def test_the_params_written_in_synthetic_json_read_back_to_the_spec(spec):
    written = spec.written()
    assert not any(k in written and written[k] == v for k, v in UNWRITTEN.items())  # defaults left out
    assert list(written)[:5] == ["seed", "rig", "size", "supersample", "frames"]
    assert WorldSpec.from_written(json.loads(json.dumps(written))) == spec
    assert spec.differences(json.loads(json.dumps(written))) == []


def test_the_street_with_fixed_cameras_writes_what_it_always_has():
    assert WorldSpec().written() == {
        "seed": 0,
        "rig": "kitti360",
        "size": 256,
        "supersample": 2,
        "frames": 200,
        "lane": "right",
    }


def test_differences_name_each_parameter_and_skip_what_a_record_lacks():
    finished = WorldSpec(**TINY, seed=1).written()
    assert WorldSpec(**{**TINY, "seed": 2, "size": 24}).differences(finished) == [
        "size 16 (asked 24)",
        "seed 1 (asked 2)",
    ]
    older = {k: v for k, v in finished.items() if k != "lane"}  # a record without the key is not compared
    assert WorldSpec(**TINY, seed=1, lane="left").differences(older) == []
    # a key left out because it had its UNWRITTEN value is compared with that value
    assert WorldSpec(**TINY, seed=1, traffic=0.5).differences(finished) == ["traffic 0 (asked 0.5)"]
    noise = WorldSpec(**TINY, seed=1, effects=["noise"])
    assert noise.differences(finished) == ["effects [] (asked ['noise'])"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A tiny dataset with traffic and an effect in the left lane, and its spec."""
    spec = WorldSpec(**TINY, seed=2, lane="left", traffic=1.0, effects=["noise"])
    return generate(tmp_path_factory.mktemp("spec") / "d", spec, **QUIET), spec


def test_a_rendered_dataset_records_its_spec(finished):
    root, spec = finished
    meta = json.loads((root / "synthetic.json").read_text())
    assert WorldSpec.from_written(meta) == spec
    assert {k: meta[k] for k in spec.written()} == spec.written()
    assert ensure_dataset(root, spec, **QUIET) == root


def test_a_dataset_asked_for_with_another_spec_is_refused(finished):
    root, spec = finished
    with pytest.raises(DatasetMismatch) as err:
        ensure_dataset(root, dataclasses.replace(spec, seed=3, effects=()), **QUIET)
    message = str(err.value)
    assert str(root) in message and "seed 2 (asked 3)" in message
    assert "effects ['noise'] (asked [])" in message
    assert "data.generate.*" in message and "traffic" not in message


def test_every_spec_of_a_config_is_made_before_anything_is_rendered(tmp_path):
    config = {**TINY, **QUIET, "worlds": [{"seed": 0}, {"rig": "fisheye"}]}
    with pytest.raises(ValueError, match="unknown rig 'fisheye'"):
        ensure_datasets([tmp_path / "a", tmp_path / "b"], config)
    assert list(tmp_path.iterdir()) == []


def test_generate_takes_a_spec_and_checks_how_it_renders(tmp_path):
    with pytest.raises(TypeError, match=r"^spec: 'kitti360' is not a WorldSpec$"):
        generate(tmp_path / "d", "kitti360")
    with pytest.raises(ValueError, match=r"^workers: -1 is not a whole number >= 0$"):
        generate(tmp_path / "d", WorldSpec(**TINY), workers=-1)
    with pytest.raises(ValueError, match=r"^lidar: 'no' is not a boolean"):
        ensure_dataset(tmp_path / "d", WorldSpec(**TINY), lidar="no")
    assert list(tmp_path.iterdir()) == [] and not is_complete(tmp_path / "d")
