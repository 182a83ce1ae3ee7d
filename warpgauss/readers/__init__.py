"""Read and write 3D scalar volumes: one module per format family, chosen by extension here.

Readers are chosen by file extension from :data:`READERS` (pyvista style: an extension-to-reader
table, early one-line errors). The full suffix decides, so ``.nii.gz`` and ``.map.bz2`` pick their
own readers. Heavy libraries (pyvista, h5py, scipy) are imported inside the readers that need them.

Conventions:
    * Arrays are indexed ``[z, y, x]`` (x fastest in memory, as raw scientific files store them).
      Shapes shown to users and in file names are ``XxYxZ``; spacing and origin are ``(x, y, z)``.
    * Values come back in the source dtype (uint8, int16, float32, ...), never normalised and
      with NaN and fill values left in place: the caller masks and normalises. Non-native byte
      order is swapped to native order (this copies the strided voxels into memory).
    * ``data`` may be a read-only ``np.memmap`` or a strided view of one; call
      ``np.ascontiguousarray`` before handing it to code that needs a contiguous buffer.

Formats read: raw binary named ``NAME_XxYxZ_DTYPE.raw`` (or ``--shape``/``--dtype``), ``.npy``,
HDF5, classic netCDF (netCDF-4 goes through the HDF5 reader), VTK ImageData (``.vti``, legacy
``.vtk``), NIfTI, MetaImage and NRRD (through pyvista), MRC/CCP4 (plain, ``.gz`` or ``.bz2``) and
gOpenMol ``.plt``. Formats written: ``.vti``, ``.npy``, ``.raw`` and ``.h5``/``.hdf5``.

Beside the readers: :class:`ReadOptions` (how stage P reads a file), volumes read on demand
(:mod:`.lazy`, out of core) and the built-in example volumes (:mod:`.synthetic`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import WarpgaussError
from .common import MAX_READ_VOXELS, ReaderSpec, Volume, check_options, check_stride, finish_read, match_suffix, parse_raw_name
from .hdf5 import read_hdf5, read_netcdf
from .mrc import read_mrc
from .plt import read_plt
from .raw import read_npy, read_raw
from .vtk import read_pyvista
from .write import WRITERS, write_volume
from .zarr import read_zarr

_RAW_OPTS = frozenset({"shape", "dtype", "endian"})
_H5_OPTS = frozenset({"dataset", "variable"})

#: File extension (lower case, full suffix) -> reader. The longest matching suffix wins.
READERS: dict[str, ReaderSpec] = {
    ".raw": ReaderSpec(read_raw, _RAW_OPTS, "raw binary"),
    ".bin": ReaderSpec(read_raw, _RAW_OPTS, "raw binary"),
    ".npy": ReaderSpec(read_npy, frozenset(), "numpy"),
    ".h5": ReaderSpec(read_hdf5, _H5_OPTS, "HDF5"),
    ".hdf5": ReaderSpec(read_hdf5, _H5_OPTS, "HDF5"),
    ".hdf": ReaderSpec(read_hdf5, _H5_OPTS, "HDF5"),
    ".nc": ReaderSpec(read_netcdf, _H5_OPTS, "netCDF"),
    ".cdf": ReaderSpec(read_netcdf, _H5_OPTS, "netCDF"),
    **{
        ext: ReaderSpec(read_pyvista, frozenset(), "VTK/medical image")
        for ext in (".vti", ".vtk", ".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
    },
    **{base + comp: ReaderSpec(read_mrc, frozenset(), "MRC/CCP4") for base in (".mrc", ".map", ".ccp4") for comp in ("", ".gz", ".bz2")},
    ".plt": ReaderSpec(read_plt, frozenset(), "gOpenMol plt"),
    ".zarr": ReaderSpec(read_zarr, frozenset({"dataset"}), "Zarr store"),
}


def supported_extensions() -> list[str]:
    """File extensions :func:`read_volume` understands, sorted."""
    return sorted(READERS)


def writable_extensions() -> list[str]:
    """File extensions :func:`write_volume` can write, sorted."""
    return sorted(WRITERS)


# --------------------------------------------------------------------------------------------------
# read_volume
# --------------------------------------------------------------------------------------------------


def read_volume(
    path: str | os.PathLike,
    *,
    shape: tuple[int, int, int] | None = None,
    dtype=None,
    endian: str | None = None,
    dataset: str | None = None,
    variable: str | None = None,
    stride: int = 1,
    lazy: bool = False,
    max_voxels: int | None = None,
) -> Volume:
    """Read a 3D scalar volume; the reader is chosen by the file's extension.

    Args:
        path: Volume file; see :func:`supported_extensions`.
        shape: Raw files only: grid size ``(x, y, z)`` when the name does not carry it.
        dtype: Raw files only: ``uint8``, ``int8``, ``uint16``, ``int16``, ``uint32``, ``int32``,
            ``float32`` (``float``), ``float64`` (``double``).
        endian: Raw files only: ``"little"`` (default) or ``"big"``.
        dataset: HDF5 (and netCDF-4): dataset path; default: the first 3D dataset in visit order.
        variable: netCDF: variable name; default: the first 3D variable.
        stride: Keep every ``stride``-th voxel on each axis (``data[::s, ::s, ::s]``); spacing is
            multiplied by it.
        lazy: Leave the voxels in the file where the format allows (raw, ``.npy`` and HDF5 /
            netCDF-4 datasets, stride 1; see :mod:`warpgauss.readers.lazy`): ``data`` is then memory-mapped
            or read on demand, in the file's byte order.
        max_voxels: The most voxels a format read into memory may declare (None:
            :data:`MAX_READ_VOXELS`, what an encode with the volume on the device indexes).

    Returns:
        The :class:`Volume`, values in the source dtype, NaN and fill values untouched.

    Raises:
        WarpgaussError: Missing file, unknown extension, an option the format does not take,
            a size that does not match the header or name, or data that is not a 3D real array.
    """
    p = Path(path)
    if not p.exists():
        raise WarpgaussError(f"no such file: {p}")
    if p.is_dir() and not p.name.lower().endswith(".zarr"):
        raise WarpgaussError(f"{p} is a directory; give a volume file (or a .zarr store)")
    suffix = match_suffix(p.name, READERS, "read")
    reader = READERS[suffix]
    s = check_stride(stride)
    given = {"shape": shape, "dtype": dtype, "endian": endian, "dataset": dataset, "variable": variable}
    check_options(p, reader, [k for k, v in given.items() if v is not None])
    got = reader.func(p, **given, stride=s, lazy=lazy and s == 1, max_voxels=max_voxels)
    return finish_read(p, suffix, got, s, lazy=lazy and s == 1)


__all__ = [
    "MAX_READ_VOXELS",
    "READERS",
    "WRITERS",
    "ReadOptions",
    "Volume",
    "parse_raw_name",
    "read_volume",
    "supported_extensions",
    "writable_extensions",
    "write_volume",
]


@dataclass
class ReadOptions:
    """How to read a file source (see :func:`read_volume`)."""

    shape: tuple[int, int, int] | None = None
    dtype: str | None = None
    endian: str | None = None
    dataset: str | None = None
    variable: str | None = None
    stride: int = 1
    fill_value: float | None = None

    def read(self, path, lazy: bool = False, max_voxels: int | None = None):
        """Read a volume file with these options (:func:`read_volume`)."""
        return read_volume(
            path,
            lazy=lazy,
            max_voxels=max_voxels,
            shape=self.shape,
            dtype=self.dtype,
            endian=self.endian,
            dataset=self.dataset,
            variable=self.variable,
            stride=self.stride,
        )
