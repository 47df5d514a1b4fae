"""Files the package writes and the paths it is given: names that are safe as file names and stay inside
their folder, inputs and outputs kept apart as resolved paths, folders checked for writing before any
work, every file written through a temporary beside it and renamed (:func:`atomic_target`), folders
built beside their target and moved into place (:func:`staged_folder`, :func:`move_into_place`), one
folder lock for every writer (:func:`take_lock`), and what killed writers left removed."""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import io
import os
import shutil
import tempfile
import unicodedata
from collections.abc import Iterator
from pathlib import Path

import numpy as np

# A name may take this many bytes (UTF-8): 255 (NAME_MAX of ext4, XFS, btrfs, APFS) less room for what the
# files named after it add (``body_mask_<camera>.png``, the LiDAR cache's ``<camera>_<W>x<H>_<16 hex>``,
# atomic writes' ``.<name>.<8 random>.tmp``).
NAME_BYTES = 200


def path_name(name: str, what: str, source: str | os.PathLike) -> str:
    """``name`` (a camera's, a sequence's: read from a file or given as an option) checked to be one plain
    file or folder name, as every command that joins it into a path needs it: ``root / sequence /
    "images" / camera`` must stay under ``root``. A ``ValueError`` ``<source>: <what> <name!r> ...``
    (``source``: the file or option it came from; ``what``: its field) otherwise.

    Refused: an empty name, ``.`` and ``..``, a path separator (``/``, and ``\\``, Windows' separator,
    which a folder copied there would split on), an absolute path, a control character (NUL ends the
    name for the operating system; a newline breaks the one-line split files and error messages),
    more than :data:`NAME_BYTES` bytes, and a leading ``-``: every shell tool (``ls``, ``rm``, ``cp``,
    ``tar``) and argparse (``--camera -left``) reads such a name as an option, so that camera's files
    could not be named on a command line without tricks, and no camera, ROS topic (which may not start
    with ``-``), Kalibr or KITTI-360 name needs one."""
    if not isinstance(name, str):
        raise ValueError(f"{source}: {what} {name!r} is not a name (a string)")
    separators = [c for c in ("/", "\\") if c in name]
    controls = [c for c in name if unicodedata.category(c) == "Cc"]
    size = len(name.encode("utf-8", "surrogateescape"))
    why = (
        "is empty" if not name
        else "is not a name but a folder (this one or its parent)" if name in (".", "..")
        else "is an absolute path" if name.startswith(("/", "\\")) or os.path.isabs(name)
        else f"contains a path separator ({separators[0]!r})" if separators
        else f"contains a control character ({controls[0]!r})" if controls
        else "starts with '-', which command-line tools read as an option" if name.startswith("-")
        else f"is {size} bytes long, more than {NAME_BYTES}" if size > NAME_BYTES
        else None
    )  # fmt: skip
    if why is not None:
        raise ValueError(f"{source}: {what} {name!r} {why}: it must be one plain file or folder name")
    return name


def inside(root: str | os.PathLike, path: str | os.PathLike, source: str | os.PathLike) -> Path:
    """``path``, checked to lie under ``root`` as written (``..`` folded away): what :func:`path_name`
    already ensures for names, checked again where a path is written. Links are not followed, so a
    dataset whose folders are links to another disk stays readable and writable."""
    top = os.path.normpath(os.path.abspath(root))
    where = os.path.normpath(os.path.abspath(path))
    if os.path.commonpath([top, where]) != top:
        raise ValueError(f"{source}: {path} lies outside {root}")
    return Path(path)


def check_apart(out: str | os.PathLike, option: str, inputs: dict[str, str | os.PathLike]) -> None:
    """``out`` (what ``option`` writes: a file or a folder) neither is, lies inside, nor holds any of
    ``inputs`` ({what: path} a command reads), compared as resolved paths: through links too, so that no
    command writes over what it reads. A ValueError names the option and the input."""
    where = os.path.realpath(out)
    for what, path in inputs.items():
        top = os.path.realpath(path)
        if os.path.commonpath([top, where]) not in (top, where):
            continue
        how = "is" if top == where else "lies inside" if os.path.commonpath([top, where]) == top else "holds"
        through = "" if (os.path.abspath(out), os.path.abspath(path)) == (where, top) else " (through a link)"
        raise ValueError(
            f"{option}: {out} {how} {what} {path}{through}; write the outputs to a place of their own"
        )


# Writes the machine refuses (a read-only or full filesystem, a folder without write permission): the
# user's output option is at fault, not the program, so they end a command like any bad input.
WRITE_ERRORS = {errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT}


def check_writable(folder: str | os.PathLike, option: str) -> Path:
    """``folder`` can take files: checked before any work, so a read-only or full filesystem is named at
    once, not after the network has run. Nothing is left behind: the check writes a temporary file into
    ``folder``, or into its nearest existing parent when it is still to be made. A ValueError names the
    option."""
    folder = Path(folder)
    here = folder
    while not here.exists() and here != here.parent:
        here = here.parent
    try:
        if not here.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "not a folder", str(here))
        with tempfile.NamedTemporaryFile(dir=here, prefix=".write-check-"):
            pass
    except OSError as err:
        if err.errno not in WRITE_ERRORS and not isinstance(err, NotADirectoryError):
            raise
        raise ValueError(f"{option}: {folder}: cannot write there ({err.strerror})") from None
    return folder


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` through a temporary file in the same folder and an atomic rename
    (:func:`atomic_target`)."""
    return atomic_write_bytes(path, text.encode())


def current_umask() -> int:
    """The process's file-creation mask (read without changing it where Linux allows)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # elsewhere: set and restore
    os.umask(mask)
    return mask


@contextlib.contextmanager
def temporary_beside(path: str | os.PathLike) -> Iterator[Path]:
    """A hidden temporary file beside ``path`` (``.NAME.<random>.<pid>.tmp``, in the same folder, so that
    a rename puts it in place atomically; the writer's pid tells a killed writer's leftovers from a live
    one's) with the permissions a plain ``open`` would give (0666 less the umask), not ``mkstemp``'s
    private 0600. It is removed when the block ends unless the block moved it away: a failed write
    leaves nothing."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".{os.getpid()}.tmp")
    try:
        os.fchmod(fd, 0o666 & ~current_umask())
        os.close(fd)
        yield Path(tmp)
    finally:
        Path(tmp).unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_target(path: str | os.PathLike, sync: bool = False) -> Iterator[Path]:
    """The one way the package writes a file: the block writes the yielded temporary file beside ``path``
    (:func:`temporary_beside`), which is renamed over ``path`` when the block completes (``sync``: its
    data flushed to disk first, for a file whose loss costs hours, as a checkpoint). A reader sees the
    old file or the new one, whole; an interrupted or failed write leaves ``path`` as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with temporary_beside(path) as tmp:
        yield tmp
        if sync:
            with open(tmp, "rb+") as handle:
                os.fsync(handle.fileno())
        os.replace(tmp, path)


def place_new(tmp: str | os.PathLike, path: Path) -> None:
    """``tmp`` at ``path``, which must not exist: ``os.link``, a FileExistsError naming ``path`` if a file
    took the name meanwhile; on a filesystem without hard links (FAT), checked and renamed."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists; pass overwrite=true to replace it") from None
    except OSError as err:
        if err.errno not in NO_HARD_LINKS:
            raise
        if path.exists():
            raise FileExistsError(f"{path} exists; pass overwrite=true to replace it") from None
        os.replace(tmp, path)


NO_HARD_LINKS = (errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.EMLINK)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Like :func:`atomic_write_text`, for bytes (:func:`atomic_target`)."""
    with atomic_target(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def atomic_write_png(path: str | os.PathLike, image: np.ndarray, compression: int | None = None) -> Path:
    """``image`` (8 or 16 bits, 1, 3 or 4 channels, OpenCV's BGR order) as a PNG file, written atomically
    (:func:`atomic_write_bytes`); ``compression``: zlib's level 0-9 (OpenCV's default 1 without)."""
    import cv2

    flags = [] if compression is None else [cv2.IMWRITE_PNG_COMPRESSION, int(compression)]
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image), flags)
    if not ok:
        raise OSError(f"{path}: could not encode a {image.shape} {image.dtype} image as PNG")
    return atomic_write_bytes(path, encoded.tobytes())


def atomic_write_npy(path: str | os.PathLike, array) -> Path:
    """``array`` as a float32 ``.npy`` file, written atomically (:func:`atomic_write_bytes`)."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array, dtype=np.float32))
    return atomic_write_bytes(path, buffer.getvalue())


@contextlib.contextmanager
def staged_folder(out: str | os.PathLike, label: str):
    """A hidden folder beside ``out`` (the same filesystem, so the final move is a rename) in which an
    importer builds ``out``, with a plain folder's permissions (not ``mkdtemp``'s private 0700); removed
    with whatever is left in it when the block ends, however it ends, and so are the folders above
    ``out`` that it created, when the block leaves no ``out`` in them."""
    out = Path(out)
    created = [p for p in (out.parent, *out.parent.parents) if not p.exists()]  # deepest first
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.{label}-", dir=out.parent))
    try:
        staging.chmod(0o777 & ~current_umask())
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if not os.path.lexists(out):
            for folder in created:
                with contextlib.suppress(OSError):  # not empty: something else was put there meanwhile
                    folder.rmdir()


def move_into_place(staging: Path, out: Path, parts: list[Path], overwrite: bool = False) -> None:
    """The finished ``staging`` folder becomes ``out`` (one rename), or, where ``out`` holds other files
    already, its ``parts`` (paths relative to both, in order) replace theirs: a folder part whole, so no
    stale file of an earlier import stays; put last the file that marks ``out`` complete.

    A part that exists in ``out`` now (another command may have written it since the caller checked)
    is replaced only with ``overwrite`` (a ``FileExistsError`` otherwise, before anything moves). The
    replaced files are set aside inside ``staging`` until every part is in place; a part that cannot be
    moved puts back what was there and takes away what was moved, so ``out`` is as it was."""
    if not out.exists() or not any(out.iterdir()):
        try:
            os.replace(staging, out)
            return
        except OSError:  # filled since: part by part, as below
            if not out.is_dir() or not any(out.iterdir()):
                raise
    for part in parts:
        inside(out, out / part, out)
    taken = [out / part for part in parts if os.path.lexists(out / part)]
    if taken and not overwrite:
        raise FileExistsError(f"{taken[0]} exists; pass overwrite=True (--overwrite) to replace it")
    aside = Path(tempfile.mkdtemp(prefix=".replaced-", dir=staging))  # a name no part can have
    moved: list[tuple[Path, Path | None]] = []  # (part, where its old file was set aside)
    made: list[Path] = []  # folders created for the parts, deepest first
    try:
        for i, part in enumerate(parts):
            target = out / part
            made = [p for p in target.parents if not p.exists()] + made
            target.parent.mkdir(parents=True, exist_ok=True)
            old = None
            if os.path.lexists(target):  # a folder cannot replace a non-empty one: set the old one aside
                old = aside / str(i)
                os.rename(target, old)
            moved.append((part, old))
            os.replace(staging / part, target)
    except BaseException:
        for part, old in reversed(moved):
            if os.path.lexists(out / part) and not os.path.lexists(staging / part):
                os.replace(out / part, staging / part)
            if old is not None:
                os.rename(old, out / part)
        for folder in made:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise


# ------------------------------------------------------------------ locks
def same_file(fd: int, path: str | os.PathLike) -> bool:
    """Whether the open descriptor ``fd`` is the file at ``path`` now (not one removed meanwhile)."""
    try:
        return os.fstat(fd).st_ino == os.stat(path).st_ino
    except FileNotFoundError:
        return False


def take_lock(lock: str | os.PathLike, wait: bool = False) -> int:
    """The one lock of the package's writers: the lock file ``lock`` opened (created) and held with
    ``flock``, its descriptor returned. ``wait``: wait for a holder to let it go; otherwise a holder is a
    ``BlockingIOError``. The kernel lets a lock go when its process ends, however it ends, so a killed
    writer's lock file is taken over, never waited on; a lock file its holder removed while this one
    waited is not held but opened again. Released with :func:`drop_lock`."""
    while True:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise
        if same_file(fd, lock):
            return fd
        os.close(fd)


def drop_lock(fd: int, lock: str | os.PathLike) -> None:
    """Let go of a lock :func:`take_lock` took: its file removed (while still the one held), then closed."""
    if same_file(fd, lock):
        Path(lock).unlink()
    os.close(fd)


@contextlib.contextmanager
def locked(lock: str | os.PathLike, wait: bool = False) -> Iterator[int]:
    """:func:`take_lock` for the duration of a ``with`` block, :func:`drop_lock` at its end."""
    fd = take_lock(lock, wait)
    try:
        yield fd
    finally:
        drop_lock(fd, lock)


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def file_key(path: str | os.PathLike, *extra: str) -> str:
    """A cache key for a file's current content, cheap to compute: its resolved path, size and
    modification time (and ``extra``). A file replaced in place gets a new key, unless it keeps both its
    size and its modification time (``cp -p``, ``rsync -t``): delete the cache entry then."""
    path = Path(path)
    stat = path.stat()
    ident = "|".join((str(path.resolve()), str(stat.st_size), str(stat.st_mtime_ns), *extra))
    return hashlib.sha1(ident.encode()).hexdigest()[:20]


def remove_stale_temporaries(folder: str | os.PathLike, target: str = "*") -> list[Path]:
    """Remove the temporaries :func:`temporary_beside` left in ``folder`` (``.NAME.<random>.<pid>.tmp``)
    for the targets whose name matches the glob ``target``, written by processes that no longer run
    (killed: SIGKILL, a power cut); a live writer's are kept. Returns those removed, in order."""
    folder = Path(folder)
    removed = []
    for tmp in sorted(folder.glob(f".{target}.*.tmp")) if folder.is_dir() else []:
        pid = tmp.name[: -len(".tmp")].rsplit(".", 1)[-1]
        if pid.isdigit() and not pid_alive(int(pid)):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed
