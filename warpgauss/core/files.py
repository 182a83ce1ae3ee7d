"""Atomic file writes: nothing partial is ever left at the destination."""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path

from ..errors import WarpgaussError


def check_writable(path: str | os.PathLike, *, force: bool = False) -> Path:
    """Validate an output path before any heavy work starts.

    Args:
        path: Destination file.
        force: Allow replacing an existing file.

    Returns:
        The destination as a :class:`~pathlib.Path`.
    """
    p = Path(path)
    if p.exists() and not force:
        raise WarpgaussError(f"{p} already exists; pass --force (force=True from Python) to overwrite it or choose another output path")
    if p.exists() and p.is_dir():
        raise WarpgaussError(f"{p} is a directory; give a file name for the output")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise WarpgaussError(f"output directory {parent} does not exist; create it first")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise WarpgaussError(f"output directory {parent} is not writable; choose another output path")
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary file keeps the destination's suffix so that writers which choose a format from
    the extension (VTK, h5py) behave as they would on the final name.
    """
    dest = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.stem}.", suffix=f".tmp{dest.suffix}", dir=dest.parent or ".")
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give what a plain open() would
        os.replace(tmp, dest)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (temp file + fsync + rename)."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
