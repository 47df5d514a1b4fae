"""Published calibrations, as cameras (facts from the datasets' own calibration files): TUM-VI's
512 x 512 ``cam0`` as Kannala-Brandt and as double sphere. KITTI-360's live with its other files in
:mod:`fisheyedepth.data.kitti360.presets`.
"""

from __future__ import annotations

from .double_sphere import DoubleSphereCamera
from .kannala_brandt import KannalaBrandtCamera


def tumvi_kannala_brandt() -> KannalaBrandtCamera:
    return KannalaBrandtCamera(
        width=512,
        height=512,
        fx=190.97847715128717,
        fy=190.9733070521226,
        cx=254.93170605935475,
        cy=256.8974428996504,
        k1=0.0034823894022493434,
        k2=0.0007150348452162257,
        k3=-0.0020532361418706202,
        k4=0.00020293673591811182,
    )


def tumvi_double_sphere() -> DoubleSphereCamera:
    return DoubleSphereCamera(
        width=512,
        height=512,
        fx=158.28600034966977,
        fy=158.2743455478755,
        cx=254.96116578191653,
        cy=256.8894394501779,
        xi=-0.17213086034353243,
        alpha=0.5931177593944744,
    )
