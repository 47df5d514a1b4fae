"""Reading images without silent surprises: truncated files are refused, grayscale is reported.

``cv2.imread`` fills the missing part of a truncated JPEG with grey and turns a grayscale image into
three grey channels without a word. ``read_image`` decodes from the file's bytes, checks that the file
ends where its format says it ends, and returns what the file really held alongside the BGR image, so
the caller can warn (training) or count and name the file (prediction).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class ImageError(ValueError):
    """An image file that cannot be used; the message names the file."""


@dataclass(frozen=True)
class Image:
    bgr: np.ndarray  # uint8 [H, W, 3]
    channels: int  # channels stored in the file (1 = grayscale, 3 = colour, 4 = with alpha)

    @property
    def grayscale(self) -> bool:
        return self.channels == 1


def truncation(data: bytes) -> str | None:
    """Why the encoded image ``data`` is cut short, or None when it ends where its format says it ends
    (JPEG: an end-of-image marker after the last scan; PNG: the IEND chunk)."""
    if data[:2] == b"\xff\xd8":
        if data.rfind(b"\xff\xd9") < data.rfind(b"\xff\xda"):
            return "truncated JPEG (no end-of-image marker after the last scan)"
    elif data[:8] == b"\x89PNG\r\n\x1a\n":
        if b"IEND" not in data[-32:]:
            return "truncated PNG (no IEND chunk)"
    return None


def read_image(path: str | os.PathLike) -> Image:
    """Decode ``path`` as 8-bit BGR. Raises :class:`ImageError` naming the file when it is empty,
    truncated or not an image, and ``FileNotFoundError`` when it is missing. 16-bit images are scaled
    to 8 bits; an alpha channel is dropped; a grayscale image is replicated to three channels and
    reported through ``Image.channels``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image not found")
    data = path.read_bytes()
    if not data:
        raise ImageError(f"{path}: empty file, not an image")
    why = truncation(data)
    if why:
        raise ImageError(f"{path}: {why}")
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageError(f"{path}: not a readable image (corrupt or not an image)")
    if raw.dtype == np.uint16:
        raw = (raw.astype(np.uint32) * 255 // 65535).astype(np.uint8)
    elif raw.dtype != np.uint8:
        raise ImageError(f"{path}: unsupported pixel type {raw.dtype} (expected 8 or 16 bits)")
    channels = 1 if raw.ndim == 2 else raw.shape[2]
    if channels == 1:
        bgr = cv2.cvtColor(raw.reshape(raw.shape[:2]), cv2.COLOR_GRAY2BGR)
    elif channels == 3:
        bgr = raw
    elif channels == 4:
        bgr = np.ascontiguousarray(raw[..., :3])
    else:
        raise ImageError(f"{path}: {channels} channels (expected 1, 3 or 4)")
    return Image(bgr, channels)


# ------------------------------------------------------------------------------------- frame sources
@dataclass(frozen=True)
class Frame:
    """One input of a prediction run: an image file or a video frame, decoded or with the reason why not."""

    name: str  # output stem: the file's stem, or frame_%06d for a video
    path: Path  # the image file, or the video
    bgr: np.ndarray | None
    channels: int = 3
    error: str | None = None


def list_images(folder: str | os.PathLike) -> list[Path]:
    """The images of ``folder`` in name order. An empty folder and two files with one stem (``a.png``
    and ``a.jpg`` would write the same outputs) are errors naming the folder or the files."""
    folder = Path(folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise FileNotFoundError(f"{folder}: no images ({' '.join(IMAGE_SUFFIXES)}) in this folder")
    seen: dict[str, Path] = {}
    for path in files:
        if path.stem in seen:
            raise ValueError(
                f"{seen[path.stem]} and {path}: two images with one name; their outputs would clash"
            )
        seen[path.stem] = path
    return files


class FrameSource:
    """Frames of a folder of images or of a video file, decoded one at a time (memory stays flat in the
    number of frames). ``names`` are known before anything is decoded."""

    def __init__(self, source: str | os.PathLike):
        self.source = Path(source)
        if self.source.is_dir():
            self.files: list[Path] | None = list_images(self.source)
            self.count = len(self.files)
        elif self.source.is_file():
            self.files = None
            video = cv2.VideoCapture(str(self.source))
            try:
                if not video.isOpened():
                    raise ImageError(f"{self.source}: not a readable video (or an image folder)")
                self.count = max(int(video.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
            finally:
                video.release()
        else:
            raise FileNotFoundError(f"{self.source}: no such image folder or video")

    @staticmethod
    def video_name(index: int) -> str:
        return f"frame_{index:06d}"

    def names(self) -> list[str]:
        """Output stems; for a video, from its frame count (containers may miscount by a few frames)."""
        if self.files is not None:
            return [p.stem for p in self.files]
        return [self.video_name(i) for i in range(self.count)]

    def __len__(self) -> int:
        return self.count

    def __iter__(self):
        if self.files is not None:
            for path in self.files:
                try:
                    image = read_image(path)
                except (ImageError, OSError) as exc:
                    yield Frame(path.stem, path, None, 0, str(exc))
                else:
                    yield Frame(path.stem, path, image.bgr, image.channels)
            return
        video = cv2.VideoCapture(str(self.source))
        try:
            index = 0
            while True:
                ok, bgr = video.read()
                if not ok:
                    break
                yield Frame(self.video_name(index), self.source, bgr)
                index += 1
        finally:
            video.release()
