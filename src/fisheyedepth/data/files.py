"""The files of a recording read and checked, each refused naming the file when it is not what it must be:
an image at its camera's calibrated size (:func:`read_checked`), a mask (:func:`binary_mask`) and a
ground-truth distance map (:func:`read_distance`). :class:`~.layouts.RigLayout` reads its recording through
them, and so does the training dataset; surprises (a grayscale folder) are reported once a process."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import torch

from ..images import read_image

log = logging.getLogger(__name__)

_reported: set[tuple] = set()


def warn_once(key: tuple, message: str, *args) -> None:
    """``log.warning`` the first time ``key`` is seen in this process."""
    if key not in _reported:
        _reported.add(key)
        log.warning(message, *args)


def report_grayscale(path: Path) -> None:
    warn_once(
        ("grayscale", str(path.parent)),
        "%s: grayscale image (1 channel), replicated to 3 channels for the network; further grayscale "
        "images in %s are not reported",
        path,
        path.parent,
    )


def read_checked(path: Path, expect: tuple[int, int]) -> np.ndarray:
    """Read an image as 8-bit BGR; a clear error naming the file when it is missing, empty, truncated,
    corrupt or of the wrong size. A grayscale image is reported (once per folder) and replicated."""
    image = read_image(path)
    if image.grayscale:
        report_grayscale(path)
    w, h = image.bgr.shape[1::-1]
    if (w, h) != tuple(expect):
        raise ValueError(f"{path}: image is {w}x{h} but its calibration says {expect[0]}x{expect[1]}")
    return image.bgr


def binary_mask(
    path: Path, size: tuple[int, int], native: tuple[int, int] | None = None, what: str = "mask"
) -> torch.Tensor:
    """``[1, H, W]`` float: 1 where the mask image at ``path`` is bright (above 127), at ``size`` (width,
    height; nearest-neighbour resized). ``native``: the size the file must have (its image's), else the
    file is refused by name, as a ``what``."""
    mask = cv2.cvtColor(read_image(path).bgr, cv2.COLOR_BGR2GRAY)
    if native is not None and mask.shape[1::-1] != tuple(native):
        raise ValueError(
            f"{path}: {what} of {mask.shape[1]}x{mask.shape[0]} pixels, but its image is "
            f"{native[0]}x{native[1]}"
        )
    if mask.shape[1::-1] != tuple(size):
        mask = cv2.resize(mask, tuple(size), interpolation=cv2.INTER_NEAREST)
    return torch.from_numpy((mask > 127).astype(np.float32))[None]


MAX_TRUE_DISTANCE = 1e4  # metres: ten kilometres, beyond any LiDAR's or depth sensor's range


def read_distance(path: Path, native) -> np.ndarray:
    """A ground-truth distance map as float32 metres: an ``H x W`` float ``.npy`` at the size of its
    image (``native``, the camera at its calibrated size), finite, 0 where there is no ground truth and
    never negative. Anything else is refused naming the file, so that no map is stretched, misread or
    scored in the wrong unit without a word."""
    try:
        d = np.load(path, allow_pickle=False)  # never unpickle: a data file must not run code
    except ValueError as exc:
        with open(path, "rb") as handle:
            head = handle.read(6)
        pickled = head.startswith(b"\x80") or (head == b"\x93NUMPY" and "allow_pickle" in str(exc))
        if pickled:  # numpy's own line would suggest unpickling it
            raise ValueError(
                f"{path}: holds Python objects (a pickled array), which are never loaded: a data file "
                "must not run code; save the distance as a float array (np.save(path, d.astype(np.float32)))"
            ) from None
        if head != b"\x93NUMPY":  # text, a pickle of an older protocol, another format
            raise ValueError(f"{path}: not a NumPy .npy array (no .npy header; it begins {head!r})") from None
        raise ValueError(f"{path}: not a NumPy .npy array: {exc}") from None
    except EOFError:
        raise ValueError(f"{path}: not a NumPy .npy array (empty)") from None
    except OSError as exc:
        raise ValueError(f"{path}: not a NumPy .npy array ({exc.strerror or exc})") from None
    if not isinstance(d, np.ndarray):  # an .npz archive
        raise ValueError(f"{path}: not a NumPy .npy array: a {type(d).__name__}")
    want = (native.height, native.width)
    if d.ndim != 2 or not np.issubdtype(d.dtype, np.floating):
        raise ValueError(
            f"{path}: ground-truth distance of shape {d.shape} and dtype {d.dtype}; "
            f"expected an H x W float array in metres, {want} for its {native.width}x{native.height} image"
        )
    if d.shape != want:
        raise ValueError(
            f"{path}: ground-truth distance of shape {d.shape}, but its image is {native.width}x"
            f"{native.height}: expected shape {want} (the image's own size, never stretched)"
        )
    bad = int((~np.isfinite(d)).sum())
    if bad:
        raise ValueError(
            f"{path}: {bad} non-finite value(s) (NaN or inf) in the ground-truth distance; "
            "write 0 where a pixel has no ground truth"
        )
    negative = d < 0
    if negative.any():
        raise ValueError(
            f"{path}: {int(negative.sum())} negative value(s) (smallest {float(d.min()):g}) in the "
            "ground-truth distance; write 0 where a pixel has no ground truth"
        )
    far = d > MAX_TRUE_DISTANCE
    if far.any():
        raise ValueError(
            f"{path}: {int(far.sum())} value(s) beyond {MAX_TRUE_DISTANCE:g} m (largest {float(d.max()):g}) "
            "in the ground-truth distance: metres expected (not millimetres, no sentinel for 'far'); "
            "write 0 where a pixel has no ground truth"
        )
    return d.astype(np.float32)
