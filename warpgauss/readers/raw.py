"""Raw binary (``NAME_XxYxZ_DTYPE.raw`` or explicit shape and dtype) and ``.npy``, memory-mapped."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult, byte_order, first_line, fmt_xyz, parse_raw_name, resolve_dtype, resolve_shape

# --------------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------------


def read_raw(path: Path, *, shape=None, dtype=None, endian=None, **_) -> ReadResult:
    """Headerless binary, C-order ``[z, y, x]``; shape and dtype from the name or the options."""
    parsed = parse_raw_name(path.name)
    if (shape is None or dtype is None) and parsed is None:
        raise WarpgaussError(
            f"cannot tell the shape and dtype of {path.name}: name it NAME_XxYxZ_DTYPE{path.suffix or '.raw'} "
            f"(e.g. vol_256x256x128_float32.raw) or pass --shape XxYxZ and --dtype"
        )
    shape_xyz = resolve_shape(shape) if shape is not None else parsed[0]  # type: ignore[index]
    base = resolve_dtype(dtype) if dtype is not None else parsed[1]  # type: ignore[index]
    # numpy's stubs take only literal byte-order codes; byte_order returns "<" or ">"
    dt = base.newbyteorder(byte_order(endian))  # type: ignore[arg-type]
    nx, ny, nz = shape_xyz
    if min(shape_xyz) < 1:
        raise WarpgaussError(f"{path.name} names an empty grid {fmt_xyz(shape_xyz)}; every axis needs at least 1 voxel")
    need = nx * ny * nz * dt.itemsize
    have = path.stat().st_size
    if have != need:
        raise WarpgaussError(f"{path.name} holds {have} bytes but {fmt_xyz(shape_xyz)} {base.name} needs {need}; check --shape/--dtype")
    return ReadResult(np.memmap(path, dtype=dt, mode="r", shape=(nz, ny, nx)))


def read_npy(path: Path, **_) -> ReadResult:
    """numpy ``.npy`` (memory-mapped, no pickle); the array must be ``[z, y, x]``."""
    try:
        data = np.load(path, allow_pickle=False, mmap_mode="r")
    except (ValueError, OSError, EOFError) as e:
        raise WarpgaussError(f"cannot read {path.name} as a .npy array ({first_line(e)}); save it with numpy.save") from e
    return ReadResult(data)
