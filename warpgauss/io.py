"""Read and write 3D scalar volumes.

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
"""

from __future__ import annotations

import gzip
import math
import os
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ._fs import atomic_path, check_writable
from .errors import WarpgaussError

# --------------------------------------------------------------------------------------------------
# The volume
# --------------------------------------------------------------------------------------------------


@dataclass
class Volume:
    """A 3D scalar volume as read from a file.

    Attributes:
        data: 3D array ``[z, y, x]`` in the source dtype (stride applied; possibly a memmap view).
        spacing: Voxel size ``(x, y, z)`` in the file's physical units, multiplied by the stride.
        origin: Position of the first voxel's centre ``(x, y, z)``.
        name: File name without its extension(s) and without a ``_XxYxZ_dtype`` tail.
        source_dtype: numpy dtype name of the stored values, e.g. ``"uint8"``, ``"float32"``.
        path: The file read, or None.
        fill_value: Value that the file marks as missing data (netCDF/HDF5 ``_FillValue`` or
            ``missing_value`` attribute), or None. The caller masks these voxels.
    """

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    name: str = "volume"
    source_dtype: str = ""
    path: str | None = None
    fill_value: float | None = None

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        """Grid size as ``(nx, ny, nz)``."""
        nz, ny, nx = self.data.shape
        return int(nx), int(ny), int(nz)

    @property
    def source_itemsize(self) -> int:
        """Bytes per voxel of the source dtype (1 for uint8, 2 for int16, 4 for float32...)."""
        try:
            return int(np.dtype(self.source_dtype).itemsize) if self.source_dtype else int(self.data.dtype.itemsize)
        except TypeError:
            return int(self.data.dtype.itemsize)

    @property
    def source_bytes(self) -> int:
        """Voxel count (after stride) times :attr:`source_itemsize` (SPEC section 4's S_src)."""
        return int(self.data.size) * self.source_itemsize


@dataclass
class _Read:
    """What a format reader found, before the common validation, stride and byte-order steps."""

    data: np.ndarray
    spacing: tuple[float, float, float] = (1.0, 1.0, 1.0)
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fill_value: float | None = None
    strided: bool = False  # the reader already applied the stride (HDF5 reads only what is kept)


@dataclass(frozen=True)
class _Reader:
    func: Callable[..., _Read]
    options: frozenset[str]  # keyword options of read_volume this format understands
    what: str


# --------------------------------------------------------------------------------------------------
# Raw file names and dtypes
# --------------------------------------------------------------------------------------------------

_RAW_DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype(np.uint8),
    "int8": np.dtype(np.int8),
    "uint16": np.dtype(np.uint16),
    "int16": np.dtype(np.int16),
    "uint32": np.dtype(np.uint32),
    "int32": np.dtype(np.int32),
    "float32": np.dtype(np.float32),
    "float64": np.dtype(np.float64),
    "float": np.dtype(np.float32),
    "double": np.dtype(np.float64),
}

_RAW_NAME = re.compile(
    r"(?:^|_)(\d+)x(\d+)x(\d+)_(" + "|".join(_RAW_DTYPES) + r")$",
    re.IGNORECASE,
)

_RAW_SUFFIXES = (".raw", ".bin")

MAX_READ_VOXELS = 2**31 - 1  # = warpgauss.analysis.MAX_VOXELS: the kernels index voxels with int32


def parse_raw_name(filename: str | os.PathLike) -> tuple[tuple[int, int, int], np.dtype] | None:
    """Shape and dtype from the open scientific-visualization naming ``name_XxYxZ_dtype.raw``.

    Args:
        filename: A file name or path, e.g. ``"bonsai_256x256x256_uint8.raw"``. A ``.raw`` or
            ``.bin`` extension is optional.

    Returns:
        ``((x, y, z), dtype)`` with a native-order dtype, or None if the name does not follow
        the convention (unknown dtype words such as ``float16`` included).
    """
    stem = Path(filename).name
    for suffix in _RAW_SUFFIXES:
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    m = _RAW_NAME.search(stem)
    if m is None:
        return None
    shape = (int(m.group(1)), int(m.group(2)), int(m.group(3)))
    return shape, _RAW_DTYPES[m.group(4).lower()]


def _resolve_dtype(dtype) -> np.dtype:
    """A user's dtype (``"float32"``, ``"float"``, ``"double"``, ``np.int16``...) as a real numeric dtype."""
    if isinstance(dtype, str) and dtype.lower() in _RAW_DTYPES:
        return _RAW_DTYPES[dtype.lower()]
    try:
        dt = np.dtype(dtype)
    except (TypeError, ValueError, SyntaxError):  # numpy parses dtype strings: "0" and "01" raise these
        dt = None
    if dt is None or dt.kind not in "iuf":
        raise WarpgaussError(f"unknown dtype {dtype!r}; use one of {', '.join(_RAW_DTYPES)}")
    return dt


def _resolve_shape(shape) -> tuple[int, int, int]:
    """Validate a user's ``(x, y, z)`` shape."""
    try:
        xyz = tuple(int(v) for v in shape)
    except (TypeError, ValueError):
        xyz = ()
    if len(xyz) != 3 or min(xyz) < 1:
        raise WarpgaussError(f"shape must be three positive integers (x, y, z), got {shape!r}")
    return xyz  # type: ignore[return-value]


def _byte_order(endian: str | None) -> str:
    if endian is None or str(endian).lower() in ("little", "le", "<"):
        return "<"
    if str(endian).lower() in ("big", "be", ">"):
        return ">"
    raise WarpgaussError(f"endian must be 'little' or 'big', got {endian!r}")


def _fmt_xyz(shape_xyz) -> str:
    return "x".join(str(int(v)) for v in shape_xyz)


# --------------------------------------------------------------------------------------------------
# Readers
# --------------------------------------------------------------------------------------------------


def _read_raw(path: Path, *, shape=None, dtype=None, endian=None, **_) -> _Read:
    """Headerless binary, C-order ``[z, y, x]``; shape and dtype from the name or the options."""
    parsed = parse_raw_name(path.name)
    if (shape is None or dtype is None) and parsed is None:
        raise WarpgaussError(
            f"cannot tell the shape and dtype of {path.name}: name it NAME_XxYxZ_DTYPE{path.suffix or '.raw'} "
            f"(e.g. vol_256x256x128_float32.raw) or pass --shape XxYxZ and --dtype"
        )
    shape_xyz = _resolve_shape(shape) if shape is not None else parsed[0]  # type: ignore[index]
    base = _resolve_dtype(dtype) if dtype is not None else parsed[1]  # type: ignore[index]
    # numpy's stubs take only literal byte-order codes; _byte_order returns "<" or ">"
    dt = base.newbyteorder(_byte_order(endian))  # type: ignore[arg-type]
    nx, ny, nz = shape_xyz
    if min(shape_xyz) < 1:
        raise WarpgaussError(f"{path.name} names an empty grid {_fmt_xyz(shape_xyz)}; every axis needs at least 1 voxel")
    need = nx * ny * nz * dt.itemsize
    have = path.stat().st_size
    if have != need:
        raise WarpgaussError(f"{path.name} holds {have} bytes but {_fmt_xyz(shape_xyz)} {base.name} needs {need}; check --shape/--dtype")
    return _Read(np.memmap(path, dtype=dt, mode="r", shape=(nz, ny, nx)))


def _read_npy(path: Path, **_) -> _Read:
    """numpy ``.npy`` (memory-mapped, no pickle); the array must be ``[z, y, x]``."""
    try:
        data = np.load(path, allow_pickle=False, mmap_mode="r")
    except (ValueError, OSError, EOFError) as e:
        raise WarpgaussError(f"cannot read {path.name} as a .npy array ({_first_line(e)}); save it with numpy.save") from e
    return _Read(data)


def _read_hdf5(path: Path, *, dataset=None, variable=None, stride: int = 1, drop_leading: bool = False, **_) -> _Read:
    """HDF5: the named dataset, else the first 3D dataset in visit order; ``[z, y, x]`` order assumed.

    With ``drop_leading`` (netCDF-4 files) leading length-1 axes such as a single time step are dropped.
    """
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise WarpgaussError(f"cannot open {path.name} as HDF5 ({_first_line(e)}); is it an HDF5 file?") from e
    with f:
        found: list[tuple[str, tuple]] = []
        keep = _drop_leading_ones if drop_leading else tuple
        f.visititems(lambda n, o: found.append((n, keep(o.shape))) if isinstance(o, h5py.Dataset) else None)
        listing = _list_datasets(found)
        wanted = dataset if dataset is not None else variable
        if wanted is not None:
            key = str(wanted).lstrip("/")
            if key not in f or not isinstance(f[key], h5py.Dataset):
                raise WarpgaussError(f"{path.name} has no dataset {wanted!r}; it holds {listing}; pick one with --dataset")
        else:
            key = next((n for n, s in found if len(s) == 3), None)
            if key is None:
                raise WarpgaussError(f"{path.name} has no 3D dataset; it holds {listing}")
        ds = f[key]
        shape = keep(ds.shape)
        _check_shape(shape, f"{path.name}:{key}")
        _check_dtype(ds.dtype, f"{path.name}:{key}")
        data, strided = _hdf5_array(path, ds, shape, stride)
        return _Read(
            data,
            spacing=_attr_xyz(ds.attrs, "spacing", (1.0, 1.0, 1.0)),
            origin=_attr_xyz(ds.attrs, "origin", (0.0, 0.0, 0.0)),
            fill_value=_fill_attr(ds.attrs),
            strided=strided,
        )


def _hdf5_array(path: Path, ds, shape: tuple, stride: int) -> tuple[np.ndarray, bool]:
    """Memory-map a contiguous uncompressed dataset; otherwise read only the strided voxels.

    ``shape`` is the dataset's 3D shape once leading length-1 axes are dropped.
    """
    offset = ds.id.get_offset() if ds.chunks is None else None
    if offset is not None and ds.size > 0 and not ds.external:
        return np.memmap(path, dtype=ds.dtype, mode="r", offset=offset, shape=shape), False
    # read into memory: the declared shape is all we know (a chunked or never-written dataset
    # may declare terabytes in a few bytes of file), so check it before allocating
    voxels = _check_declared(f"{path.name}:{ds.name}", shape, ds.dtype.itemsize, stride)
    s = slice(None, None, stride)
    try:
        return np.asarray(ds[(0,) * (ds.ndim - 3) + (s, s, s)]), True
    except MemoryError:
        raise WarpgaussError(
            f"not enough memory to read {path.name}:{ds.name} ({voxels} voxels x {ds.dtype.itemsize} bytes); use a larger --stride"
        ) from None
    except OSError as e:  # a damaged chunk or a missing compression filter
        raise WarpgaussError(f"cannot read {path.name}:{ds.name} ({_first_line(e)})") from None


def _physical_memory() -> int | None:
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return None


def _check_declared(what: str, shape_zyx, itemsize: int, stride: int = 1) -> int:
    """Refuse a declared grid before anything is allocated for it; returns the voxels to read.

    A header's dimensions are only a claim: compressed or sparse storage lets a few bytes declare
    terabytes. Beyond :data:`MAX_READ_VOXELS` (after the stride) or beyond this machine's physical
    memory the read is refused with the way out (a larger ``--stride``).
    """
    kept = [-(-int(n) // stride) for n in shape_zyx]
    voxels = math.prod(kept)
    shown = _fmt_xyz(tuple(shape_zyx)[::-1])
    if voxels > MAX_READ_VOXELS:
        raise WarpgaussError(
            f"{what} declares {shown} voxels ({voxels} after --stride {stride}), more than the {MAX_READ_VOXELS} "
            "warpgauss can encode; use a larger --stride"
        )
    ram = _physical_memory()
    if ram is not None and voxels * int(itemsize) > ram:
        raise WarpgaussError(
            f"{what} declares {shown} voxels of {itemsize} bytes ({voxels * int(itemsize) / 2**30:.1f} GiB after "
            f"--stride {stride}), more than this machine's {ram / 2**30:.1f} GiB of memory; use a larger --stride"
        )
    return voxels


def _list_datasets(found: list[tuple[str, tuple]], limit: int = 12) -> str:
    if not found:
        return "no datasets"
    items = [f"{n} {tuple(int(v) for v in s)}" for n, s in found[:limit]]
    more = f" and {len(found) - limit} more" if len(found) > limit else ""
    return ", ".join(items) + more


def _read_netcdf(path: Path, *, variable=None, dataset=None, stride: int = 1, **_) -> _Read:
    """Classic netCDF (CDF-1/2) through scipy; a netCDF-4 (HDF5-based) file goes to the HDF5 reader.

    Leading length-1 axes (a single time step, ``(1, nz, ny, nx)``) are dropped. ``scale_factor`` /
    ``add_offset`` packing is not applied: the stored (packed) values are returned.
    """
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(b"\x89HDF\r\n\x1a\n"):
        return _read_hdf5(path, dataset=dataset if dataset is not None else variable, stride=stride, drop_leading=True)
    if not magic.startswith(b"CDF"):
        raise WarpgaussError(f"{path.name} is neither classic netCDF nor netCDF-4/HDF5 (it starts with {magic[:4]!r})")
    from scipy.io import netcdf_file

    try:
        f = netcdf_file(path, "r", mmap=False)
    except Exception as e:  # scipy raises TypeError/ValueError for unsupported variants (CDF-5)
        raise WarpgaussError(f"scipy cannot read {path.name} ({_first_line(e)}); convert it with `nccopy -k nc4` and retry") from e
    with f:
        shapes = [(n, _drop_leading_ones(v.shape)) for n, v in f.variables.items()]
        wanted = variable if variable is not None else dataset
        if wanted is not None:
            if wanted not in f.variables:
                raise WarpgaussError(f"{path.name} has no variable {wanted!r}; it holds {_list_datasets(shapes)}; pick one with --variable")
            key = wanted
        else:
            key = next((n for n, s in shapes if len(s) == 3), None)
            if key is None:
                raise WarpgaussError(f"{path.name} has no 3D variable; it holds {_list_datasets(shapes)}")
        var = f.variables[key]
        data = np.array(var.data)
        data = data.reshape(_drop_leading_ones(data.shape))
        return _Read(data, fill_value=_fill_attr(var._attributes))


def _drop_leading_ones(shape: tuple) -> tuple:
    shape = tuple(int(v) for v in shape)
    while len(shape) > 3 and shape[0] == 1:
        shape = shape[1:]
    return shape


def _read_pyvista(path: Path, **_) -> _Read:
    """VTK ImageData, legacy structured points, NIfTI, MetaImage, NRRD via ``pyvista.read``.

    The active point-data scalars (else the first point-data array) are used; a file with cell data
    only uses its first cell array on the cell-centre grid. Multi-component arrays are refused
    (no magnitude is taken). The NIfTI affine / VTK direction matrix is not applied.
    """
    import pyvista as pv

    _precheck_vtk(path)
    mesh, vtk_error = _quiet_pyvista_read(pv, path)
    if vtk_error is not None:  # whatever VTK returned after an error is not the file's data
        raise WarpgaussError(f"cannot read {path.name}: VTK reports: {vtk_error}")
    if not isinstance(mesh, pv.ImageData):
        raise WarpgaussError(
            f"{path.name} holds a {type(mesh).__name__}, not image data on a regular grid; "
            f"warpgauss reads VTK ImageData (structured points)"
        )
    dims = tuple(int(d) for d in mesh.dimensions)
    spacing = tuple(float(v) for v in mesh.spacing)
    origin = tuple(float(v) for v in mesh.origin)
    arrays = mesh.point_data
    if len(arrays.keys()) == 0 and len(mesh.cell_data.keys()) > 0:
        arrays = mesh.cell_data
        dims = tuple(max(d - 1, 1) for d in dims)
        origin = tuple(o + s / 2 for o, s in zip(origin, spacing))
    if len(arrays.keys()) == 0:
        raise WarpgaussError(f"{path.name} has no data arrays; nothing to encode")
    name = arrays.active_scalars_name or arrays.keys()[0]
    arr = np.asarray(arrays[name])
    if arr.ndim > 1 and path.name.lower().endswith((".nrrd", ".nhdr")):
        fixed = _nrrd_undo_vtk_components(path, arr, spacing)
        if fixed is not None:
            return _Read(fixed[0], spacing=fixed[1], origin=origin)  # type: ignore[arg-type]
    if arr.ndim > 1 and int(np.prod(arr.shape[1:])) != 1:
        raise WarpgaussError(
            f"{path.name}: array {name!r} has {int(np.prod(arr.shape[1:]))} components per voxel; "
            f"warpgauss encodes scalar volumes, so extract one component (or the magnitude) first"
        )
    xyz = arr.reshape(dims, order="F")  # [x, y, z]
    return _Read(np.ascontiguousarray(xyz.transpose(2, 1, 0)), spacing=spacing, origin=origin)  # type: ignore[arg-type]


_NRRD_SIZES = {
    1: ("uchar", "unsigned char", "uint8", "uint8_t", "signed char", "int8", "int8_t", "char"),
    2: (
        "short",
        "short int",
        "signed short",
        "signed short int",
        "int16",
        "int16_t",
        "ushort",
        "unsigned short",
        "unsigned short int",
        "uint16",
        "uint16_t",
    ),
    4: ("int", "signed int", "int32", "int32_t", "uint", "unsigned int", "uint32", "uint32_t", "float"),
}
_META_SIZES = {
    "MET_UCHAR": 1,
    "MET_CHAR": 1,
    "MET_SHORT": 2,
    "MET_USHORT": 2,
    "MET_INT": 4,
    "MET_UINT": 4,
    "MET_FLOAT": 4,
    "MET_LONG": 4,
    "MET_ULONG": 4,
}


def _quiet_pyvista_read(pv, path: Path):
    """``pv.read`` with VTK's own error output (its logger, pyvista's warnings and log records)
    held back: a damaged file must end in one line, not thirty. Returns (mesh, first VTK error)."""
    import contextlib
    import logging
    import warnings

    verbosity = getattr(pv, "vtk_verbosity", None)
    quiet = verbosity("off") if verbosity is not None else contextlib.nullcontext()
    previous = logging.root.manager.disable
    with warnings.catch_warnings(), quiet, pv.VtkErrorCatcher() as catcher:
        warnings.simplefilter("ignore")
        logging.disable(logging.CRITICAL)
        try:
            mesh = pv.read(path)
        except Exception as e:  # VTK and pyvista raise a mix of types for unreadable files
            raise WarpgaussError(f"cannot read {path.name} with pyvista ({_first_line(e)})") from e
        finally:
            logging.disable(previous)
    errors = [ev for ev in catcher.events if str(getattr(ev, "kind", "ERROR")) == "ERROR"]
    if not errors:
        return mesh, None
    text = str(getattr(errors[0], "alert", "") or errors[0]).strip()
    return mesh, (text.splitlines() or ["unknown error"])[0]


def _precheck_vtk(path: Path) -> None:
    """Check the dimensions a VTK/NRRD/MetaImage/NIfTI header declares before VTK allocates for them.

    VTK trusts a header's sizes: a 90-byte NRRD declaring 99999^3 voxels makes it throw
    ``std::bad_alloc`` and abort the process. The declared grid is refused here if it is empty,
    larger than warpgauss can encode or than this machine's memory, or (uncompressed data in the
    same file) larger than the bytes the file holds. Headers this cannot parse are left to VTK.
    """
    name = path.name.lower()
    if name.endswith((".nrrd", ".nhdr")):
        found = _nrrd_declared(path)
    elif name.endswith((".mha", ".mhd")):
        found = _meta_declared(path)
    elif name.endswith((".nii", ".nii.gz")):
        found = _nifti_declared(path)
    else:
        found = _vtk_xml_or_legacy_declared(path)
    if found is None:
        return
    dims, itemsize, need_after = found
    if not dims or min(dims) < 1:
        raise WarpgaussError(f"{path.name} declares an empty grid (sizes {dims}); the header is damaged")
    _check_declared(path.name, tuple(dims)[::-1], itemsize)
    if need_after is not None:
        offset, amount, mode = need_after
        have = _gzip_bytes(path, offset, amount) if mode == "gzip" else path.stat().st_size - offset
        if have < amount:
            raise WarpgaussError(
                f"{path.name} declares {'x'.join(map(str, dims))} voxels ({amount} bytes of data) but holds "
                f"{max(have, 0)}; the file is truncated or its header is damaged"
            )


def _gzip_bytes(path: Path, offset: int, enough: int) -> int:
    """Bytes a gzip stream starting at ``offset`` (of the file, or of its gunzipped content for a
    ``.gz`` file) decompresses to, counted in 1 MiB pieces up to ``enough``; memory stays bounded."""
    import zlib

    outer_gz = path.name.lower().endswith(".gz")
    total = 0
    try:
        with gzip.open(path, "rb") if outer_gz else open(path, "rb") as fh:
            fh.seek(offset) if not outer_gz else fh.read(offset)
            if outer_gz:  # the file itself is gzip: count what follows the header
                while total < enough:
                    piece = fh.read(1 << 20)
                    if not piece:
                        break
                    total += len(piece)
                return total
            z = zlib.decompressobj(16 + zlib.MAX_WBITS)
            while total < enough:
                piece = fh.read(1 << 20)
                if not piece:
                    break
                total += len(z.decompress(piece, enough - total + 1))
                while z.unconsumed_tail and total < enough:
                    total += len(z.decompress(z.unconsumed_tail, enough - total + 1))
    except (OSError, EOFError, zlib.error):
        pass
    return total


def _head_text(path: Path, limit: int = 65536) -> bytes:
    with open(path, "rb") as fh:
        return fh.read(limit)


def _ints(text: str) -> list[int] | None:
    try:
        return [int(float(v)) for v in text.replace(",", " ").split()]
    except (ValueError, OverflowError):
        return None


def _nrrd_declared(path: Path):
    head = _head_text(path)
    if not head.startswith(b"NRRD"):
        raise WarpgaussError(f"{path.name} does not start with the NRRD magic; it is not a NRRD file")
    fields = _nrrd_fields(path)
    sizes = _ints(fields.get("sizes", ""))
    if not sizes:
        raise WarpgaussError(f"{path.name} has no valid 'sizes:' field; the NRRD header is damaged")
    kind = fields.get("type", "").strip().lower()
    itemsize = next((k for k, names in _NRRD_SIZES.items() if kind in names), 8)
    need = None
    end = head.find(b"\n\n")
    detached = "data file" in fields or "datafile" in fields
    encoding = fields.get("encoding", "").strip().lower()
    if not detached and end >= 0:
        if encoding == "raw":
            need = (end + 2, math.prod(sizes) * itemsize, "raw")
        elif encoding in ("gzip", "gz"):
            need = (end + 2, math.prod(sizes) * itemsize, "gzip")
        elif encoding in ("ascii", "text", "txt"):
            # vtkNrrdReader returns zeros and noise for ASCII data instead of failing (VTK 9.x)
            raise WarpgaussError(
                f"{path.name} stores its values as ASCII text, which the NRRD reader (VTK) reads as garbage; "
                "convert it to raw or gzip encoding (e.g. unu save -e raw) and retry"
            )
    return sizes, itemsize, need


def _meta_declared(path: Path):
    head = _head_text(path)
    fields: dict[str, str] = {}
    offset = None
    pos = 0
    for line in head.split(b"\n"):
        pos += len(line) + 1
        key, sep, value = line.decode("latin-1").partition("=")
        if sep:
            fields[key.strip()] = value.strip()
        if key.strip() == "ElementDataFile":
            offset = pos
            break
    sizes = _ints(fields.get("DimSize", ""))
    if not sizes:
        raise WarpgaussError(f"{path.name} has no valid 'DimSize =' line; it is not a MetaImage header")
    channels = _ints(fields.get("ElementNumberOfChannels", "1")) or [1]
    itemsize = _META_SIZES.get(fields.get("ElementType", ""), 8) * max(channels[0], 1)
    need = None
    compressed = fields.get("CompressedData", "False").strip().lower() == "true"
    if fields.get("ElementDataFile", "").strip().upper() == "LOCAL" and not compressed and offset is not None:
        need = (offset, math.prod(sizes) * itemsize, "raw")
    return sizes, itemsize, need


def _nifti_declared(path: Path):
    if path.name.lower().endswith(".gz"):
        try:
            with gzip.open(path, "rb") as fh:
                head = fh.read(544)
        except (OSError, EOFError) as e:
            raise WarpgaussError(f"cannot decompress {path.name} ({_first_line(e)})") from None
        size = None
    else:
        head = _head_text(path, 544)
        size = path.stat().st_size
    for order in ("<", ">"):
        if len(head) >= 348 and struct.unpack(order + "i", head[:4])[0] == 348:
            dim = struct.unpack(order + "8h", head[40:56])
            bitpix = struct.unpack(order + "h", head[72:74])[0]
            offset = struct.unpack(order + "f", head[108:112])[0]
            break
        if len(head) >= 540 and struct.unpack(order + "i", head[:4])[0] == 540:
            dim = struct.unpack(order + "8q", head[16:80])
            bitpix = struct.unpack(order + "h", head[14:16])[0]
            offset = struct.unpack(order + "q", head[168:176])[0]
            break
    else:
        raise WarpgaussError(f"{path.name} has no NIfTI-1 or NIfTI-2 header (sizeof_hdr is not 348 or 540)")
    ndim = int(dim[0])
    if not 1 <= ndim <= 7:
        raise WarpgaussError(f"{path.name} declares {ndim} dimensions; the NIfTI header is damaged")
    sizes = [int(v) for v in dim[1 : ndim + 1]]
    itemsize = max(int(bitpix) // 8, 1) if 0 < bitpix <= 256 else 8
    need = None
    if np.isfinite(offset) and 0 <= offset < 2**40 and min(sizes) >= 1:
        need = (int(offset), math.prod(sizes) * itemsize, "gzip" if size is None else "raw")
    return sizes, itemsize, need


_VTK_EXTENT = re.compile(rb'WholeExtent\s*=\s*"([^"]*)"')
_VTK_DIMS = re.compile(rb"DIMENSIONS\s+(-?\d+)\s+(-?\d+)\s+(-?\d+)")


def _vtk_xml_or_legacy_declared(path: Path):
    head = _head_text(path)
    m = _VTK_EXTENT.search(head)
    if m:
        ext = _ints(m.group(1).decode("latin-1"))
        if not ext or len(ext) != 6:
            raise WarpgaussError(f"{path.name} has a WholeExtent that is not six integers; the file is damaged")
        return [ext[1] - ext[0] + 1, ext[3] - ext[2] + 1, ext[5] - ext[4] + 1], 8, None
    m = _VTK_DIMS.search(head)
    if m:
        return [int(v) for v in m.groups()], 8, None
    return None


def _nrrd_undo_vtk_components(path: Path, arr: np.ndarray, spacing) -> tuple[np.ndarray, tuple] | None:
    """Undo VTK's guess that a fastest NRRD axis of 9 samples or fewer holds vector components.

    vtkNrrdReader turns such an axis into components and shifts the grid axes down by one. When
    the header says ``dimension: 3`` and the first axis is not marked as a non-spatial kind, the
    file is a scalar volume: rebuild ``[z, y, x]`` and take the x spacing from the header.

    Returns:
        (data, spacing) or None if the file really holds vectors.
    """
    fields = _nrrd_fields(path)
    try:
        ndim = int(fields.get("dimension", "0"))
        sizes = [int(v) for v in fields.get("sizes", "").split()]
    except ValueError:
        return None
    kinds = fields.get("kinds", "").lower().split()
    directions = fields.get("space directions", "").split()
    if ndim != 3 or len(sizes) != 3 or arr.ndim != 2 or arr.shape[1] != sizes[0]:
        return None
    if (kinds and kinds[0] not in ("domain", "space")) or (directions and directions[0] == "none"):
        return None
    sx = 1.0
    try:
        if "spacings" in fields:
            sx = float(fields["spacings"].split()[0])
        elif directions:
            sx = float(np.linalg.norm([float(v) for v in directions[0].strip("()").split(",")]))
    except ValueError:
        pass
    sx = sx if np.isfinite(sx) and sx > 0 else 1.0
    data = np.ascontiguousarray(arr.reshape(sizes[2], sizes[1], sizes[0]))
    return data, (sx, float(spacing[0]), float(spacing[1]))


def _nrrd_fields(path: Path) -> dict[str, str]:
    """``field: value`` lines of a NRRD header (up to the blank line that ends it)."""
    with open(path, "rb") as fh:
        text = fh.read(65536).split(b"\n\n", 1)[0].decode("latin-1")
    fields = {}
    for line in text.splitlines()[1:]:
        key, sep, value = line.partition(": ")
        if sep and not line.startswith("#"):
            fields[key.strip().lower()] = value.strip()
    return fields


_MRC_MODES: dict[int, np.dtype] = {
    0: np.dtype(np.int8),
    1: np.dtype(np.int16),
    2: np.dtype(np.float32),
    6: np.dtype(np.uint16),
    12: np.dtype(np.float16),
}


def _read_mrc(path: Path, **_) -> _Read:
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
    return _Read(data, spacing=spacing, origin=_mrc_origin(floats[49:52], ints[4:7], mapcrs, spacing))


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
        raise WarpgaussError(f"cannot decompress {path.name} ({_first_line(e)})") from e


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


def _read_plt(path: Path, **_) -> _Read:
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
    return _Read(data, spacing=spacing, origin=origin)  # type: ignore[arg-type]


def _plt_step(lo: float, hi: float, n: int) -> float:
    d = (hi - lo) / n
    return d if np.isfinite(d) and d > 0 else 1.0


_RAW_OPTS = frozenset({"shape", "dtype", "endian"})
_H5_OPTS = frozenset({"dataset", "variable"})

#: File extension (lower case, full suffix) -> reader. The longest matching suffix wins.
READERS: dict[str, _Reader] = {
    ".raw": _Reader(_read_raw, _RAW_OPTS, "raw binary"),
    ".bin": _Reader(_read_raw, _RAW_OPTS, "raw binary"),
    ".npy": _Reader(_read_npy, frozenset(), "numpy"),
    ".h5": _Reader(_read_hdf5, _H5_OPTS, "HDF5"),
    ".hdf5": _Reader(_read_hdf5, _H5_OPTS, "HDF5"),
    ".hdf": _Reader(_read_hdf5, _H5_OPTS, "HDF5"),
    ".nc": _Reader(_read_netcdf, _H5_OPTS, "netCDF"),
    ".cdf": _Reader(_read_netcdf, _H5_OPTS, "netCDF"),
    **{
        ext: _Reader(_read_pyvista, frozenset(), "VTK/medical image")
        for ext in (".vti", ".vtk", ".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr")
    },
    **{base + comp: _Reader(_read_mrc, frozenset(), "MRC/CCP4") for base in (".mrc", ".map", ".ccp4") for comp in ("", ".gz", ".bz2")},
    ".plt": _Reader(_read_plt, frozenset(), "gOpenMol plt"),
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

    Returns:
        The :class:`Volume`, values in the source dtype, NaN and fill values untouched.

    Raises:
        WarpgaussError: Missing file, unknown extension, an option the format does not take,
            a size that does not match the header or name, or data that is not a 3D real array.
    """
    p = Path(path)
    if not p.exists():
        raise WarpgaussError(f"no such file: {p}")
    if p.is_dir():
        raise WarpgaussError(f"{p} is a directory; give a volume file")
    suffix = _match_suffix(p.name, READERS, "read")
    reader = READERS[suffix]
    s = _check_stride(stride)
    given = {"shape": shape, "dtype": dtype, "endian": endian, "dataset": dataset, "variable": variable}
    _check_options(p, reader, [k for k, v in given.items() if v is not None])
    got = reader.func(p, **given, stride=s)
    return _finish(p, suffix, got, s)


def _finish(p: Path, suffix: str, got: _Read, stride: int) -> Volume:
    """Common validation, stride and byte order; builds the :class:`Volume`."""
    data = got.data
    _check_shape(data.shape, p.name)
    _check_dtype(data.dtype, p.name)
    if stride > 1 and not got.strided:
        data = data[::stride, ::stride, ::stride]
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    # a header's inf/NaN geometry (metadata only) must not reach the model header, which is strict JSON
    spacing = tuple(float(v) * stride if np.isfinite(v) else float(stride) for v in got.spacing)
    origin = tuple(float(v) if np.isfinite(v) else 0.0 for v in got.origin)
    return Volume(
        data=data,
        spacing=spacing,  # type: ignore[arg-type]
        origin=origin,  # type: ignore[arg-type]
        name=_volume_name(p.name, suffix),
        source_dtype=data.dtype.name,
        path=str(p),
        fill_value=_fill_in_dtype(got.fill_value, data.dtype),
    )


def _fill_in_dtype(fill: float | None, dtype: np.dtype) -> float | None:
    """The fill value as the data stores it (a float64 attribute on float32 data is rounded to float32)."""
    if fill is None or dtype.kind != "f" or not np.isfinite(fill):
        return fill
    with np.errstate(over="ignore"):
        stored = dtype.type(fill)
    return float(stored) if np.isfinite(stored) else fill


def _match_suffix(filename: str, table: dict, verb: str) -> str:
    lower = filename.lower()
    hits = [ext for ext in table if lower.endswith(ext)]
    if not hits:
        ext = "".join(Path(filename).suffixes[-2:]) or "no extension"
        raise WarpgaussError(f"cannot {verb} {filename}: unknown extension {ext!r}; supported: {' '.join(sorted(table))}")
    return max(hits, key=len)


def _check_options(p: Path, reader: _Reader, given: list[str]) -> None:
    extra = [o for o in given if o not in reader.options]
    if extra:
        opts = ", ".join(f"--{o}" for o in extra)
        verb, it = ("does", "it") if len(extra) == 1 else ("do", "them")
        raise WarpgaussError(f"{opts} {verb} not apply to {p.name} ({reader.what} file); leave {it} out")


def _check_stride(stride) -> int:
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise WarpgaussError(f"stride must be a positive integer, got {stride!r}")
    return int(stride)


def _check_shape(shape: tuple, what: str) -> None:
    if len(shape) != 3:
        raise WarpgaussError(f"{what} is {len(shape)}D (shape {tuple(shape)}); warpgauss encodes 3D volumes")
    if min(shape) < 1:
        raise WarpgaussError(f"{what} has an empty axis (shape z,y,x = {tuple(shape)}); every axis needs at least 1 voxel")


def _check_dtype(dtype: np.dtype, what: str) -> None:
    if dtype.kind not in "iuf":
        raise WarpgaussError(f"{what} holds {dtype} values; warpgauss encodes real numbers (integer or float)")


def _volume_name(filename: str, suffix: str) -> str:
    stem = filename[: len(filename) - len(suffix)]
    stem = _RAW_NAME.sub("", stem)
    return stem or "volume"


def _attr_xyz(attrs, key: str, default: tuple[float, float, float]) -> tuple[float, float, float]:
    """Three finite numbers from an attribute; the default for anything else (metadata only)."""
    value = attrs.get(key)
    if value is None:
        return default
    try:
        arr = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):  # a string, a compound value...
        return default
    if arr.size != 3 or not np.isfinite(arr).all():
        return default
    return tuple(float(v) for v in arr)  # type: ignore[return-value]


def _fill_attr(attrs) -> float | None:
    for key in ("_FillValue", "missing_value"):
        value = attrs.get(key)
        if value is not None:
            arr = np.asarray(value).ravel()
            if arr.size and arr.dtype.kind in "iuf":
                return float(arr[0])
    return None


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


# --------------------------------------------------------------------------------------------------
# Writers
# --------------------------------------------------------------------------------------------------


def _write_vti(tmp: Path, data: np.ndarray, spacing, origin, name: str) -> None:
    import pyvista as pv

    if data.dtype == np.float16:  # VTK has no half-precision arrays
        data = data.astype(np.float32)
    nz, ny, nx = data.shape
    grid = pv.ImageData(dimensions=(nx, ny, nz), spacing=spacing, origin=origin)
    grid.point_data[name] = data.transpose(2, 1, 0).ravel(order="F")  # x fastest
    grid.save(tmp)


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
    suffix = _match_suffix(p.name, WRITERS, "write")
    data = np.asarray(data_zyx)
    _check_shape(data.shape, "the array to write")
    _check_dtype(data.dtype, "the array to write")
    if not data.dtype.isnative:
        data = data.astype(data.dtype.newbyteorder("="))
    spacing_t = _xyz_tuple(spacing, "spacing")
    origin_t = _xyz_tuple(origin, "origin")
    check_writable(p, force=force)
    with atomic_path(p) as tmp:
        WRITERS[suffix](tmp, data, spacing_t, origin_t, str(name) or "value")
    return p


def _xyz_tuple(value, what: str) -> tuple[float, float, float]:
    try:
        out = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(np.isfinite(out)):
        raise WarpgaussError(f"{what} must be three finite numbers (x, y, z), got {value!r}")
    return out  # type: ignore[return-value]


@dataclass
class ReadOptions:
    """How to read a file source (see :func:`warpgauss.io.read_volume`)."""

    shape: tuple[int, int, int] | None = None
    dtype: str | None = None
    endian: str | None = None
    dataset: str | None = None
    variable: str | None = None
    stride: int = 1
    fill_value: float | None = None

    def read(self, path):
        """Read a volume file with these options (:func:`warpgauss.io.read_volume`)."""
        return read_volume(
            path,
            shape=self.shape,
            dtype=self.dtype,
            endian=self.endian,
            dataset=self.dataset,
            variable=self.variable,
            stride=self.stride,
        )
