"""HDF5 (and netCDF-4) and classic netCDF, read by chunks of the stride without loading the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import WarpgaussError
from .common import ReadResult, attr_xyz, check_declared, check_dtype, check_shape, fill_attr, first_line, pick_array


def read_hdf5(
    path: Path,
    *,
    dataset=None,
    variable=None,
    stride: int = 1,
    drop_leading: bool = False,
    lazy: bool = False,
    max_voxels: int | None = None,
    **_,
) -> ReadResult:
    """HDF5: the named dataset, else the first 3D dataset in visit order; ``[z, y, x]`` order assumed.

    With ``drop_leading`` (netCDF-4 files) leading length-1 axes such as a single time step are dropped.
    """
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise WarpgaussError(f"cannot open {path.name} as HDF5 ({first_line(e)}); is it an HDF5 file?") from e
    with f:
        found: list[tuple[str, tuple]] = []
        keep = _drop_leading_ones if drop_leading else tuple
        f.visititems(lambda n, o: found.append((n, keep(o.shape))) if isinstance(o, h5py.Dataset) else None)
        wanted = dataset if dataset is not None else variable
        key = pick_array(path.name, found, wanted, lambda k: k in f and isinstance(f[k], h5py.Dataset), "dataset", "--dataset")
        ds = f[key]
        shape = keep(ds.shape)
        check_shape(shape, f"{path.name}:{key}")
        check_dtype(ds.dtype, f"{path.name}:{key}")
        data, strided = _hdf5_array(path, ds, shape, stride, lazy, max_voxels)
        return ReadResult(
            data,
            spacing=attr_xyz(ds.attrs, "spacing", (1.0, 1.0, 1.0)),
            origin=attr_xyz(ds.attrs, "origin", (0.0, 0.0, 0.0)),
            fill_value=fill_attr(ds.attrs),
            strided=strided,
        )


def _hdf5_array(path: Path, ds, shape: tuple, stride: int, lazy: bool = False, max_voxels: int | None = None) -> tuple[np.ndarray, bool]:
    """Memory-map a contiguous uncompressed dataset; otherwise read only the strided voxels
    (``lazy``: leave a chunked dataset unread, to be read by bricks; see :mod:`warpgauss.readers.lazy`).

    ``shape`` is the dataset's 3D shape once leading length-1 axes are dropped.
    """
    offset = ds.id.get_offset() if ds.chunks is None else None
    if offset is not None and ds.size > 0 and not ds.external:
        return np.memmap(path, dtype=ds.dtype, mode="r", offset=offset, shape=shape), False
    if lazy:
        from .lazy import ArraySource, Lazy3D

        src = ArraySource("hdf5", str(path), tuple(int(v) for v in shape), ds.dtype.str, key=ds.name)  # type: ignore[arg-type]
        return Lazy3D(src), False  # type: ignore[return-value]
    # read into memory: the declared shape is all we know (a chunked or never-written dataset
    # may declare terabytes in a few bytes of file), so check it before allocating
    voxels = check_declared(f"{path.name}:{ds.name}", shape, ds.dtype.itemsize, stride, max_voxels)
    s = slice(None, None, stride)
    try:
        return np.asarray(ds[(0,) * (ds.ndim - 3) + (s, s, s)]), True
    except MemoryError:
        raise WarpgaussError(
            f"not enough memory to read {path.name}:{ds.name} ({voxels} voxels x {ds.dtype.itemsize} bytes); use a larger --stride"
        ) from None
    except OSError as e:  # a damaged chunk or a missing compression filter
        raise WarpgaussError(f"cannot read {path.name}:{ds.name} ({first_line(e)})") from None


def read_netcdf(
    path: Path, *, variable=None, dataset=None, stride: int = 1, lazy: bool = False, max_voxels: int | None = None, **_
) -> ReadResult:
    """Classic netCDF (CDF-1/2) through scipy; a netCDF-4 (HDF5-based) file goes to the HDF5 reader.

    Leading length-1 axes (a single time step, ``(1, nz, ny, nx)``) are dropped. ``scale_factor`` /
    ``add_offset`` packing is not applied: the stored (packed) values are returned.
    """
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(b"\x89HDF\r\n\x1a\n"):
        wanted = dataset if dataset is not None else variable
        return read_hdf5(path, dataset=wanted, stride=stride, drop_leading=True, lazy=lazy, max_voxels=max_voxels)
    if not magic.startswith(b"CDF"):
        raise WarpgaussError(f"{path.name} is neither classic netCDF nor netCDF-4/HDF5 (it starts with {magic[:4]!r})")
    from scipy.io import netcdf_file

    try:
        f = netcdf_file(path, "r", mmap=False)
    except Exception as e:  # scipy raises TypeError/ValueError for unsupported variants (CDF-5)
        raise WarpgaussError(f"scipy cannot read {path.name} ({first_line(e)}); convert it with `nccopy -k nc4` and retry") from e
    with f:
        shapes = [(n, _drop_leading_ones(v.shape)) for n, v in f.variables.items()]
        wanted = variable if variable is not None else dataset
        key = pick_array(path.name, shapes, wanted, lambda k: k in f.variables, "variable", "--variable", strip="")
        var = f.variables[key]
        data = np.array(var.data)
        data = data.reshape(_drop_leading_ones(data.shape))
        return ReadResult(data, fill_value=fill_attr(var._attributes))


def _drop_leading_ones(shape: tuple) -> tuple:
    shape = tuple(int(v) for v in shape)
    while len(shape) > 3 and shape[0] == 1:
        shape = shape[1:]
    return shape
