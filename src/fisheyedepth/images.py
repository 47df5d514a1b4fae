"""Reading images without silent surprises: truncated files are refused, grayscale is reported.

``cv2.imread`` fills the missing part of a truncated JPEG with grey and turns a grayscale image into
three grey channels without a word. ``read_image`` decodes from the file's bytes, checks that the file
ends where its format says it ends, and returns what the file really held alongside the BGR image, so
the caller can warn (training) or count and name the file (prediction). It reads the image's size from
its header first and refuses an image of more pixels than ``FISHEYEDEPTH_MAX_IMAGE_PIXELS`` (default
64 megapixels) before decoding it: a 140 KB PNG can hold 12000 x 12000 pixels (a decompression bomb).
"""

from __future__ import annotations

import errno
import io
import os
import stat
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image as PILImage

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
MAX_PIXELS_VARIABLE = "FISHEYEDEPTH_MAX_IMAGE_PIXELS"
MAX_PIXELS = 64_000_000  # default for the variable: 8000 x 8000, 32x a KITTI-360 frame


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


def max_image_pixels() -> int:
    """The largest image :func:`read_image` decodes: ``$FISHEYEDEPTH_MAX_IMAGE_PIXELS``, or MAX_PIXELS."""
    text = os.environ.get(MAX_PIXELS_VARIABLE, "").strip()
    if not text:
        return MAX_PIXELS
    try:
        value = int(float(text))
    except ValueError:
        value = 0
    if value < 1:
        raise ValueError(f"{MAX_PIXELS_VARIABLE}={text!r}: expected a number of pixels >= 1")
    return value


def header_size(data: bytes) -> tuple[str, int] | None:
    """The size of the encoded image ``data`` from its header alone (nothing is decoded), as words
    (``"12000x12000"``) and pixels, or None when Pillow does not know the format (the decoder then says
    what it is)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PILImage.DecompressionBombWarning)  # the caller sets the limit
        try:
            with PILImage.open(io.BytesIO(data)) as image:
                return f"{image.width}x{image.height}", image.width * image.height
        except PILImage.DecompressionBombError:  # Pillow refuses to open more than twice its limit
            pixels = 2 * (PILImage.MAX_IMAGE_PIXELS or 0)
            return f"more than {pixels:,}", pixels + 1
        except Exception:  # not a format Pillow reads: the decoder reports the file
            return None


def missing(path: Path) -> FileNotFoundError:
    """The error for an image that is not a file: absent, or a broken or looping symbolic link."""
    if path.is_symlink():
        try:
            os.stat(path)
            why = "does not lead to a file"
        except OSError as exc:
            why = "loops back on itself" if exc.errno == errno.ELOOP else "leads nowhere (its target is gone)"
        return FileNotFoundError(f"{path}: a symbolic link to {os.readlink(path)} that {why}")
    return FileNotFoundError(f"{path}: image not found")


def data_bits(raw: np.ndarray) -> int:
    """The bits of data in a 16-bit image, by its range: the highest set bit of its largest value rounded
    up to a sensor's depth (8, 10, 12, 14 or 16 bits). A 12-bit camera's PNG holds 0-4095 in 16 bits; read
    as 16 bits it would be near-black (4095 / 65535 = 6 %, 0-15 of 255), and nothing could be matched or
    learnt on it. Decided per image: the rounding keeps a camera's frames on one scale unless one's
    brightest pixel is under a quarter of its range (a 12-bit frame whose maximum is under 1024)."""
    bits = max(8, int(raw.max()).bit_length())
    return bits + bits % 2


def read_image(path: str | os.PathLike, max_pixels: int | None = None, bit_depth: int | None = None) -> Image:
    """Decode ``path`` as 8-bit BGR. Raises :class:`ImageError` naming the file when it is empty,
    truncated, not an image or larger than ``max_pixels`` (default: :func:`max_image_pixels`; checked
    on the header, before decoding), and ``FileNotFoundError`` when it is missing or a broken symbolic
    link. 16-bit images are scaled to 8 bits from ``bit_depth`` bits of data (default: by the image's
    range, :func:`data_bits`); an alpha channel is dropped; a grayscale image is replicated to three
    channels and reported through ``Image.channels``."""
    if bit_depth is not None and not 8 <= int(bit_depth) <= 16:
        raise ValueError(f"bit_depth: {bit_depth}; expected 8 to 16 bits of data in a 16-bit image")
    path = Path(path)
    if not path.is_file():
        raise missing(path)
    data = path.read_bytes()
    if not data:
        raise ImageError(f"{path}: empty file, not an image")
    why = truncation(data)
    if why:
        raise ImageError(f"{path}: {why}")
    limit = max_image_pixels() if max_pixels is None else int(max_pixels)
    size = header_size(data)
    if size is not None and size[1] > limit:
        raise ImageError(
            f"{path}: an image of {size[0]} pixels, over the limit of {limit:,} (a decompression bomb?); "
            f"set {MAX_PIXELS_VARIABLE} to read larger images"
        )
    raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ImageError(f"{path}: not a readable image (corrupt or not an image)")
    if raw.dtype == np.uint16:
        top = 2 ** (bit_depth or data_bits(raw)) - 1
        raw = (np.minimum(raw, top).astype(np.uint32) * 255 // top).astype(np.uint8)
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
    """The images of ``folder`` in name order, broken and looping symbolic links named like an image
    included (reading them fails, so they are counted and named as skipped, not silently missing). An
    empty folder and two files with one stem (``a.png`` and ``a.jpg`` would write the same outputs) are
    errors naming the folder or the files."""
    folder = Path(folder)
    files = sorted(
        p
        for p in folder.iterdir()
        if p.suffix.lower() in IMAGE_SUFFIXES and (p.is_file() or (p.is_symlink() and not p.exists()))
    )
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


def is_live(source: str | os.PathLike) -> bool:
    """A live camera: a device file (``/dev/video0``), or a camera index (``0``) that names no file or
    folder (a sequence folder called ``00`` is a folder)."""
    text = str(source)
    try:
        return stat.S_ISCHR(os.stat(text).st_mode)
    except OSError:
        return text.isdigit()


class FrameSource:
    """Frames of a folder of images, a video file or a live camera (``/dev/video0``, or an index such as
    ``0``), decoded one at a time (memory stays flat in the number of frames). ``names`` are known before
    anything is decoded, except for a live camera (its frames are named as they come). ``max_frames``
    stops after that many frames (a live camera otherwise runs until interrupted)."""

    def __init__(self, source: str | os.PathLike, max_frames: int | None = None):
        if max_frames is not None and int(max_frames) < 1:
            raise ValueError(f"max_frames: {max_frames!r}, expected a number of frames >= 1 (or null)")
        self.max_frames = None if max_frames is None else int(max_frames)
        self.source = Path(source)
        self.live = is_live(source)
        self.files: list[Path] | None = None
        if self.live:
            self.capture = int(str(source)) if str(source).isdigit() else str(self.source)
            self.count = 0  # unknown
        elif self.source.is_dir():
            self.files = list_images(self.source)[: self.max_frames]
            self.count = len(self.files)
        elif self.source.is_file():
            self.capture = str(self.source)
            video = cv2.VideoCapture(self.capture)
            try:
                if not video.isOpened():
                    raise ImageError(f"{self.source}: not a readable video (or an image folder)")
                self.count = max(int(video.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
            finally:
                video.release()
            if self.max_frames is not None:
                self.count = min(self.count, self.max_frames)
        else:
            raise FileNotFoundError(f"{self.source}: no such image folder, video or camera")

    @staticmethod
    def video_name(index: int) -> str:
        return f"frame_{index:06d}"

    def names(self) -> list[str]:
        """Output stems; for a video, from its frame count (containers may miscount by a few frames);
        none for a live camera."""
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
        video = cv2.VideoCapture(self.capture)
        try:
            if self.live and not video.isOpened():
                raise ImageError(f"{self.source}: the camera could not be opened")
            index = 0
            while self.max_frames is None or index < self.max_frames:
                ok, bgr = video.read()
                if not ok:
                    break
                yield Frame(self.video_name(index), self.source, bgr)
                index += 1
        finally:
            video.release()
