"""Writing output files so that a crash or a full disk never leaves a torn or emptied file.

* :func:`write_atomic`: the whole file to a temporary name in the same folder, fsync, rename over
  the target. A failure (``ENOSPC``...) removes the temporary file and leaves the previous version
  of the target as it was (``map.json``, state files, checkpoints).
* :class:`AppendFile`: an append-only file written row by row (``trajectory.tum``,
  ``templates.csv``). Every :meth:`AppendFile.append` reaches the operating system before it
  returns (a killed process loses nothing it appended), and a failed append is cut back to the
  previous size, so the file always ends with complete rows.

Every byte goes through :func:`write_all`, the one place tests replace to simulate a full disk.
"""

from __future__ import annotations

import errno
import os
from pathlib import Path


def write_all(fd: int, data: bytes) -> None:
    """Write every byte of ``data`` to ``fd`` (``os.write`` may write less than asked)."""
    view = memoryview(data)
    while view:
        n = os.write(fd, view)
        view = view[n:]


def describe_write_error(path: str | os.PathLike, exc: OSError) -> str:
    """One line for the log: ``disk full writing PATH: ...`` for ENOSPC / EDQUOT."""
    what = "disk full writing" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else "cannot write"
    return f"{what} {os.fspath(path)}: {exc}"


def write_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Replace ``path`` by ``data`` atomically (temporary file, fsync, rename). On failure the
    temporary file is removed, the previous ``path`` is untouched and the OSError is raised."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        try:
            write_all(fd, data)
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


class AppendFile:
    """An append-only output file; see the module docstring. ``truncate=True`` starts it empty."""

    def __init__(self, path: str | os.PathLike, truncate: bool = False) -> None:
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if truncate else 0)
        self.fd = os.open(self.path, flags, 0o644)
        self.size = os.fstat(self.fd).st_size

    def append(self, data: bytes) -> None:
        """Append ``data`` whole, or raise OSError with the file cut back to its previous size."""
        try:
            write_all(self.fd, data)
        except OSError:
            self.cut(self.size)
            raise
        self.size += len(data)

    def cut(self, size: int) -> None:
        """Shorten the file to ``size`` bytes (best effort: truncating frees space, so it works on a
        full disk)."""
        try:
            os.ftruncate(self.fd, size)
            self.size = size
        except OSError:
            pass

    def sync(self) -> None:
        os.fsync(self.fd)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


def complete_lines(path: str | os.PathLike) -> list[bytes]:
    """The newline-terminated lines of ``path`` (a torn last line, written when the writer died, is
    left out); [] when it does not exist."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        return []
    end = data.rfind(b"\n")
    return data[: end + 1].splitlines(keepends=True) if end >= 0 else []
