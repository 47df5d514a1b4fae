"""Losses: SSIM/L1 photometric error, minimum reprojection with auto-masking, smoothness."""

from __future__ import annotations

import pytest
import torch

from fisheyedepth.losses import (
    INVALID_WARP_ERROR,
    ReprojectionLoss,
    automasked_error,
    box_mean3,
    edge_aware_smoothness,
    min_reprojection,
    photometric_error,
    ssim,
)


def textured(seed=0, shape=(1, 3, 16, 16)):
    return torch.rand(shape, generator=torch.Generator().manual_seed(seed))


def test_ssim_and_photometric_error():
    x = textured()
    assert torch.allclose(ssim(x, x), torch.ones_like(x), atol=1e-6)
    assert torch.allclose(photometric_error(x, x), torch.zeros(1, 16, 16), atol=1e-6)
    # a constant offset leaves local structure intact: the L1 term dominates
    err = photometric_error(x + 0.1, x)
    assert err.mean().item() == pytest.approx(0.15 * 0.1, abs=0.01)
    y = textured(1)
    assert photometric_error(y, x).mean() > 5 * err.mean()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_box_mean3_is_avg_pool_forward_and_backward(dtype):
    x = textured(2, (2, 5, 11, 9)).to(dtype).requires_grad_()
    ref = torch.nn.functional.avg_pool2d(x, 3, 1)
    out = box_mean3(x)
    tol = 1e-6 if dtype == torch.float32 else 1e-12
    assert out.shape == (2, 5, 9, 7) and torch.allclose(out, ref, atol=tol)
    weights = torch.rand_like(ref)
    (g_ref,) = torch.autograd.grad((ref * weights).sum(), x)
    (g_out,) = torch.autograd.grad((out * weights).sum(), x)
    assert torch.allclose(g_out, g_ref, atol=tol)
    assert g_ref[0, 0, 0, 0] == pytest.approx(float(weights[0, 0, 0, 0]) / 9)  # a corner sits in one window


def test_min_reprojection_picks_the_best_valid_source_and_automasks():
    reproj = torch.tensor([[[[0.5, 0.2]], [[0.1, 0.3]]]])  # [B=1, S=2, H=1, W=2]
    valid = torch.tensor([[[[True, True]], [[False, True]]]])
    loss, used = min_reprojection(reproj, valid)
    assert torch.allclose(loss, torch.tensor([[[0.5, 0.2]]])) and bool(used.all())
    none_valid = torch.zeros_like(valid)
    loss, used = min_reprojection(reproj, none_valid)  # no warp reaches: the worst error, not zero
    assert not bool(used.any()) and torch.equal(loss, torch.full_like(loss, INVALID_WARP_ERROR))
    identity = torch.tensor([[[[0.4, 0.9]], [[0.6, 0.9]]]])  # unwarped source 0 explains pixel 0 better
    loss, used = min_reprojection(reproj, valid, identity, noise=0.0)
    assert used.tolist() == [[[False, True]]]
    assert torch.allclose(loss, torch.tensor([[[0.4, 0.2]]]))  # pixel 0 costs its unwarped error
    loss, used = min_reprojection(reproj, none_valid, identity, noise=0.0)  # unreachable: unwarped error
    assert torch.allclose(loss, torch.tensor([[[0.4, 0.9]]])) and not bool(used.any())
    loss, used = min_reprojection(reproj, none_valid, identity, automask=False)  # ... with or without masking
    assert torch.allclose(loss, torch.tensor([[[0.4, 0.9]]])) and not bool(used.any())
    loss, used = min_reprojection(reproj, valid, identity, automask=False)  # reachable: the warp, however bad
    assert torch.allclose(loss, torch.tensor([[[0.5, 0.2]]])) and bool(used.all())


def test_reprojection_loss_counts_every_usable_pixel():
    """The mean runs over the usable pixels (mask), whatever the warps do: a masked pixel never counts,
    an unreachable one always does, at the worst error, so pushing warps out of the image never pays."""
    torch.manual_seed(0)
    target = textured(0, (1, 3, 8, 8))
    good = target.clone() + 0.05
    warped = torch.stack((good, good), 1)
    sources = torch.stack((textured(3, (1, 3, 8, 8)), textured(4, (1, 3, 8, 8))), 1)
    valid = torch.ones(1, 2, 8, 8, dtype=torch.bool)
    mask = torch.ones(1, 8, 8, dtype=torch.bool)
    fn = ReprojectionLoss(automask=False)
    full, frac, _ = fn(target, warped, valid, fn.identity(sources, target), mask)
    assert frac.item() == 1.0
    good_error = photometric_error(good, target)
    assert full.item() == pytest.approx(good_error.mean().item(), rel=1e-5)
    # a masked half with huge errors changes nothing: the mean is over the unmasked half
    bad = warped.clone()
    bad[..., 4:, :] = 10.0
    mask2 = mask.clone()
    mask2[:, 4:] = False
    half, frac2, _ = fn(target, bad, valid, None, mask2)
    assert frac2.item() == 1.0
    bad_error = photometric_error(bad[:, 0], target)  # SSIM's 3x3 window sees the bad rows from row 3
    assert half.item() == pytest.approx(bad_error[:, :4].mean().item(), rel=1e-5)
    # invalid warps on the lower half: those pixels still count, at the worst error (no unwarped errors
    # given) or at their unwarped error, with no gradient
    valid2 = valid.clone()
    valid2[..., 4:, :] = False
    warped_grad = bad.clone().requires_grad_(True)
    again, frac3, _ = fn(target, warped_grad, valid2, None, mask)
    assert frac3.item() == 0.5
    assert again.item() == pytest.approx(
        (bad_error[:, :4].sum().item() + 32 * INVALID_WARP_ERROR) / 64, rel=1e-5
    )
    assert again.item() > full.item()  # leaving the image costs more than a decent warp
    again.backward()
    assert warped_grad.grad[..., 5:, :].abs().max().item() == 0.0  # row 4 is in row 3's SSIM window
    ident = fn.identity(sources, target)
    unwarped, _, _ = fn(target, bad, valid2, ident, mask)
    expected = bad_error.clone()
    expected[:, 4:] = ident.min(1).values[:, 4:]
    assert unwarped.item() == pytest.approx(expected.mean().item(), rel=1e-5)
    # with auto-masking the unwarped error also wins wherever it is lower
    fn_auto = ReprojectionLoss(automask=True)
    masked, _, measured = fn_auto(target, bad, valid2, ident, mask)
    expected = torch.minimum(bad_error, ident.min(1).values)
    expected[:, 4:] = ident.min(1).values[:, 4:]
    assert masked.item() == pytest.approx(expected.mean().item(), abs=1e-4)  # 1e-5 tie-breaking noise
    assert measured.item() == pytest.approx(expected.mean().item(), rel=1e-5)


def test_edge_aware_smoothness():
    image = torch.zeros(1, 3, 8, 8)
    flat = torch.full((1, 1, 8, 8), 0.3)
    assert edge_aware_smoothness(flat, image).item() == pytest.approx(0.0, abs=1e-7)
    ramp = torch.linspace(0.1, 1, 8).reshape(1, 1, 1, 8).expand(1, 1, 8, 8)
    s = edge_aware_smoothness(ramp, image)
    assert s > 0
    assert edge_aware_smoothness(ramp * 7, image).item() == pytest.approx(
        s.item(), rel=1e-5
    )  # mean-normalised
    edges = image.clone()
    edges[..., ::2] = 1.0  # image gradients everywhere along x damp the x term
    assert edge_aware_smoothness(ramp, edges) < s


def test_automasked_error_only_falls_as_warps_improve():
    """The validation criterion: the mean of min(best warp, best unwarped source) over the usable pixels;
    a better warp never raises it."""
    rep = torch.tensor([[[[0.5, 0.5], [0.5, 0.5]]]])  # [B=1, S=1, 2, 2]
    ident = torch.full_like(rep, 0.3)
    valid = torch.ones_like(rep, dtype=torch.bool)
    mask = torch.ones(1, 2, 2, dtype=torch.bool)
    assert automasked_error(rep, valid, ident, mask).item() == pytest.approx(0.3)  # identity wins everywhere
    better = rep.clone()
    better[..., 0, 0] = 0.1  # one pixel now warps well: the error falls
    assert automasked_error(better, valid, ident, mask).item() == pytest.approx((0.1 + 3 * 0.3) / 4)
    both = better.clone()
    both[..., 0, 1] = 0.29  # a second pixel won narrowly: it falls again
    assert automasked_error(both, valid, ident, mask) < automasked_error(better, valid, ident, mask)
    invalid = torch.zeros_like(valid)
    assert automasked_error(rep, invalid, None, mask).item() == pytest.approx(INVALID_WARP_ERROR)
    assert (
        automasked_error(rep, valid, None, torch.zeros_like(mask)).item() == 0.0
    )  # nothing usable: 0, not NaN
