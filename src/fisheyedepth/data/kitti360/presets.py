"""KITTI-360's published calibration, as values (facts from the dataset's own calibration files).

- Fisheyes ``image_02`` (left) and ``image_03`` (right), Mei model, 1400 x 1400, from the official
  ``calibration/image_0X.yaml``. ``kitti360_camera(2)`` drops p1/p2 like the official tools;
  ``tangential=True`` keeps them.
- Extrinsics from ``calib_cam_to_pose.txt`` and ``calib_cam_to_velo.txt``.
"""

from __future__ import annotations

from ...cameras import MeiCamera

KITTI360_MEI = {
    2: dict(
        xi=2.2134047507854890,
        k1=1.6798235660113681e-02,
        k2=1.6548773243373522,
        p1=4.2223943394772046e-04,
        p2=4.2462134260997584e-04,
        gamma1=1.3363220825849971e03,
        gamma2=1.3357883350012958e03,
        u0=7.1694323510126321e02,
        v0=7.0576498308221585e02,
    ),
    3: dict(
        xi=2.5535139132482758,
        k1=4.9370396274089505e-02,
        k2=4.5068455478645308,
        p1=1.3477698472982495e-03,
        p2=-7.0340482615055284e-04,
        gamma1=1.4854388981875156e03,
        gamma2=1.4849477411748708e03,
        u0=6.9888316784030962e02,
        v0=6.9814541887723055e02,
    ),
}


# calibration/calib_cam_to_pose.txt: camera -> pose (IMU/GPS) frame, 3x4 row-major. image_00/01 are the
# perspective stereo pair, image_02/03 the side fisheyes. The pose frame is x forward, y right, z down.
KITTI360_CAM_TO_POSE = {
    "image_00": (
        0.0371783278,
        -0.0986182135,
        0.9944306009,
        1.5752681039,
        0.9992675562,
        -0.0053553387,
        -0.0378902567,
        0.0043914093,
        0.0090621821,
        0.9951109327,
        0.0983468786,
        -0.6500000000,
    ),
    "image_01": (
        0.0194000864,
        -0.1051529641,
        0.9942668106,
        1.5977241400,
        0.9997374956,
        -0.0100836652,
        -0.0205732716,
        0.5981494900,
        0.0121891942,
        0.9944049345,
        0.1049297370,
        -0.6488433108,
    ),
    "image_02": (
        0.9995185086,
        0.0041276589,
        -0.0307524527,
        0.7264036936,
        -0.0307926666,
        0.0100608424,
        -0.9994751579,
        -0.1499658517,
        -0.0038160970,
        0.9999408692,
        0.0101830998,
        -1.0686400091,
    ),
    "image_03": (
        -0.9996821702,
        0.0005703407,
        -0.0252038325,
        0.7016842127,
        -0.0252033830,
        0.0007820814,
        0.9996820384,
        0.7463650950,
        0.0005898709,
        0.9999995315,
        -0.0007674583,
        -1.0751978255,
    ),
}
# calibration/calib_cam_to_velo.txt: camera 0 (unrectified) -> Velodyne, 3x4 row-major.
KITTI360_CAM0_TO_VELO = (
    0.04307104361,
    -0.08829286498,
    0.995162929,
    0.8043914418,
    -0.999004371,
    0.007784614041,
    0.04392796942,
    0.2993489574,
    -0.01162548558,
    -0.9960641394,
    -0.08786966659,
    -0.1770225824,
)


def kitti360_camera(index: int, tangential: bool = False) -> MeiCamera:
    """KITTI-360 ``image_0{index}`` (2 or 3) at its native 1400 x 1400."""
    if index not in KITTI360_MEI:
        raise ValueError(f"KITTI-360 fisheye cameras are image_02 and image_03, not image_0{index}")
    params = dict(KITTI360_MEI[index])
    if not tangential:
        params.update(p1=0.0, p2=0.0)
    return MeiCamera(width=1400, height=1400, **params)
