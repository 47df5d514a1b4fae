"""Networks: ResNet fidelity and weight loading, heads, bin_expectation, PoseNet."""

from __future__ import annotations

import pytest
import torch

from fisheyedepth.geometry import invert_pose
from fisheyedepth.models import (
    PoseNet,
    ResNetEncoder,
    WeightsError,
    bin_expectation,
    bin_sums_conv,
    bin_sums_reduced,
    distance_bins,
    sigmoid_to_distance,
)

from conftest import bare_module, bare_net

# torchvision's resnet parameter counts minus the 1000-way fc layer
TORCHVISION_PARAMS = {18: 11_689_512 - 513_000, 34: 21_797_672 - 513_000, 50: 25_557_032 - 2_049_000}


@pytest.mark.parametrize("depth", [18, 34, 50])
def test_resnet_matches_torchvision_layout(depth):
    enc = ResNetEncoder(depth)
    assert sum(p.numel() for p in enc.parameters()) == TORCHVISION_PARAMS[depth]
    feats = enc(torch.rand(1, 3, 64, 96))
    assert [f.shape[1] for f in feats] == enc.channels
    assert [f.shape[-1] for f in feats] == [48, 24, 12, 6, 3]
    assert "layer4.1.bn2.running_var" in enc.state_dict() or depth == 50


def test_imagenet_weights_load_in_torchvision_layout(tmp_path):
    src = ResNetEncoder(18)
    state = dict(src.state_dict())
    state["fc.weight"], state["fc.bias"] = (
        torch.zeros(1000, 512),
        torch.zeros(1000),
    )  # as torchvision ships it
    path = tmp_path / "resnet18.pth"
    torch.save(state, path)
    loaded = ResNetEncoder(18, weights=path).eval()
    x = torch.rand(2, 3, 64, 64)
    assert all(torch.equal(a, b) for a, b in zip(src.eval()(x), loaded(x), strict=True))
    pose = ResNetEncoder(18, in_images=2, weights=path)
    assert torch.allclose(pose.conv1.weight, torch.cat([state["conv1.weight"]] * 2, 1) / 2)


def test_bad_weights_name_the_file_and_key(tmp_path):
    wrong_depth = tmp_path / "resnet34.pth"
    torch.save(ResNetEncoder(34).state_dict(), wrong_depth)
    with pytest.raises(WeightsError, match=r"resnet34.pth: key 'layer1.2"):
        ResNetEncoder(18, weights=wrong_depth)
    state = ResNetEncoder(18).state_dict()
    state["layer2.0.conv1.weight"] = torch.zeros(128, 64, 5, 5)
    bad_shape = tmp_path / "shape.pth"
    torch.save(state, bad_shape)
    with pytest.raises(WeightsError, match=r"shape.pth: key 'layer2.0.conv1.weight' has shape"):
        ResNetEncoder(18, weights=bad_shape)
    with pytest.raises(WeightsError, match="missing.pth"):
        ResNetEncoder(18, weights=tmp_path / "missing.pth")
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(WeightsError, match="junk.pth"):
        ResNetEncoder(18, weights=junk)


@pytest.mark.parametrize("multi_channel", [True, False])
def test_depth_net_shapes_ranges_and_gradients(multi_channel):
    net = bare_net(multi_channel=multi_channel, n_bins=16, min_distance=0.5, max_distance=150.0)
    image = torch.rand(2, 3, 64, 96)
    scale = torch.tensor([1.0, 2.5])
    out = net(image, scale)
    for s in (0, 1, 2, 3):
        d, disp = out["distance"][s], out["disp"][s]
        assert d.shape == disp.shape == (2, 1, 64 // 2**s, 96 // 2**s)
        assert (disp >= 0).all() and (disp <= 1).all()
        for b in range(2):
            assert (d[b] >= 0.5 * scale[b] - 1e-4).all() and (d[b] <= 150.0 * scale[b] * (1 + 1e-5)).all()
    sum(v.mean() for v in out["distance"].values()).backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert any(g.abs().sum() > 0 for g in grads)


def test_lite_variant_is_the_same_network_with_fewer_channels_and_bins(tmp_path):
    """``model=fisheyedepth_lite``: half the decoder's channels and 32 bins; a checkpoint of it loads
    back as itself (the width is a stored hyperparameter)."""
    from fisheyedepth.module import FisheyeDepthModule

    full = bare_module()
    lite = bare_module(net={"decoder_width": 0.5, "n_bins": 32})
    assert lite.depth_net.decoder.channels == (8, 16, 32, 64, 128)
    assert full.depth_net.decoder.channels == (16, 32, 64, 128, 256)
    assert lite.depth_net.heads["0"].logits[1].out_channels == 32

    def head_and_decoder(net):
        return sum(p.numel() for part in (net.decoder, net.heads) for p in part.parameters())

    assert head_and_decoder(lite.depth_net) < 0.4 * head_and_decoder(full.depth_net)
    out = lite.depth_net(torch.rand(1, 3, 64, 64), 1.0)
    assert out["distance"][0].shape == (1, 1, 64, 64) and torch.isfinite(out["distance"][0]).all()
    path = tmp_path / "lite.ckpt"
    torch.save({"state_dict": lite.state_dict(), "hyper_parameters": dict(lite.hparams)}, path)
    back = FisheyeDepthModule.from_checkpoint(path)
    assert back.depth_net.decoder.channels == (8, 16, 32, 64, 128)
    with pytest.raises(ValueError, match="decoder_width: 0"):
        bare_module(net={"decoder_width": 0})


def test_gather_output_is_a_monotone_expectation_within_the_bins():
    bins = distance_bins(64, 0.5, 150.0)
    assert bins[0].item() == pytest.approx(0.5) and bins[-1].item() == pytest.approx(150.0)
    assert torch.all(bins[1:] / bins[:-1] > 1)  # log-spaced, increasing
    # a peak moving to farther bins moves the distance monotonically
    peaks = torch.full((64, 64, 1, 1), -10.0)
    peaks[torch.arange(64), torch.arange(64)] = 10.0
    d, disp = bin_expectation(peaks, 1.0, bins, 0.5, 150.0)
    d = d.flatten()
    assert torch.all(d[1:] > d[:-1]) and torch.all(disp.flatten()[1:] < disp.flatten()[:-1])
    assert d[0].item() == pytest.approx(0.5, rel=1e-4) and d[-1].item() == pytest.approx(150.0, rel=1e-4)
    # raising one logit moves the expectation towards that bin
    logits = torch.randn(1, 64, 3, 3, generator=torch.Generator().manual_seed(0))
    base, _ = bin_expectation(logits, 1.0, bins, 0.5, 150.0)
    bumped = logits.clone()
    bumped[:, 63] += 1.0
    far, _ = bin_expectation(bumped, 1.0, bins, 0.5, 150.0)
    assert torch.all(far > base)
    scaled, _ = bin_expectation(logits, torch.tensor([2.0]), bins, 0.5, 150.0)
    assert torch.allclose(scaled, 2 * base)
    # huge logits are clamped: no overflow, finite gradients
    wild = (torch.randn(1, 64, 2, 2) * 1e4).requires_grad_(True)
    out, _ = bin_expectation(wild, 1.0, bins, 0.5, 150.0)
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(wild.grad).all()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("channels_last", [False, True])
@pytest.mark.parametrize("sums", [bin_sums_conv, bin_sums_reduced])
def test_fused_bin_expectation_equals_the_softmax_written_out(dtype, channels_last, sums):
    """The fused form (exp of the clamped logits, then the bin sums as one 1x1 convolution or as two
    channel reductions, the compiled training kernel's form) against the paper's
    ``sum_k softmax(l)_k b_k``: values and gradients, at the clamp's edges and beyond them."""
    bins = distance_bins(64, 0.5, 150.0).to(dtype)
    gen = torch.Generator().manual_seed(3)
    logits = torch.randn(2, 64, 5, 7, generator=gen, dtype=dtype) * 6.0  # many beyond +-10
    logits[0, :, 0, 0] = 10.0
    logits[0, :, 0, 1] = -10.0
    logits[1, 5, 2, 2] = 1e4
    if channels_last:
        logits = logits.contiguous(memory_format=torch.channels_last)
    a = logits.clone().requires_grad_(True)
    b = logits.clone().requires_grad_(True)
    fused, disp = bin_expectation(a, torch.tensor([1.0, 2.5]), bins, 0.5, 150.0, sums=sums)
    p = torch.softmax(b.clamp(-10.0, 10.0), dim=1)
    written = (p * bins[None, :, None, None]).sum(1, keepdim=True) * torch.tensor([1.0, 2.5]).to(
        dtype
    ).reshape(-1, 1, 1, 1)
    tol = 1e-6 if dtype == torch.float32 else 1e-13
    assert fused.dtype == dtype
    assert torch.allclose(fused, written, rtol=tol, atol=0)
    assert fused[0, 0, 0, 0].item() == pytest.approx(float(bins.mean()), rel=tol)  # equal logits: the mean
    assert torch.allclose(
        disp,
        (1 / (fused / torch.tensor([1.0, 2.5]).to(dtype).reshape(-1, 1, 1, 1)) - 1 / 150.0) / (2 - 1 / 150.0),
        rtol=1e-5,
    )
    weights = torch.rand(fused.shape, generator=gen, dtype=dtype)
    (fused * weights).sum().backward()
    (written * weights).sum().backward()
    grad_tol = (1e-4, 1e-5) if dtype == torch.float32 else (1e-10, 1e-12)  # (rtol, atol)
    assert torch.allclose(a.grad, b.grad, rtol=grad_tol[0], atol=grad_tol[1])
    assert a.grad[1, 5, 2, 2].item() == 0.0  # clamped: no gradient, as the softmax of the clamp


def test_bin_expectation_stays_float32_under_bf16_autocast():
    bins = distance_bins(64, 0.5, 150.0)
    logits = torch.randn(1, 64, 4, 4, generator=torch.Generator().manual_seed(0))
    exact, _ = bin_expectation(logits, 1.0, bins, 0.5, 150.0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        d, disp = bin_expectation(logits.bfloat16(), 1.0, bins, 0.5, 150.0)
    assert d.dtype == disp.dtype == torch.float32
    # only the logits were rounded to bf16 (8 bits of mantissa): the distance moves by well under 5 %
    assert ((d - exact).abs() / exact).max() < 0.05


def test_sigmoid_head_mapping():
    s = torch.tensor([0.0, 0.5, 1.0])
    d = sigmoid_to_distance(s, 0.1, 100.0)
    assert d[0].item() == pytest.approx(100.0) and d[2].item() == pytest.approx(0.1)
    assert 1 / d[1].item() == pytest.approx(0.5 * (1 / 0.1 + 1 / 100.0))


def test_posenet_outputs_rigid_motion_and_inverts_for_earlier_sources():
    torch.manual_seed(0)
    net = PoseNet().eval()
    a, b = torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64)
    T = net(a, b, source_is_earlier=False)
    R = T[:, :3, :3]
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3).expand(2, 3, 3), atol=1e-5)
    assert torch.equal(T[:, 3], torch.tensor([[0.0, 0, 0, 1]] * 2))
    # target b with an earlier source a sees the same frame pair (a, b): the inverse transform
    assert torch.allclose(net(b, a, source_is_earlier=True), invert_pose(T), atol=1e-6)


@pytest.mark.parametrize("bad", ["auto", 0.0, -3.0])
def test_base_focal_must_be_a_positive_focal_or_none(bad):
    with pytest.raises(ValueError, match=r"base_focal=.*expected a focal length in pixels > 0"):
        bare_net(base_focal=bad)


class _FixedLogits(torch.nn.Module):
    """A scale-0 head that ignores its input: the near bin on the left half, the far bin on the right."""

    def __init__(self, n_bins: int, near: int, far: int, size: int):
        super().__init__()
        logits = torch.full((1, n_bins, size, size), -10.0)
        logits[:, near, :, : size // 2] = 10.0
        logits[:, far, :, size // 2 :] = 10.0
        self.register_buffer("logits", logits)

    def forward(self, x):
        return self.logits.expand(x.shape[0], -1, -1, -1)


def test_upsampling_logits_keeps_edges_sharp_where_upsampling_distance_blends_them():
    """``upsample="logits"``: the expectation of the bilinearly upsampled logits, so a step from a near to
    a far surface stays a step (at most one column in between) where inverse-distance interpolation
    fills the columns near the edge with distances of neither surface; away from the edge both agree."""
    from fisheyedepth.cameras import MeiCamera

    camera = MeiCamera(width=256, height=256, xi=1.0, gamma1=160.0, gamma2=160.0, u0=128.0, v0=128.0)
    image = torch.rand(1, 3, 256, 256)
    results = {}
    for upsample in ("distance", "logits"):
        net = bare_net(scales=(0,), upsample=upsample).eval()
        net.heads["0"] = _FixedLogits(64, 10, 50, 64)
        with torch.no_grad():
            results[upsample] = net.distance(image, [camera], (64, 64))[0, 0]
    for d in results.values():  # a 4x upsampling: the edge at column 128 of 256
        assert d.shape == (256, 256)
        assert torch.allclose(d[:, :120], torch.full_like(d[:, :120], float(net.bins[10])), rtol=1e-3)
        assert torch.allclose(d[:, 136:], torch.full_like(d[:, 136:], float(net.bins[50])), rtol=1e-3)
    lo, hi = float(net.bins[10]) * 1.05, float(net.bins[50]) * 0.95
    between = {k: int(((d[0] > lo) & (d[0] < hi)).sum()) for k, d in results.items()}
    assert between["logits"] <= 1 and between["distance"] >= 3, between
    with pytest.raises(ValueError, match="upsample: 'nearest' is not one of distance, logits"):
        bare_net(upsample="nearest")
