"""Seeded pose noise: the odometry error of the paper's noise claim, with the statistics it promises."""

from __future__ import annotations

import math

import pytest
import torch

from fisheyedepth.data import FisheyeDataModule, PoseNoise
from fisheyedepth.geometry import axis_angle_to_matrix, make_pose, rotation_error_deg


def a_pose() -> torch.Tensor:
    R = axis_angle_to_matrix(torch.tensor([0.02, -0.1, 0.03], dtype=torch.float64))
    return make_pose(R, torch.tensor([0.1, -0.05, 1.2], dtype=torch.float64))


def test_no_noise_is_the_identity_and_noise_is_seeded_per_key():
    T = a_pose()
    assert torch.equal(PoseNoise()(T, "a"), T)
    noise = PoseNoise(rotation_deg=1.0, translation=0.05, seed=3)
    assert torch.equal(noise(T, "a"), noise(T, "a"))  # the same every epoch
    assert not torch.equal(noise(T, "a"), noise(T, "b"))
    assert not torch.equal(noise(T, "a"), PoseNoise(1.0, 0.05, seed=4)(T, "a"))
    R = noise(T, "a")[:3, :3]
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-12)  # still a rotation
    with pytest.raises(ValueError, match="non-negative"):
        PoseNoise(rotation_deg=-1.0)


def test_noise_has_the_promised_spread():
    T = a_pose()
    noise = PoseNoise(rotation_deg=2.0, translation=0.05, seed=0)
    noisy = torch.stack([noise(T, str(i)) for i in range(2000)])
    angles = rotation_error_deg(noisy, T.expand_as(noisy))
    # |N(0, 2 deg)|: mean 2 * sqrt(2 / pi) = 1.596 deg
    assert angles.mean().item() == pytest.approx(2.0 * math.sqrt(2 / math.pi), rel=0.05)
    error = (noisy[:, :3, 3] - T[:3, 3]) / T[:3, 3].norm()
    assert error.std(0).tolist() == pytest.approx([0.05] * 3, rel=0.07)
    assert error.mean(0).abs().max().item() < 0.005  # unbiased


def test_the_datamodule_applies_it_to_every_sample(kitti_data, tmp_path):
    def poses(noise):
        dm = FisheyeDataModule(
            kitti_data, splits={"train": "splits/train.txt"}, size=(32, 32), pose_noise=noise,
            cache_dir=tmp_path, ground_truth="none",
        )  # fmt: skip
        ds = dm.dataset("train")
        return torch.stack([ds[i]["poses"] for i in range(len(ds))]).double()

    clean = poses(None)
    noisy = poses({"rotation_deg": 1.0, "translation": 0.0, "seed": 0})
    again = poses({"rotation_deg": 1.0, "translation": 0.0, "seed": 0})
    assert torch.equal(noisy, again)
    angles = rotation_error_deg(noisy, clean)
    assert 0.3 < angles.mean().item() < 1.6 and angles.max().item() < 5.0
    assert torch.allclose(noisy[..., :3, 3], clean[..., :3, 3], atol=1e-6)  # rotation noise only
