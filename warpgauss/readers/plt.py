"""gOpenMol ``.plt`` grids."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult


def read_plt(path: Path, **_) -> ReadResult:
    """gOpenMol ``.plt``: 5 int32 (rank=3, surface type, nz, ny, nx) + 6 float32 (zmin, zmax,
    ymin, ymax, xmin, xmax) header, then float32 with x fastest.

    min/max are taken as the outer edges of the grid (as gridData reads them): spacing =
    (max - min) / n and the first voxel centre sits at min + spacing / 2.
    """
    with open(path, "rb") as fh:
        head = fh.read(44)
    if len(head) < 44:
        raise WarpgaussError(f"{path.name} is {len(head)} bytes, shorter than the 44-byte gOpenMol .plt header")
    e = next((e for e in ("<", ">") if int(np.frombuffer(head, e + "i4", count=1)[0]) == 3), None)
    if e is None:
        raise WarpgaussError(f"{path.name} does not start with rank 3 in either byte order; it is not a 3D gOpenMol .plt file")
    nz, ny, nx = (int(v) for v in np.frombuffer(head, e + "i4", count=5)[2:5])
    zmin, zmax, ymin, ymax, xmin, xmax = (float(v) for v in np.frombuffer(head, e + "f4", offset=20, count=6))
    if min(nx, ny, nz) < 1:
        raise WarpgaussError(f"{path.name} has an empty grid {nx}x{ny}x{nz}")
    need = 44 + nx * ny * nz * 4
    have = path.stat().st_size
    if have != need:
        raise WarpgaussError(f"{path.name} holds {have} bytes but a {nx}x{ny}x{nz} float32 .plt needs {need}; the file is damaged")
    data = np.memmap(path, dtype=e + "f4", mode="r", offset=44, shape=(nz, ny, nx))
    spacing = tuple(_plt_step(lo, hi, n) for lo, hi, n in ((xmin, xmax, nx), (ymin, ymax, ny), (zmin, zmax, nz)))
    origin = tuple(lo + d / 2 for lo, d in zip((xmin, ymin, zmin), spacing))
    return ReadResult(data, spacing=spacing, origin=origin)  # type: ignore[arg-type]


def _plt_step(lo: float, hi: float, n: int) -> float:
    d = (hi - lo) / n
    return d if np.isfinite(d) and d > 0 else 1.0
