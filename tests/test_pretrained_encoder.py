"""EfficientNet-Lite0 with the ImageNet weights of its installed package: it labels photographs (and does
not with its weights shuffled), its input normalisation is the better of two, and as the encoder of the
depth network and the PoseNet it runs, learns, exports to ONNX and loads from old checkpoints."""

from __future__ import annotations

import warnings

import pytest
import torch
from hydra import compose, initialize_config_dir
from skimage import data
from skimage.transform import resize

from fisheyedepth.checkpoints import network_differences
from fisheyedepth.config import configured_model
from fisheyedepth.inference import ExportableNet
from fisheyedepth.models import (
    DepthNet,
    EfficientNetLiteEncoder,
    PoseNet,
    ResNetEncoder,
    WeightsError,
    efficientnet,
)
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.runtimes import onnx_export, onnx_session

from conftest import ROOT, bare_module, bare_net

# scikit-image's photographs and the ImageNet classes that name them
PHOTOGRAPHS = {
    "chelsea": {281, 282, 283, 284, 285},  # tabby, tiger cat, Persian, Siamese, Egyptian cat
    "coffee": {967, 504, 968},  # espresso, coffee mug, cup
    "rocket": {657, 744, 812},  # missile, projectile, space shuttle
}


def centre_crop(image, size: int = 224) -> torch.Tensor:
    """``[3, size, size]`` in [0, 1]: the shorter side resized to ``size`` (anti-aliased), the centre cut."""
    h, w = image.shape[:2]
    scale = size / min(h, w)
    resized = resize(image, (round(h * scale), round(w * scale)), anti_aliasing=True)
    top, left = (resized.shape[0] - size) // 2, (resized.shape[1] - size) // 2
    crop = resized[top : top + size, left : left + size]
    return torch.from_numpy(crop).permute(2, 0, 1).float()


@pytest.fixture(scope="module")
def photographs() -> torch.Tensor:
    return torch.stack([centre_crop(getattr(data, name)()) for name in PHOTOGRAPHS])


@pytest.fixture(scope="module")
def classifier() -> EfficientNetLiteEncoder:
    return EfficientNetLiteEncoder(classifier=True).eval()


@pytest.fixture(scope="module")
def depth_net() -> DepthNet:
    return bare_net(encoder="efficientnet_lite0")


def probabilities(encoder: EfficientNetLiteEncoder, images: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return encoder.classify(images).softmax(1)


@pytest.fixture(scope="module")
def pretrained_probabilities(classifier, photographs) -> torch.Tensor:
    return probabilities(classifier, photographs)


def labelled(probs: torch.Tensor) -> dict[str, list[int]]:
    """Each photograph's top-5 classes, for those whose right class is among them."""
    top5 = probs.topk(5).indices.tolist()
    return {
        name: top for (name, right), top in zip(PHOTOGRAPHS.items(), top5, strict=True) if right & set(top)
    }


def test_the_imagenet_classifier_labels_the_photographs(pretrained_probabilities):
    assert sorted(labelled(pretrained_probabilities)) == sorted(PHOTOGRAPHS)


def test_with_shuffled_weights_it_labels_none_of_them(classifier, photographs):
    """The same network with every tensor's values permuted (a fixed generator): what the labels owe to
    the weights, not to the architecture or to chance."""
    generator = torch.Generator().manual_seed(0)
    state = {
        key: value.flatten()[torch.randperm(value.numel(), generator=generator)].view_as(value)
        if value.is_floating_point()
        else value
        for key, value in classifier.state_dict().items()
    }
    shuffled = EfficientNetLiteEncoder(classifier=True, pretrained=False)
    shuffled.load_state_dict(state)
    assert labelled(probabilities(shuffled.eval(), photographs)) == {}


def test_the_tf_lite_normalisation_beats_imagenet_mean_and_std(
    classifier, photographs, pretrained_probabilities, monkeypatch
):
    """The right classes are more probable with ``(255 x - 127) / 128`` (the encoder's) than with
    ImageNet's mean and std, on every photograph."""

    def right(probs: torch.Tensor) -> list[float]:
        return [float(p[list(classes)].sum()) for p, classes in zip(probs, PHOTOGRAPHS.values(), strict=True)]

    tf_lite = right(pretrained_probabilities)
    mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
    monkeypatch.setattr(efficientnet, "normalise", lambda x: (x - mean[:, None, None]) / std[:, None, None])
    imagenet = right(probabilities(classifier, photographs))
    assert all(a > b for a, b in zip(tf_lite, imagenet, strict=True)), (tf_lite, imagenet)


def test_tensorflow_same_padding(classifier):
    """``ceil(n / s)`` outputs; the smaller half of the padding before."""
    assert efficientnet.same_padding(224, 3, 2) == (0, 1)
    assert efficientnet.same_padding(224, 5, 2) == (1, 2)
    assert efficientnet.same_padding(7, 5, 2) == (2, 2)
    assert efficientnet.same_padding(56, 5, 1) == (2, 2)
    with torch.no_grad():
        features = classifier(torch.rand(1, 3, 70, 98))
    assert [f.shape[-2:] for f in features] == [(35, 49), (18, 25), (9, 13), (5, 7), (3, 4)]


def test_depth_net_carries_the_packaged_weights_without_the_classifier(depth_net):
    encoder = depth_net.encoder
    assert isinstance(encoder, EfficientNetLiteEncoder) and encoder.channels == [16, 24, 40, 112, 320]
    packaged = torch.load(efficientnet.packaged_weights(), map_location="cpu", weights_only=True)
    own = encoder.state_dict()
    assert len(own) == len(packaged) - 8  # _conv_head (1), _bn1 (5) and _fc (2) left out
    assert all(torch.equal(value, packaged[key]) for key, value in own.items())


@pytest.mark.parametrize("size", [(160, 160), (192, 320)])
def test_depth_net_on_the_pretrained_encoder_runs_and_learns(depth_net, size):
    """Every scale at its size, positive finite distances; at 160x160 also a backward pass, which reaches
    every encoder weight."""
    h, w = size
    learn = size == (160, 160)
    depth_net.train(learn).zero_grad()
    with torch.set_grad_enabled(learn):
        out = depth_net(torch.rand(1, 3, h, w), torch.tensor([1.5]))
    for s in (0, 1, 2, 3):
        assert out["distance"][s].shape == out["disp"][s].shape == (1, 1, h // 2**s, w // 2**s)
        assert torch.isfinite(out["distance"][s]).all() and (out["distance"][s] > 0).all()
    if learn:
        sum(d.mean() for d in out["distance"].values()).backward()
        grads = [p.grad for p in depth_net.encoder.parameters()]
        assert all(g is not None and torch.isfinite(g).all() for g in grads)
        assert depth_net.encoder._conv_stem.weight.grad.abs().sum() > 0


def test_posenet_on_the_pretrained_encoder_gives_poses():
    net = PoseNet(encoder="efficientnet_lite0").eval()
    packaged = torch.load(efficientnet.packaged_weights(), map_location="cpu", weights_only=True)
    stem = packaged["_conv_stem.weight"]
    assert torch.allclose(net.encoder._conv_stem.weight, torch.cat([stem, stem], 1) / 2)
    target, source = torch.rand(2, 3, 64, 96), torch.rand(2, 3, 64, 96)
    with torch.no_grad():
        T = net(target, source, source_is_earlier=True)
    assert T.shape == (2, 4, 4) and torch.isfinite(T).all()
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-5)
    assert torch.equal(T[:, 3], torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 2))


def test_wrong_weights_name_the_file_and_the_key(tmp_path):
    resnet = tmp_path / "resnet18.pth"
    torch.save(ResNetEncoder(18).state_dict(), resnet)
    with pytest.raises(WeightsError, match=r"resnet18.pth: key '_blocks\.0\._bn1\.bias' missing"):
        EfficientNetLiteEncoder(pretrained=resnet)
    with pytest.raises(WeightsError, match=r"resnet18.pth: key '_blocks"):  # threaded through DepthNet
        bare_net(encoder="efficientnet_lite0", weights=resnet)
    state = torch.load(efficientnet.packaged_weights(), map_location="cpu", weights_only=True)
    state["_blocks.3._depthwise_conv.weight"] = torch.zeros(144, 1, 3, 3)
    torch.save(state, tmp_path / "reshaped.pth")
    with pytest.raises(
        WeightsError, match=r"reshaped.pth: key '_blocks\.3\._depthwise_conv\.weight' has shape"
    ):
        EfficientNetLiteEncoder(pretrained=tmp_path / "reshaped.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a state dict")
    with pytest.raises(WeightsError, match="junk.pth: cannot read"):
        EfficientNetLiteEncoder(pretrained=tmp_path / "junk.pth")
    with pytest.raises(ValueError, match="encoder: 'vgg' is not one of resnet, efficientnet_lite0"):
        bare_net(encoder="vgg")


def test_onnx_export_matches_torch(depth_net):
    pytest.importorskip("onnxruntime")
    net = ExportableNet(depth_net, 1.0).eval()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        exported = onnx_session(onnx_export(net, (64, 96), None), threads=2)
    # the "SAME" padding is read from the traced size on purpose (constant at the export size), quietly
    assert not [w for w in caught if "Python integer" in str(w.message)]
    image = torch.rand(2, 3, 96, 64, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        expected = net(image)
    got = torch.from_numpy(exported.run(None, {"image": image.numpy()})[0])
    assert got.shape == expected.shape == (2, 1, 96, 64)
    assert float(((got - expected).abs() / expected).max()) < 1e-4


def test_the_effnet_model_config_builds_both_networks_on_it():
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["model=fisheyedepth_effnet"])
    options = configured_model(cfg)
    assert options["net"]["encoder"] == "efficientnet_lite0"
    module = bare_module(net={"encoder": "efficientnet_lite0"}, objective={"real_scale": False})
    assert isinstance(module.depth_net.encoder, EfficientNetLiteEncoder)
    assert isinstance(module.pose_net.encoder, EfficientNetLiteEncoder)
    assert module.pose_net.encoder._conv_stem.in_channels == 6


def test_a_checkpoint_from_before_the_encoder_option_loads_as_a_resnet(tmp_path):
    module = bare_module(net={"scales": [0], "decoder_width": 0.25})
    hparams = dict(module.hparams)
    hparams["net"] = {k: v for k, v in hparams["net"].items() if k != "encoder"}
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": hparams}, tmp_path / "old.ckpt")
    loaded = FisheyeDepthModule.from_checkpoint(tmp_path / "old.ckpt")
    assert loaded.hparams.net["encoder"] == "resnet"
    assert isinstance(loaded.depth_net.encoder, ResNetEncoder)
    configured = FisheyeDepthModule.options(
        net={"scales": [0], "decoder_width": 0.25, "encoder": "efficientnet_lite0"}
    )
    assert network_differences(hparams, configured) == [
        "model.net.encoder is efficientnet_lite0 here, resnet in the checkpoint"
    ]
