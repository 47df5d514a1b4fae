"""Losses: SSIM/L1 photometric error, minimum reprojection with auto-masking, smoothness."""

from __future__ import annotations

import pytest
import torch

from fisheyedepth.losses import (
    ReprojectionLoss,
    automasked_error,
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


def test_min_reprojection_picks_the_best_valid_source_and_automasks():
    reproj = torch.tensor([[[[0.5, 0.2]], [[0.1, 0.3]]]])  # [B=1, S=2, H=1, W=2]
    valid = torch.tensor([[[[True, True]], [[False, True]]]])
    loss, used = min_reprojection(reproj, valid)
    assert torch.allclose(loss, torch.tensor([[[0.5, 0.2]]])) and bool(used.all())
    none_valid = torch.zeros_like(valid)
    loss, used = min_reprojection(reproj, none_valid)
    assert not bool(used.any()) and torch.equal(loss, torch.zeros_like(loss))
    identity = torch.tensor([[[[0.4, 0.9]], [[0.6, 0.9]]]])  # unwarped source 0 explains pixel 0 better
    loss, used = min_reprojection(reproj, valid, identity)
    assert used.tolist() == [[[False, True]]]


def test_reprojection_loss_is_normalised_by_used_pixels_only():
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
    assert full.item() == pytest.approx(photometric_error(good, target).mean().item(), rel=1e-5)
    # a masked half with huge errors changes neither the value nor anything but the fraction
    bad = warped.clone()
    bad[..., 4:, :] = 10.0
    mask2 = mask.clone()
    mask2[:, 4:] = False
    half, frac2, _ = fn(target, bad, valid, None, mask2)
    assert frac2.item() == 0.5
    assert half.item() == pytest.approx(photometric_error(bad[:, 0], target)[:, :4].mean().item(), rel=1e-5)
    # invalid warps do not count either
    valid2 = valid.clone()
    valid2[..., 4:, :] = False
    again, frac3, _ = fn(target, bad, valid2, None, mask)
    assert frac3.item() == 0.5 and again.item() == pytest.approx(half.item(), rel=1e-6)


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
    """The validation criterion: the mean of min(best warp, best unwarped source) over the usable pixels.
    Unlike the training loss (normalised by the pixels the warps win), a better warp never raises it."""
    rep = torch.tensor([[[[0.5, 0.5], [0.5, 0.5]]]])  # [B=1, S=1, 2, 2]
    ident = torch.full_like(rep, 0.3)
    valid = torch.ones_like(rep, dtype=torch.bool)
    mask = torch.ones(1, 2, 2, dtype=torch.bool)
    assert automasked_error(rep, valid, ident, mask).item() == pytest.approx(0.3)  # identity wins everywhere
    better = rep.clone()
    better[..., 0, 0] = 0.1  # one pixel now warps well: the error falls ...
    assert automasked_error(better, valid, ident, mask).item() == pytest.approx((0.1 + 3 * 0.3) / 4)
    # ... while the training loss, normalised by the pixels the warp wins, says 0.1 for one pixel;
    # a second pixel that the warp wins narrowly raises the training loss but lowers the error
    both = better.clone()
    both[..., 0, 1] = 0.29
    loss1, _ = min_reprojection(better, valid, ident, noise=0.0)
    loss2, _ = min_reprojection(both, valid, ident, noise=0.0)
    used1, used2 = (loss1 > 0).sum(), (loss2 > 0).sum()
    assert (loss2.sum() / used2) > (loss1.sum() / used1)
    assert automasked_error(both, valid, ident, mask) < automasked_error(better, valid, ident, mask)
    invalid = torch.zeros_like(valid)
    assert automasked_error(rep, invalid, None, mask).item() == 0.0  # nothing usable: 0, not NaN
