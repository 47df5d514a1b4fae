"""The per-camera ray cache: computed once, kept on the device, exact."""

from __future__ import annotations

import pytest
import torch

from fisheyedepth.cameras import RayCache, compute_rays, pixel_grid

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
