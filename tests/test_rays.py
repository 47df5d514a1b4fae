"""The per-camera ray cache: computed once, kept on the device, exact."""

from __future__ import annotations

import math

import pytest
import torch

from fisheyedepth.cameras import RayCache, compute_rays, erode_field_of_view, pixel_grid

from conftest import kitti02, kitti03


def test_pixel_grid_is_column_row_at_centres():
    g = pixel_grid(4, 3)
    assert g.shape == (3, 4, 2)
    assert g[2, 3].tolist() == [3.0, 2.0]  # (u, v) = (column, row)


def test_cache_returns_the_same_tensors():
    cache = RayCache()
    cam = kitti02().resize(64, 64)
    first = cache.get(cam)
    second = cache.get(kitti02().resize(64, 64))  # an equal camera value hits the same entry
    assert first.rays is second.rays and first.valid is second.valid
    assert cache.misses == 1 and len(cache) == 1
    cache.get(cam, dtype=torch.float64)
    cache.get(cam.flip())
    cache.get(kitti02().resize(32, 32))
    assert cache.misses == 4 and len(cache) == 4


def test_cached_rays_equal_unprojection():
    cam = kitti03(tangential=True).resize(96, 80)
    rays, valid = RayCache().get(cam, dtype=torch.float64)
    expected, expected_valid = cam.unproject(pixel_grid(96, 80, dtype=torch.float64))
    assert torch.equal(valid, expected_valid)
    assert torch.equal(rays, expected)
    r32, v32 = RayCache().get(cam, dtype=torch.float32)
    assert r32.dtype == torch.float32 and torch.equal(v32, valid)
    assert (r32.double() - rays).abs().max() < 1e-7  # correctly rounded from float64


def test_lru_bound():
    cache = RayCache(max_entries=2)
    cams = [kitti02().resize(16 + i, 16) for i in range(3)]
    for cam in cams:
        cache.get(cam)
    assert len(cache) == 2
    cache.get(cams[2])
    assert cache.misses == 3
    cache.get(cams[0])
    assert cache.misses == 4


def test_batch_of_cameras():
    cache = RayCache()
    a, b = kitti02().resize(40, 40), kitti03().resize(40, 40)
    rays, valid = cache.batch([a, b, a])
    assert rays.shape == (3, 40, 40, 3) and valid.shape == (3, 40, 40)
    assert torch.equal(rays[0], rays[2]) and not torch.equal(rays[0], rays[1])
    same, _ = cache.batch([a, a])
    assert same.shape == (2, 40, 40, 3) and torch.equal(same[1], cache.get(a).rays)
    with pytest.raises(ValueError, match="image size"):
        cache.batch([a, kitti02().resize(30, 30)])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cache_lives_on_the_device():
    cache = RayCache()
    cam = kitti02().resize(64, 64)
    entry = cache.get(cam, device="cuda")
    assert entry.rays.device.type == "cuda"
    assert cache.get(cam, device=torch.device("cuda", torch.cuda.current_device())).rays is entry.rays
    cpu = compute_rays(cam)
    assert torch.allclose(entry.rays.cpu(), cpu.rays)


def test_the_rim_erosion_drops_exactly_the_pixels_next_to_the_field_of_view_edge():
    """``erode_field_of_view`` keeps a pixel only if every pixel within ``margin`` (a square window) has a
    ray: on kitti03's image circle at 64 px it equals that rule written as a loop; the rectangle's border
    is not an edge of the field of view; margin 0 changes nothing and a negative margin is refused."""
    _, valid = RayCache().get(kitti03().resize(64, 64), dtype=torch.float64)
    valid = valid[None]
    assert 0.5 < valid.float().mean() < 0.95  # a circle inside the square: corners without rays
    for margin in (1, 2):
        eroded = erode_field_of_view(valid, margin)
        expected = torch.zeros_like(valid)
        for v in range(64):
            for u in range(64):
                window = valid[0, max(v - margin, 0) : v + margin + 1, max(u - margin, 0) : u + margin + 1]
                expected[0, v, u] = bool(window.all())
        assert torch.equal(eroded, expected), margin
        ring = valid & ~eroded
        # the ring is the circle's rim: about its perimeter (2 pi r with r ~ 32 px) per pixel of margin
        assert 0.7 * 2 * math.pi * 32 * margin < ring.sum() < 1.6 * 2 * math.pi * 32 * margin, int(ring.sum())
    full = torch.ones(2, 5, 7, dtype=torch.bool)
    assert torch.equal(erode_field_of_view(full, 2), full)
    hole = full.clone()
    hole[1, 2, 3] = False
    eroded = erode_field_of_view(hole, 1)
    assert eroded[0].all() and int((~eroded[1]).sum()) == 9 and not eroded[1, 1:4, 2:5].any()
    assert erode_field_of_view(hole, 0) is hole
    with pytest.raises(ValueError, match="rim margin: -1 pixels is negative"):
        erode_field_of_view(hole, -1)


def test_the_cache_erodes_each_camera_once_per_margin():
    """``RayCache.inside``: one eroded field of view per (camera, margin), stacked per sample, the same
    numbers as eroding the cached validity; a resized camera is its own entry."""
    cache = RayCache()
    cams = [kitti03().resize(64, 64), kitti02().resize(64, 64), kitti03().resize(64, 64)]
    inside = cache.inside(cams, 1)
    expected = torch.stack([erode_field_of_view(cache.get(c).valid[None], 1)[0] for c in cams])
    assert torch.equal(inside, expected) and not torch.equal(inside[0], inside[1])
    assert len(cache._inside) == 2 and cache.misses == 2  # kitti03 once, kitti02 once
    assert torch.equal(cache.inside(cams[::-1], 1), inside.flip(0))  # the same entries, reused
    assert len(cache._inside) == 2 and cache.misses == 2
    cache.inside([kitti03().resize(32, 32)], 1)
    cache.inside(cams[:1], 2)
    assert len(cache._inside) == 4


# ------------------------------------------------------------- a large image without the iterative inverse
def test_interpolated_rays_are_the_models_inverse(camera):
    """Every model: the rays by interpolation and Newton's polish project back within
    1e-6 px of their pixel, equal the model's own unprojection to 1e-7 radians (under float32's resolution),
    and the same pixels have a ray."""
    from fisheyedepth.cameras.rays import interpolated_rays

    big = camera
    rays, valid = interpolated_rays(big)
    expected, expected_valid = big.unproject(pixel_grid(big.width, big.height, dtype=torch.float64))
    assert torch.equal(valid, expected_valid)
    assert (rays[valid] - expected[valid]).norm(dim=-1).max() < 1e-7  # below float32's resolution
    uv, projects = big.project(rays[valid])
    assert (
        projects.all()
        and (uv - pixel_grid(big.width, big.height, dtype=torch.float64)[valid]).norm(dim=-1).max() < 1e-6
    )
    assert torch.equal(
        rays[~valid], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(int((~valid).sum()), 3)
    )


def test_a_large_image_of_an_iterative_model_is_interpolated_and_a_small_one_is_not(monkeypatch):
    """compute_rays takes the interpolated path for a model whose inverse is a two-dimensional iteration
    (Fisheye624, OpenCV, Mei with tangential terms) from INTERPOLATE_FROM_PIXELS on, the model's own
    unprojection for the others and for small images."""
    from fisheyedepth.cameras import rays as module

    calls = []

    def instead(camera, device, tolerance_px):
        calls.append(camera)
        return camera.unproject(pixel_grid(camera.width, camera.height, dtype=torch.float64))

    monkeypatch.setattr(module, "interpolated_rays", instead)
    small, large = kitti03(tangential=True).resize(64, 64), kitti03(tangential=True).resize(256, 256)
    compute_rays(small)
    compute_rays(kitti02().resize(256, 256))  # no tangential terms: a one-dimensional solve
    assert calls == []
    compute_rays(large)
    assert calls == [large] and large.width * large.height >= module.INTERPOLATE_FROM_PIXELS


@pytest.mark.parametrize("dtype,tolerance", [(torch.float64, 1e-9), (torch.float32, 1e-6)])
def test_interpolated_rays_are_polished_to_the_precision_asked_for(dtype, tolerance):
    """float64 rays project back within 1e-9 px of their pixel (a warp by them maps every pixel onto
    itself); float32 ones within float32's own resolution (the polish stops at 1e-6 px)."""
    camera = kitti03(tangential=True).resize(256, 256)
    rays, valid = RayCache().get(camera, dtype=dtype)
    uv, _ = camera.project(rays[valid].double())
    error = (uv - pixel_grid(256, 256, dtype=torch.float64)[valid]).norm(dim=-1).max()
    assert error < (tolerance if dtype == torch.float64 else 1e-4)
