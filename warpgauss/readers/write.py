"""Writers: ``.vti``, ``.npy``, ``.raw`` and ``.h5``/``.hdf5``, atomically."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np

from .._fs import atomic_path, check_writable
from ..errors import WarpgaussError
from .common import check_dtype, check_shape, match_suffix

# --------------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------------


def image_data(data: np.ndarray, spacing, origin, name: str):
    """A (nz, ny, nx) grid as VTK ImageData (pyvista) with point array ``name`` (x fastest)."""
    import pyvista as pv

    if data.dtype == np.float16:  # VTK has no half-precision arrays
        data = data.astype(np.float32)
    nz, ny, nx = data.shape
    grid = pv.ImageData(dimensions=(nx, ny, nz), spacing=spacing, origin=origin)
    grid.point_data[name] = data.transpose(2, 1, 0).ravel(order="F")  # x fastest
    return grid


def _write_vti(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    image_data(data, spacing, origin, name).save(tmp)


def _write_npy(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    with open(tmp, "wb") as fh:
        np.save(fh, np.ascontiguousarray(data), allow_pickle=False)


def _write_raw(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<")).tofile(tmp)


def _write_hdf5(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    import h5py

    with h5py.File(tmp, "w") as f:
        ds = f.create_dataset("volume", data=np.ascontiguousarray(data))
        ds.attrs["spacing"] = np.asarray(spacing, dtype=np.float64)
        ds.attrs["origin"] = np.asarray(origin, dtype=np.float64)
        ds.attrs["name"] = name
        ds.attrs["axis_order"] = "zyx"


#: File extension -> writer(temp_path, data, spacing, origin, name).
WRITERS: dict[str, Callable[..., None]] = {
    ".vti": _write_vti,
    ".npy": _write_npy,
    ".raw": _write_raw,
    ".h5": _write_hdf5,
    ".hdf5": _write_hdf5,
}


def write_volume(
    path: str | os.PathLike,
    data_zyx: np.ndarray,
    *,
    spacing=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    name: str = "value",
    force: bool = False,
) -> Path:
    """Write a 3D array ``[z, y, x]`` atomically, in the format its extension names.

    ``.vti``: VTK ImageData with point array ``name`` (x fastest), spacing and origin. ``.npy``:
    the array as is. ``.raw``: little-endian, C-order, native dtype, no header (name the file
    ``NAME_XxYxZ_DTYPE.raw`` so that it can be read back). ``.h5``/``.hdf5``: dataset ``volume``
    with ``spacing`` and ``origin`` attributes ``(x, y, z)``.

    Args:
        path: Destination; see :func:`writable_extensions`.
        data_zyx: 3D array of real numbers, indexed ``[z, y, x]``.
        spacing: Voxel size ``(x, y, z)``.
        origin: First voxel centre ``(x, y, z)``.
        name: Array name inside ``.vti`` files (and an attribute in HDF5).
        force: Replace an existing file.

    Returns:
        The written path.
    """
    p = Path(path)
    suffix = match_suffix(p.name, WRITERS, "write")
    data = np.asarray(data_zyx)
    check_shape(data.shape, "the array to write")
    check_dtype(data.dtype, "the array to write")
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    spacing_t = _xyz_tuple(spacing, "spacing")
    origin_t = _xyz_tuple(origin, "origin")
    if suffix in (".raw", ".bin"):
        _check_raw_name(p, data)
    check_writable(p, force=force)
    with atomic_path(p) as tmp:
        WRITERS[suffix](tmp, data, spacing_t, origin_t, str(name) or "value")
    return p


def _check_raw_name(p: Path, data: np.ndarray) -> None:
    """A raw file holds no shape or dtype: its name must carry them (``NAME_XxYxZ_DTYPE.raw``), as
    the readers take them back, and agree with the data (a 48^3 volume under a 128^3 name was
    written, and the next command failed on its size)."""
    from .common import parse_raw_name

    nz, ny, nx = data.shape
    want = f"{nx}x{ny}x{nz}_{data.dtype.name}"
    stem = p.name[: -len(p.suffix)]
    base = re.sub(r"_?\d+x\d+x\d+_[A-Za-z0-9]+$", "", stem) or "volume"
    fix = p.with_name(f"{base}_{want}{p.suffix}")
    named = parse_raw_name(p.name)
    if named is None:
        raise WarpgaussError(f"{p.name} does not say the volume's shape and dtype, which a raw file cannot hold; name it {fix.name}")
    (x, y, z), dtype = named
    if (x, y, z) != (nx, ny, nz) or np.dtype(dtype) != data.dtype:
        raise WarpgaussError(
            f"{p.name} says {x}x{y}x{z} {np.dtype(dtype).name} but the volume is {nx}x{ny}x{nz} {data.dtype.name}; name it {fix.name}"
        )


def _xyz_tuple(value, what: str) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(np.isfinite(out)):
        raise WarpgaussError(f"{what} must be three finite numbers (x, y, z), got {value!r}")
    return out  # type: ignore[return-value]
