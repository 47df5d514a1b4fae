"""The model's options have one source of defaults, its YAML: the classes declare their keywords, the YAML
gives every one of them a value, and what the code fills in is what Hydra composes."""

from __future__ import annotations

import inspect
import json

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from fisheyedepth.losses.objective import SelfSupervisedObjective
from fisheyedepth.models import DepthNet
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.options import defaults as options
from fisheyedepth.options.defaults import CONF_DIR, keywords, model_defaults, model_options, net_options


def keyword_defaults(cls) -> dict[str, object]:
    params = inspect.signature(cls.__init__).parameters.values()
    return {p.name: p.default for p in params if p.kind is p.KEYWORD_ONLY}


def test_every_keyword_of_the_classes_is_in_the_yaml_and_none_has_a_default_of_its_own():
    net, objective = keyword_defaults(DepthNet), keyword_defaults(SelfSupervisedObjective)
    defaults = model_defaults()
    assert set(net) == set(defaults["net"])
    # the objective's scales are the network's; its PoseNet is an object, not an option; the PoseNet's
    # translation scale is the module's to pass to the PoseNet
    assert set(objective) - {"scales", "pose_net"} == set(defaults["objective"]) - {"pose_translation_scale"}
    given = {k: v for k, v in {**net, **objective}.items() if v is not inspect.Parameter.empty}
    assert given == {"pose_net": None}


def test_the_defaults_are_what_hydra_composes_for_the_model():
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["model=fisheyedepth"])
    composed = OmegaConf.to_container(cfg.model, resolve=True)
    composed.pop("_target_")
    assert composed.pop("input_size") == list(cfg.data.datamodule.size)  # the entry point's to fill
    defaults = model_defaults()
    assert defaults.pop("input_size") is None
    assert json.loads(json.dumps(defaults)) == composed  # its lists as tuples
    assert defaults["net"]["scales"] == (0, 1, 2, 3) and defaults["eval_cap"] == (0.001, 80.0)
    assert defaults["optimizer"]["lr"] == 3e-4 and defaults["scheduler"]["step_size"] == 5  # the YAML's
    assert set(keywords()) == set(composed) | {"input_size"}


def test_given_options_go_over_the_yaml_key_by_key_and_a_class_of_its_own_replaces_the_group():
    sgd = {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 0.1}
    out = model_options(net={"n_bins": 16}, optimizer=sgd, log_images_every=0)
    assert out["net"] == model_defaults()["net"] | {"n_bins": 16}
    assert out["optimizer"] == sgd and out["log_images_every"] == 0
    assert net_options(encoder="resnet")["n_bins"] == 64
    out["net"]["n_bins"] = 3  # a copy: the next caller gets the YAML again
    assert model_defaults()["net"]["n_bins"] == 64


def test_a_network_built_without_training_cameras_names_its_base_focal():
    with pytest.raises(ValueError, match="base_focal='auto'.*resolved from the training cameras"):
        DepthNet(**net_options())
    with pytest.raises(TypeError, match="FisheyeDepthModule: unexpected learning_rate"):
        FisheyeDepthModule(learning_rate=1e-3)


def test_an_unreadable_yaml_is_named(tmp_path, monkeypatch):
    bad = tmp_path / "fisheyedepth.yaml"
    bad.write_text("net: [unclosed\n")
    monkeypatch.setattr(options, "MODEL_CONFIG", bad)
    options._defaults.cache_clear()
    try:
        with pytest.raises(FileNotFoundError, match=f"{bad}: the model's default options cannot be read"):
            model_defaults()
        bad.write_text("net: {}\nobjective: {}\n")
        with pytest.raises(ValueError, match=f"{bad}: no optimizer, scheduler group of options"):
            model_defaults()
    finally:
        options._defaults.cache_clear()
