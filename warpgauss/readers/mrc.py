"""MRC/CCP4 maps (plain, ``.gz`` or ``.bz2``), read by our own parser."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult, first_line

_MRC_MODES: dict[int, np.dtype] = {
    0: np.dtype(np.int8),
    1: np.dtype(np.int16),
    2: np.dtype(np.float32),
    6: np.dtype(np.uint16),
    12: np.dtype(np.float16),
}


def read_mrc(path: Path, **_) -> ReadResult:
    """MRC2014 / CCP4 density maps, optionally ``.gz`` or ``.bz2`` compressed.

    1024-byte header, NSYMBT extended-header bytes skipped, MODE gives the dtype, axes permuted by
    MAPC/MAPR/MAPS into ``[z, y, x]``. Voxel size = CELLA / (MX, MY, MZ). Origin = the MRC2014
    ORIGIN field if non-zero, else the grid start (NCSTART, NRSTART, NSSTART) times the voxel size.
    The cell angles are ignored (a non-orthogonal cell is read as if it were orthogonal).
    """
    blob = _decompressed(path)  # None: an uncompressed file, memory-mapped below
    if blob is None:
        with open(path, "rb") as fh:
            head = fh.read(1024)
        size = path.stat().st_size
    else:
        head, size = blob[:1024], len(blob)
    if len(head) < 1024:
        raise WarpgaussError(f"{path.name} holds {len(head)} bytes, less than the 1024-byte MRC/CCP4 header")
    e = _mrc_byte_order(head)
    ints = np.frombuffer(head, dtype=e + "i4")
    floats = np.frombuffer(head, dtype=e + "f4")
    nx, ny, nz, mode = (int(v) for v in ints[0:4])
    mapcrs = _mrc_axis_map(path, ints[16:19])
    # numpy's stubs take only literal byte-order codes; _mrc_byte_order returns "<" or ">"
    dt = _mrc_dtype(path, mode).newbyteorder(e)  # type: ignore[arg-type]
    if min(nx, ny, nz) < 1:
        raise WarpgaussError(f"{path.name} has an empty MRC grid {nx}x{ny}x{nz} (columns x rows x sections)")
    offset = 1024 + max(int(ints[23]), 0)
    need = nx * ny * nz * dt.itemsize
    if size - offset < need:
        raise WarpgaussError(
            f"{path.name} holds {max(size - offset, 0)} bytes of data but its header "
            f"({nx}x{ny}x{nz}, MODE {mode}) needs {need}; the file is truncated"
        )
    data: np.ndarray  # a memmap of the file, or a view of the decompressed bytes
    if blob is None:
        data = np.memmap(path, dtype=dt, mode="r", offset=offset, shape=(nz, ny, nx))
    else:
        data = np.frombuffer(blob, dtype=dt, count=nx * ny * nz, offset=offset).reshape(nz, ny, nx)
    # File axes [section, row, column] run along the crystal axes MAPS, MAPR, MAPC (1 = x, 2 = y, 3 = z).
    file_axes = (mapcrs[2], mapcrs[1], mapcrs[0])
    data = data.transpose(file_axes.index(3), file_axes.index(2), file_axes.index(1))
    spacing = _mrc_spacing(floats[10:13], ints[7:10], data.shape[::-1])
    return ReadResult(data, spacing=spacing, origin=_mrc_origin(floats[49:52], ints[4:7], mapcrs, spacing))


def _decompressed(path: Path) -> bytes | None:
    """The whole decompressed content of a ``.gz``/``.bz2`` file; None for an uncompressed one."""
    lower = path.name.lower()
    codec: ModuleType
    if lower.endswith(".bz2"):
        import bz2 as codec
    elif lower.endswith(".gz"):
        import gzip as codec
    else:
        return None
    try:
        with codec.open(path, "rb") as fh:
            return fh.read()
    except (OSError, EOFError, ValueError) as e:
        raise WarpgaussError(f"cannot decompress {path.name} ({first_line(e)})") from e


def _mrc_dtype(path: Path, mode: int) -> np.dtype:
    if mode not in _MRC_MODES:
        raise WarpgaussError(
            f"{path.name} has MRC MODE {mode}; warpgauss reads modes 0 (int8), 1 (int16), 2 (float32), "
            f"6 (uint16) and 12 (float16), not complex or packed modes"
        )
    return _MRC_MODES[mode]


def _mrc_axis_map(path: Path, words) -> tuple[int, int, int]:
    mapcrs = tuple(int(v) for v in words)
    if mapcrs == (0, 0, 0):
        return (1, 2, 3)  # some old writers leave the axis map blank
    if sorted(mapcrs) != [1, 2, 3]:
        raise WarpgaussError(f"{path.name} has MAPC/MAPR/MAPS = {mapcrs}, not a permutation of 1, 2, 3; the header is corrupt")
    return mapcrs  # type: ignore[return-value]


def _mrc_origin(origin_words, start_crs, mapcrs, spacing) -> tuple[float, float, float]:
    origin = tuple(float(v) for v in origin_words)
    if any(v != 0 for v in origin) and all(np.isfinite(origin)):
        return origin  # type: ignore[return-value]
    start = [0, 0, 0]
    for axis, value in zip(mapcrs, start_crs):
        start[axis - 1] = int(value)
    return tuple(float(s * d) for s, d in zip(start, spacing))  # type: ignore[return-value]


def _mrc_byte_order(head: bytes) -> str:
    """'<' or '>' from MACHST (bytes 212-213), else from which order gives a plausible MODE and axis map."""
    if head[212] == 0x44:
        return "<"
    if head[212] == 0x11:
        return ">"
    for e in ("<", ">"):
        ints = np.frombuffer(head, dtype=e + "i4")
        if 0 <= ints[3] <= 16 and sorted(int(v) for v in ints[16:19]) in ([1, 2, 3], [0, 0, 0]):
            return e
    return "<"


def _mrc_spacing(cella, sampling, shape_xyz) -> tuple[float, float, float]:
    """CELLA / (MX, MY, MZ) per axis, falling back to the grid size for MX and to 1 for a zero cell."""
    out = []
    for cell, m, n in zip(cella, sampling, shape_xyz):
        m = int(m) if int(m) > 0 else int(n)
        out.append(float(cell) / m if np.isfinite(cell) and cell > 0 else 1.0)
    return tuple(out)  # type: ignore[return-value]
