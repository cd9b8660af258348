"""Crash-safe file writing: write to a temporary name in the same directory, then rename.

An interrupted run never leaves a half-written file under the final name, because
``os.replace`` within one file system is atomic; every write is checked, so a full disk
raises ``OSError`` instead of leaving an empty or truncated file behind. Commands check their
outputs before the work (:func:`check_output_dir`, :func:`check_output_file`), so that a bad
``--out`` does not cost the computation.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from don_gym.errors import DonGymError

# File systems without hard links (some FUSE and SMB mounts) answer os.link with one of these.
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOSYS, errno.EXDEV}


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None, *, exclusive: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it to ``path``.

    ``suffix`` defaults to the suffix of ``path`` so that writers that pick a format
    from the extension (PNG, NPZ) still do. On an exception the temporary file is removed.
    ``exclusive``: publish only if ``path`` does not exist yet, else raise FileExistsError, so
    that of several processes (or machines sharing a file system) racing to create the file
    exactly one succeeds and nobody replaces what another wrote.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{path.name}.partial-", suffix=path.suffix if suffix is None else suffix, dir=path.parent
    )
    os.close(fd)
    tmp = Path(tmp_name)
    # mkstemp creates owner-only files; give the result the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    try:
        yield tmp
        if exclusive:
            _link_new(tmp, path)
        else:
            os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is not None or exc.errno is None:
            raise
        # A failed write() names no file ("[Errno 28] No space left on device"): name the one we wrote.
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def _link_new(tmp: Path, path: Path) -> None:
    # A hard link fails if the name exists, atomically, also on NFS: the classic lock-file idiom.
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        if path.exists():
            raise FileExistsError(errno.EEXIST, "file exists", str(path)) from None
        os.replace(tmp, path)


def write_bytes_atomic(path: str | Path, data: bytes, *, exclusive: bool = False) -> None:
    with atomic_path(path, exclusive=exclusive) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str, *, exclusive: bool = False) -> None:
    with atomic_path(path, exclusive=exclusive) as tmp:
        tmp.write_text(text)


def encode_png(image: np.ndarray, name: str | Path = "image") -> bytes:
    """PNG bytes of a uint8/uint16 (H, W) or (H, W, 3) BGR image; OSError if OpenCV cannot encode it."""
    import cv2

    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok or buffer is None or buffer.size == 0:
        raise OSError(
            errno.EIO, f"could not encode PNG (shape {np.shape(image)}, dtype {np.asarray(image).dtype})", str(name)
        )
    return buffer.tobytes()


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write ``image`` (OpenCV's BGR order) as a PNG atomically; raises OSError on any failure.

    Encodes in memory and writes with Python's file I/O, whose errors (ENOSPC, EIO, EFBIG)
    raise: ``cv2.imwrite`` only returns False, and a caller that forgets to check it keeps an
    empty or truncated file.
    """
    write_bytes_atomic(path, encode_png(image, path))


def check_output_dir(path: str | Path, option: str = "--out") -> Path:
    """Refuse, before any work, a directory that outputs cannot be written into; return it as a Path.

    Refused: a file in its place or on its way, and a nearest existing folder where no file can be
    created (read-only mount, no permission). Creates nothing. ``option`` names the input in the
    :class:`~don_gym.errors.DonGymError`.
    """
    return _check_output(path, option, directory=True)


def check_output_file(path: str | Path, option: str = "--out", suffixes: tuple[str, ...] = ()) -> Path:
    """Like :func:`check_output_dir` for one output file (new, or a regular file to replace), whose
    name must end in one of ``suffixes`` (any if empty, case-insensitive)."""
    if suffixes and path and Path(path).suffix.lower() not in suffixes:
        raise DonGymError(f"{option} {str(path)!r}: expected a file name ending in {', '.join(suffixes)}")
    return _check_output(path, option, directory=False)


def _check_output(path: str | Path, option: str, directory: bool) -> Path:
    if path is None or not str(path).strip():
        raise DonGymError(f"{option} {path!r}: expected a path")
    path = Path(path).expanduser()
    wanted = "a directory for the outputs" if directory else "a file name"
    folder = path if directory else path.parent
    try:
        if path.exists():
            if directory and not path.is_dir():
                raise DonGymError(f"{option} {path}: exists and is not a directory; expected {wanted}")
            if not directory and not path.is_file():
                # A device or FIFO would be replaced by the rename, not written to.
                what = "a directory" if path.is_dir() else "not a regular file"
                raise DonGymError(f"{option} {path}: is {what}; expected {wanted}")
        while not folder.exists():
            if folder.is_symlink():
                raise DonGymError(f"{option} {path}: {folder} is a broken symbolic link")
            folder = folder.parent
        if not folder.is_dir():
            raise DonGymError(f"{option} {path}: {folder} is a file, so no directory can be made there")
        # Try what the real write will do: permissions, ACLs and read-only mounts all answer as they will then.
        fd, probe = tempfile.mkstemp(prefix=".don_gym-write-check-", dir=folder)
    except OSError as exc:
        raise DonGymError(f"{option} {path}: cannot write in {folder}: {exc.strerror or exc}") from None
    os.close(fd)
    os.unlink(probe)
    return path


#: The lock file of a directory that don_gym writes (a dataset, a training run); it holds no data.
LOCK_FILE = ".lock"


class DirectoryLock:
    """Advisory POSIX byte-range locks (``fcntl.lockf``) on ``DIR/.lock`` between the processes of one machine
    that write one directory, released by the kernel when a process dies.

    A process never conflicts with its own locks, and closing any descriptor of the file drops all of them:
    use one instance per process and directory. On a file system without locks (some NFS set-ups) every
    lock is granted, so callers keep their files correct without them (atomic writes and renames).
    """

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self._fd: int | None = os.open(self.root / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o666)

    def lock(self, byte: int, mode: int, blocking: bool = True) -> bool:
        """Lock byte ``byte`` of the file in ``mode`` (``fcntl.LOCK_SH``, ``LOCK_EX`` or ``LOCK_UN``); False
        when ``blocking`` is False and another process holds a conflicting lock."""
        assert self._fd is not None, "lock used after close()"
        try:
            fcntl.lockf(self._fd, mode if blocking else mode | fcntl.LOCK_NB, 1, byte)
        except OSError as exc:
            if exc.errno in (errno.EACCES, errno.EAGAIN):
                return False
            if exc.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                return True
            raise
        return True

    def close(self) -> None:
        """Release every lock of this process on the file."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
