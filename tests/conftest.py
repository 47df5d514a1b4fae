"""Shared fixtures: reference cameras of every model and the real-data folder."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from fisheyedepth.cameras import DoubleSphereCamera, KannalaBrandtCamera, MeiCamera, PinholeCamera

ROOT = Path(__file__).resolve().parents[1]

# KITTI-360 official calibration values (image_02.yaml / image_03.yaml), 1400 x 1400.
KITTI_02 = dict(
    xi=2.2134047507854890, k1=1.6798235660113681e-02, k2=1.6548773243373522, p1=4.2223943394772046e-04,
    p2=4.2462134260997584e-04, gamma1=1.3363220825849971e03, gamma2=1.3357883350012958e03,
    u0=7.1694323510126321e02, v0=7.0576498308221585e02,
)
KITTI_03 = dict(
    xi=2.5535139132482758, k1=4.9370396274089505e-02, k2=4.5068455478645308, p1=1.3477698472982495e-03,
    p2=-7.0340482615055284e-04, gamma1=1.4854388981875156e03, gamma2=1.4849477411748708e03,
    u0=6.9888316784030962e02, v0=6.9814541887723055e02,
)
# TUM-VI 512 calibrations (Kannala-Brandt and double sphere), 512 x 512.
TUMVI_KB = dict(
    fx=190.97847715128717, fy=190.9733070521226, cx=254.93170605935475, cy=256.8974428996504,
    k1=0.0034823894022493434, k2=0.0007150348452162257, k3=-0.0020532361418706202, k4=0.00020293673591811182,
)
TUMVI_DS = dict(
    fx=158.28600034966977, fy=158.2743455478755, cx=254.96116578191653, cy=256.8894394501779,
    xi=-0.17213086034353243, alpha=0.5931177593944744,
)


def kitti02(tangential: bool = False) -> MeiCamera:
    params = dict(KITTI_02)
    if not tangential:
        params.update(p1=0.0, p2=0.0)
    return MeiCamera(width=1400, height=1400, **params)


def kitti03(tangential: bool = False) -> MeiCamera:
    params = dict(KITTI_03)
    if not tangential:
        params.update(p1=0.0, p2=0.0)
    return MeiCamera(width=1400, height=1400, **params)


def all_cameras() -> dict[str, object]:
    """One camera per model and regime, small enough for full-grid tests."""
    return {
        "mei_kitti02_384": kitti02().resize(384, 384),
        "mei_kitti03_tangential_384": kitti03(tangential=True).resize(384, 384),
        # xi < 1 and a radial distortion that folds back: the domain ends where g'(r) = 0
        "mei_xi_below_1": MeiCamera(width=320, height=240, xi=0.8, k1=-0.25, k2=0.02,
                                    gamma1=300.0, gamma2=302.0, u0=160.3, v0=119.6),
        "kb_tumvi": KannalaBrandtCamera(width=512, height=512, **TUMVI_KB),
        # a KB fit whose polynomial folds before 180 degrees (Aria slam-left fit)
        "kb_aria": KannalaBrandtCamera(width=640, height=480, fx=241.00432, fy=240.98965, cx=316.88001,
                                       cy=236.94558, k1=-0.0225306, k2=0.0922766, k3=-0.0640892, k4=0.0113456),
        "ds_tumvi": DoubleSphereCamera(width=512, height=512, **TUMVI_DS),
        "ds_alpha_below_half": DoubleSphereCamera(width=400, height=300, fx=150.0, fy=151.0, cx=200.2, cy=149.7,
                                                  xi=0.3, alpha=0.4),
        "pinhole": PinholeCamera(width=320, height=240, fx=200.0, fy=201.0, cx=159.5, cy=120.25),
    }


@pytest.fixture(params=list(all_cameras()))
def camera(request):
    return all_cameras()[request.param]


def realdata_dir() -> Path:
    return Path(os.environ.get("FISHEYEDEPTH_REALDATA", ROOT.parent / "shared" / "realdata"))


@pytest.fixture
def realdata() -> Path:
    path = realdata_dir()
    if not path.is_dir():
        pytest.skip(f"real data not found at {path} (set FISHEYEDEPTH_REALDATA)")
    return path
