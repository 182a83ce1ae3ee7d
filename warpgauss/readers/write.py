"""Writers: ``.vti``, ``.npy``, ``.raw``, ``.h5``/``.hdf5`` and NIfTI-1 ``.nii``/``.nii.gz``, atomically."""

from __future__ import annotations

import gzip
import os
import re
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..core.files import atomic_path, check_writable
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


# NIfTI-1 (https://nifti.nimh.nih.gov/nifti-1): a 348-byte header, 4 bytes of no extension, then
# the voxels x fastest (a C-order (z, y, x) array as it is), little-endian
NIFTI_HEADER = struct.Struct("<i10s18sihbb8h3f4h8f3fhbb4f2i80s24s2h3f3f4f4f4f16s4s")
NIFTI_DATATYPES = {
    "uint8": 2,
    "int16": 4,
    "int32": 8,
    "float32": 16,
    "float64": 64,
    "int8": 256,
    "uint16": 512,
    "uint32": 768,
    "int64": 1024,
    "uint64": 1280,
}
NIFTI_MAX_DIM = 32767  # dim[] are signed 16-bit


def nifti_problem(shape_xyz) -> str | None:
    """Why a grid of this shape cannot be a NIfTI-1 file (an axis beyond 32,767 voxels), or None."""
    if max(int(v) for v in shape_xyz) > NIFTI_MAX_DIM:
        return f"a NIfTI-1 file holds at most {NIFTI_MAX_DIM:,} voxels an axis, the grid is {'x'.join(str(int(v)) for v in shape_xyz)}; write .h5 or .npy"
    return None


def nifti_header(shape_zyx, dtype: np.dtype, spacing, origin, name: str) -> bytes:
    """The 352 bytes before a NIfTI-1 file's voxels: dimensions, datatype, voxel size, and the
    origin as the qform's and sform's offset (no rotation), the array's name as its description."""
    nz, ny, nx = (int(v) for v in shape_zyx)
    dx, dy, dz = (float(v) for v in spacing)
    ox, oy, oz = (float(v) for v in origin)
    head = NIFTI_HEADER.pack(
        348, b"", b"", 0, 0, ord("r"), 0,  # sizeof_hdr, data_type, db_name, extents, session_error, regular, dim_info
        *(3, nx, ny, nz, 1, 1, 1, 1),  # dim
        0.0, 0.0, 0.0, 0,  # intent_p1..3, intent_code
        NIFTI_DATATYPES[dtype.name], 8 * dtype.itemsize, 0,  # datatype, bitpix, slice_start
        *(1.0, dx, dy, dz, 1.0, 1.0, 1.0, 1.0),  # pixdim (qfac 1)
        352.0, 1.0, 0.0,  # vox_offset, scl_slope, scl_inter: the values as stored
        0, 0, 0,  # slice_end, slice_code, xyzt_units (unknown: the grid's spacing has no unit)
        0.0, 0.0, 0.0, 0.0, 0, 0,  # cal_max, cal_min, slice_duration, toffset, glmax, glmin
        name.encode("ascii", "replace")[:79], b"warpgauss",  # descrip, aux_file
        1, 1,  # qform_code, sform_code: scanner coordinates
        0.0, 0.0, 0.0, ox, oy, oz,  # quatern_b..d (no rotation), qoffset
        *(dx, 0.0, 0.0, ox), *(0.0, dy, 0.0, oy), *(0.0, 0.0, dz, oz),  # srow_x, srow_y, srow_z
        b"", b"n+1\0",
    )  # fmt: skip
    return head + b"\0\0\0\0"


def _write_nifti(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    if data.dtype == np.float16:  # NIfTI-1 has no half precision
        data = data.astype(np.float32)
    problem = nifti_problem(data.shape[::-1])
    if problem is not None:
        raise WarpgaussError(problem)
    data = np.ascontiguousarray(data, dtype=data.dtype.newbyteorder("<"))
    gz = tmp.name.lower().endswith(".gz")
    with open(tmp, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", compresslevel=6, mtime=0) if gz else raw as fh:
        fh.write(nifti_header(data.shape, data.dtype, spacing, origin, name))
        for z in range(data.shape[0]):  # a slab at a time: no second copy of the grid
            fh.write(data[z].tobytes())


#: File extension -> writer(temp_path, data, spacing, origin, name).
WRITERS: dict[str, Callable[..., None]] = {
    ".vti": _write_vti,
    ".npy": _write_npy,
    ".raw": _write_raw,
    ".h5": _write_hdf5,
    ".hdf5": _write_hdf5,
    ".nii": _write_nifti,
    ".nii.gz": _write_nifti,
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
    with ``spacing`` and ``origin`` attributes ``(x, y, z)``. ``.nii``/``.nii.gz``: NIfTI-1 with
    the voxel size and the origin (qform and sform offsets, no rotation), as the readers take it
    back (they read the voxel size; the origin is for other tools); half precision as float32.

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
