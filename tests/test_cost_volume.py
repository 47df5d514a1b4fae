"""The multi-view network's cost volume: matching over metric distance with fisheye warps, and the depth
network reading it (``net.cost_volume``)."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from fisheyedepth.cameras import PinholeCamera
from fisheyedepth.cli.export import export
from fisheyedepth.geometry.se3 import invert_pose
from fisheyedepth.models import DepthNet
from fisheyedepth.models.cost_volume import CostVolume, Sources, inverse_distances
from fisheyedepth.module import FisheyeDepthModule
from fisheyedepth.runtimes import TorchRuntime
from stereo_world import pose, render, texture_volume
from test_faults_export import export_cfg

from conftest import bare_module, bare_net, kitti02, tiny_batch, train_few_steps


def patches(image: torch.Tensor, window: int = 5) -> torch.Tensor:
    """``[B, window**2, H, W]``: each pixel's neighbourhood as channels (the L1 over them is a SAD)."""
    r = window // 2
    return F.unfold(F.pad(image, (r, r, r, r), mode="replicate"), window).reshape(
        image.shape[0], window * window, *image.shape[-2:]
    )


def test_hypotheses_are_uniform_in_inverse_distance_nearest_first():
    inverse = inverse_distances(5, 0.5, 80.0)
    assert inverse[0] == pytest.approx(2.0) and inverse[-1] == pytest.approx(1 / 80)
    assert torch.allclose(inverse.diff(), torch.full((4,), (1 / 80 - 2.0) / 4))


def rig_volume(baseline_scale: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, CostVolume]:
    """The raw volume's winner (5x5 patches as features, no aggregation) ``[1, H, W]`` metres, the
    truth and the volume, for two KITTI-360 fisheyes 0.6 m apart and turned 30 degrees in a room with
    exact distance (a coarse texture, so that 96 px do not alias it); the baseline told to the volume is
    ``baseline_scale`` times the true one."""
    camera = kitti02().resize(96, 96)
    volume = texture_volume(0, cell=0.25)
    T_a, T_b = pose(), pose(30.0, (0.6, 0.0, 0.0))
    (image_a, truth), (image_b, _) = render(camera, T_a, volume), render(camera, T_b, volume)
    T = (invert_pose(T_b) @ T_a).float()
    T[:3, 3] *= baseline_scale
    cost = CostVolume(64, 0.5, 20.0)
    out = cost(patches(image_a), patches(image_b)[:, None], T[None, None], [camera], [[camera]])
    assert out.shape == (1, 65, 96, 96)
    fraction = out[:, -1]
    assert 0.5 < float(fraction[truth > 0].mean()) < 1.0  # the partner sees part of each ray
    winner = 1 / cost.inverse[out[:, :-1].argmin(1)]
    return torch.where(fraction == 1, winner, torch.zeros_like(winner)), truth, cost


def test_the_cost_is_lowest_at_the_true_distance_on_a_fisheye_rig():
    winner, truth, _ = rig_volume()
    kept = (truth > 0) & (winner > 0)
    ratio = winner[kept] / truth[kept]
    assert kept.sum() > 4000
    assert float((torch.maximum(ratio, 1 / ratio) < 1.25).float().mean()) > 0.9
    assert float((ratio - 1).abs().median()) < 0.04


def test_the_volume_is_metric_through_the_poses():
    """Told twice the baseline, the same images match at twice the distance: the scale is the poses'."""
    winner, truth, _ = rig_volume(baseline_scale=2.0)
    kept = (truth > 0) & (winner > 0) & (truth < 8.0)  # twice that stays inside the 20 m range
    assert float((winner[kept] / truth[kept]).median()) == pytest.approx(2.0, rel=0.06)


def test_hypotheses_no_source_sees_take_the_mean_and_are_counted():
    """A pinhole source at the same place turned round sees nothing of the target's view: every
    hypothesis is unseen, the fraction channel is 0 and the cost the fill value, not a NaN."""
    camera = PinholeCamera(width=32, height=32, fx=20.0, fy=20.0, cx=15.5, cy=15.5)
    turned = pose(180.0, (0.0, 0.0, 0.0)).float()
    features = torch.rand(1, 4, 32, 32)
    out = CostVolume(8, 0.5, 20.0)(features, features[:, None], turned[None, None], [camera], [[camera]])
    assert torch.isfinite(out).all()
    assert (out[:, -1] == 0).all() and (out[:, :-1] == 0).all()


def test_bad_volume_settings_are_refused():
    with pytest.raises(ValueError, match="hypotheses 1"):
        CostVolume(1)
    with pytest.raises(ValueError, match="min_distance < max_distance"):
        CostVolume(8, 10.0, 5.0)


# ------------------------------------------------------------------ the network
@pytest.fixture(scope="module")
def batch(kitti_data):
    return tiny_batch(kitti_data)


def mv_net(**options) -> DepthNet:
    torch.manual_seed(0)
    return bare_net(scales=(0, 1), cost_volume=8, base_focal=None, channels_last=False, **options)


def test_without_sources_the_network_reads_an_empty_volume(batch):
    net = mv_net().eval()
    none = net.for_cameras(batch.image, batch.camera)["distance"][0]
    empty = Sources(batch.sources[:, :0], batch.poses[:, :0], [[] for _ in batch.camera])
    assert torch.equal(none, net.for_cameras(batch.image, batch.camera, sources=empty)["distance"][0])
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    with_sources = net.for_cameras(batch.image, batch.camera, sources=sources)["distance"][0]
    assert (with_sources - none).abs().max() > 1e-4  # the matches change the map
    assert torch.isfinite(with_sources).all() and (with_sources > 0).all()


def test_the_volume_joins_the_encoder_map_at_its_stride(batch):
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    for stride, channels in ((2, 64), (4, 64)):
        net = mv_net(cost_volume_stride=stride).eval()
        with torch.no_grad():
            level = net.encoder.stage(0, batch.image)
            if stride == 4:
                level = net.encoder.stage(1, level)
            volume = net.match(level, batch.camera, sources)
        assert level.shape[1] == channels and volume.shape == (4, 9, 64 // stride, 64 // stride)
        assert 0 < float(volume[:, -1].mean()) <= 1  # the sources see most hypotheses
    with pytest.raises(ValueError, match="cost_volume_stride: 8"):
        mv_net(cost_volume_stride=8)


def test_the_network_volume_spans_its_own_range():
    net = mv_net(cost_volume_min=1.5, cost_volume_max=60.0)
    assert net.cost_volume.inverse[0] == pytest.approx(1 / 1.5) and net.cost_volume.inverse[
        -1
    ] == pytest.approx(1 / 60)
    assert net.min_distance == 0.5  # the head's range is its own


def test_a_residual_volume_changes_nothing_at_the_start(batch):
    """``cost_volume_fusion: residual``: the correction starts at zero, so the pretrained deeper stages
    first see the features they were trained on; ``replace`` passes a fresh map on instead."""
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    for fusion, same in (("residual", True), ("replace", False)):
        net = mv_net(cost_volume_fusion=fusion).eval()
        with torch.no_grad():
            matched = net.for_cameras(batch.image, batch.camera, sources=sources)["distance"][0]
            alone = net.for_cameras(batch.image, batch.camera)["distance"][0]
            features = net.encoder.stage(1, net.encoder.stage(0, batch.image))
            fused = net.encode(batch.image, batch.camera, sources)[1]
        assert torch.equal(matched, alone) == same and torch.equal(fused, features) == same
    with pytest.raises(ValueError, match="cost_volume_fusion: 'sum'"):
        mv_net(cost_volume_fusion="sum")


def test_sources_dropped_in_training_leave_the_image_alone(batch):
    """``source_dropout`` 1: every sample's volume is withheld, as without sources (train mode both)."""
    net = mv_net(source_dropout=1.0).train()
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    dropped = net.for_cameras(batch.image, batch.camera, sources=sources)["distance"][0]
    alone = net.for_cameras(batch.image, batch.camera)["distance"][0]
    assert torch.allclose(dropped, alone)


def test_gradients_reach_the_matching_features(batch):
    net = mv_net(source_dropout=0.0).train()
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    net.for_cameras(batch.image, batch.camera, sources=sources)["distance"][0].mean().backward()
    assert net.fuse[0].weight.grad.abs().sum() > 0
    volume_weights = net.fuse[0].weight.grad[:, net.encoder.channels[1] :]
    assert volume_weights.abs().sum() > 0  # the cost channels are read


def test_the_encoder_in_stages_is_the_encoder_layer_by_layer():
    """The stages the cost volume joins between are the encoders' layers in order: ResNet's stem,
    max-pool + layer1, layer2-4; EfficientNet-Lite0's stem and the blocks up to each tap."""
    from fisheyedepth.models.efficientnet import TAPS

    torch.manual_seed(0)
    image = torch.rand(1, 3, 64, 64)
    resnet = bare_net(encoder="resnet", channels_last=False).eval().encoder
    x = resnet.relu(resnet.bn1(resnet.conv1((image - 0.45) / 0.225)))
    expected = [x, resnet.layer1(resnet.maxpool(x))]
    for layer in (resnet.layer2, resnet.layer3, resnet.layer4):
        expected.append(layer(expected[-1]))
    effnet = bare_net(encoder="efficientnet_lite0", channels_last=False).eval().encoder
    h, taps = effnet.stem(image), []
    for i, block in enumerate(effnet._blocks):
        h = block(h)
        if i in TAPS:
            taps.append(h)
    for encoder, reference in ((resnet, expected), (effnet, taps)):
        with torch.no_grad():
            features, x = encoder(image), image
            for k in range(5):
                x = encoder.stage(k, x)
                assert torch.equal(x, reference[k]) and torch.equal(features[k], reference[k])
                assert x.shape[1] == encoder.channels[k] and x.shape[-1] == 64 // 2 ** (k + 1)


def test_the_volume_needs_metric_poses():
    with pytest.raises(ValueError, match="net.cost_volume.*real_scale"):
        bare_module(net={"cost_volume": 8}, objective={"real_scale": False})


def test_a_module_with_a_volume_reads_the_batch_sources(batch):
    module = bare_module(net={"cost_volume": 8, "scales": (0, 1), "base_focal": 20.0})
    assert bare_module(net={"scales": (0, 1)}).sources(batch) is None
    sources = module.sources(batch, augmented=True)
    assert sources.images is batch.sources_aug and sources.poses is batch.poses
    loss, _ = module.objective(batch, module(batch.image, batch.camera, sources))
    assert math.isfinite(float(loss.detach()))


@pytest.fixture(scope="module")
def mv_checkpoint(kitti_data, tmp_path_factory):
    path = tmp_path_factory.mktemp("mv") / "mv.ckpt"
    train_few_steps(kitti_data, path, cost_volume=8)
    return path


def test_a_multiview_checkpoint_runs_with_its_sources_and_refuses_what_cannot_take_them(
    mv_checkpoint, batch, tmp_path
):
    runtime = TorchRuntime(FisheyeDepthModule.from_checkpoint(mv_checkpoint))
    assert runtime.sources == ((-1, 1), ())  # the frames its loss warped: what evaluation reads
    sources = Sources(batch.sources, batch.poses, batch.source_camera)
    matched, alone = (
        runtime.distance(batch.image, batch.camera, sources),
        runtime.distance(batch.image, batch.camera),
    )
    assert matched.shape == alone.shape == (4, 1, 64, 64) and (matched - alone).abs().max() > 1e-4
    with pytest.raises(ValueError, match="post_process: 'flip'.*sources"):
        TorchRuntime(FisheyeDepthModule.from_checkpoint(mv_checkpoint), post_process="flip")
    with pytest.raises(ValueError, match="net.cost_volume.*export a monocular checkpoint"):
        export(export_cfg(mv_checkpoint, tmp_path / "mv.onnx"))
    assert not (tmp_path / "mv.onnx").exists()


def test_predicting_single_images_with_a_multiview_checkpoint_says_so(mv_checkpoint, batch, caplog):
    """predict.py has no source frames: the multi-view network runs in its one-image mode, and says so."""
    from fisheyedepth.inference import DistancePredictor

    with caplog.at_level("WARNING", logger="fisheyedepth.inference"):
        predictor = DistancePredictor(FisheyeDepthModule.from_checkpoint(mv_checkpoint), batch.camera[0])
    assert "multi-view checkpoint" in caplog.text and "without the source frames" in caplog.text
    distance = predictor(batch.image[:1])
    assert distance.shape == (1, 1, 64, 64) and (distance[torch.isfinite(distance)] > 0).all()
    caplog.clear()
    with caplog.at_level("WARNING", logger="fisheyedepth.inference"):
        DistancePredictor(bare_module(net={"scales": (0, 1)}, input_size=(64, 64)), batch.camera[0])
    assert "multi-view" not in caplog.text
