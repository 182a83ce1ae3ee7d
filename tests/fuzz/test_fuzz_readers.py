"""Fuzz the volume readers: raw sizes and names, .npy, HDF5 layouts, netCDF, MRC and .plt headers, VTK.

Invariant of ``read_volume``: it returns a Volume holding a 3D real array whose shape and dtype
follow from the file, or raises a one-line WarpgaussError; nothing else escapes, and no reader
allocates from a length the file declares but does not hold.
"""

from __future__ import annotations

import bz2
import gzip
import struct
import tempfile
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from fuzz_support import assert_clear_refusal, fuzz
from hypothesis import example, given
from hypothesis import strategies as st

from warpgauss.errors import WarpgaussError
from warpgauss.readers import Volume, read_volume

_TMP = Path(tempfile.mkdtemp(prefix="reader-fuzz-"))
DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64", "float", "double"]


def _read(path, **kw):
    """read_volume, with the invariant checked: a valid Volume or a clear refusal (returned as None)."""
    try:
        vol = read_volume(path, **kw)
    except WarpgaussError as e:
        assert_clear_refusal(e)
        return None
    assert isinstance(vol, Volume)
    d = vol.data
    assert d.ndim == 3 and min(d.shape) >= 1 and d.dtype.kind in "iuf" and d.dtype.isnative
    assert len(vol.spacing) == 3 and len(vol.origin) == 3
    np.asarray(d[-1, -1, -1])  # the last voxel is really there (no short memmap)
    return vol


def _write(name: str, data: bytes) -> Path:
    path = _TMP / name
    path.write_bytes(data)
    return path


# -- raw -------------------------------------------------------------------------------------------


@fuzz(120)
@given(
    shape=st.tuples(*[st.integers(0, 9)] * 3),
    dtype=st.sampled_from(DTYPES),
    delta=st.integers(-9, 9),
    by_name=st.booleans(),
    endian=st.sampled_from([None, "little", "big", "LE", "middle"]),
)
def test_raw_files_of_any_size(shape, dtype, delta, by_name, endian):
    dt = np.dtype({"float": "float32", "double": "float64"}.get(dtype, dtype))
    need = int(np.prod(shape)) * dt.itemsize
    size = max(0, need + delta)
    nx, ny, nz = shape
    if by_name:
        path = _write(f"v_{nx}x{ny}x{nz}_{dtype}.raw", bytes(size))
        vol = _read(path, endian=endian)
    else:
        path = _write("v.raw", bytes(size))
        vol = _read(path, shape=shape, dtype=dtype, endian=endian)
    ok = size == need and min(shape) >= 1 and endian != "middle"
    assert (vol is not None) == ok
    if ok:
        assert vol.data.shape == (nz, ny, nx) and vol.data.dtype == dt


@fuzz(80)
@given(
    shape=st.one_of(st.none(), st.text(max_size=12), st.lists(st.integers(-(2**40), 2**40), max_size=4)),
    dtype=st.one_of(st.none(), st.text(max_size=10), st.sampled_from(DTYPES + ["float16", "complex64", "bool", "S4"])),
)
def test_raw_options_of_any_kind(shape, dtype):
    path = _write("opts_2x2x2_uint8.raw", bytes(8))
    tracemalloc.start()
    try:
        _read(path, shape=shape, dtype=dtype)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # a huge declared shape is compared with the file size, never allocated


# -- npy -------------------------------------------------------------------------------------------

NPY_DTYPES = ["u1", "i2", "<f4", ">f4", "f8", "f2", "?", "c8", "U3", "S2", "i2,f4", "M8[s]", "m8[s]"]


@fuzz(80)
@given(
    shape=st.lists(st.integers(0, 4), min_size=0, max_size=5),
    dtype=st.sampled_from(NPY_DTYPES),
    fortran=st.booleans(),
    cut=st.integers(0, 40),
)
def test_npy_files_of_any_layout(shape, dtype, fortran, cut):
    a = np.zeros(shape, dtype=dtype, order="F" if fortran else "C")
    path = _TMP / "a.npy"
    with open(path, "wb") as fh:
        np.save(fh, a, allow_pickle=False)
    if cut:  # a truncated array
        path.write_bytes(path.read_bytes()[:-cut])
    vol = _read(path)
    ok = len(shape) == 3 and min(shape) >= 1 and np.dtype(dtype).kind in "iuf" and (cut == 0 or a.nbytes == 0)
    assert (vol is not None) == ok, (shape, dtype, cut)
    if ok:
        assert vol.data.shape == tuple(shape)


@fuzz(80)
@given(st.binary(max_size=300), st.booleans())
@example(b"\x01\x00\xff\xff{'descr': '<f4', 'fortran_order': False, 'shape': (99999, 99999, 99999), }", True)
@example(b"\x03\x00\xff\xff\xff\xff", True)
def test_npy_random_bytes(data, magic):
    _read(_write("r.npy", (b"\x93NUMPY" if magic else b"") + data))


def test_object_npy_is_refused_without_unpickling():
    path = _TMP / "obj.npy"
    np.save(path, np.array([[[object()]]], dtype=object), allow_pickle=True)
    assert _read(path) is None


# -- HDF5 layouts ----------------------------------------------------------------------------------

H5_DTYPES = ["u1", "i1", "<i2", ">i2", "<f4", ">f8", "f2", "?", "c8", "S3", "i4,f4"]
ATTR = st.one_of(
    st.none(),
    st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=5),  # HDF5: UTF-8, no NUL
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
    st.integers(-5, 5),
    st.floats(allow_nan=True),
)


@st.composite
def h5_layout(draw):
    """A file of a few datasets in nested groups, with random shapes, dtypes, storage and attributes."""
    items = []
    for i in range(draw(st.integers(0, 3))):
        group = draw(st.sampled_from(["", "g/", "g/h/"]))
        shape = tuple(draw(st.lists(st.integers(0, 5), min_size=0, max_size=5)))
        items.append(
            {
                "name": f"{group}d{i}",
                "shape": shape,
                "dtype": draw(st.sampled_from(H5_DTYPES)),
                "chunked": draw(st.booleans()) and len(shape) > 0 and min(shape, default=0) > 0,
                "gzip": draw(st.booleans()),
                "written": draw(st.booleans()),
                "attrs": {
                    k: draw(ATTR) for k in draw(st.sets(st.sampled_from(["spacing", "origin", "_FillValue", "missing_value"]), max_size=3))
                },
            }
        )
    return items


def _make_h5(path: Path, items) -> None:
    import h5py

    with h5py.File(path, "w") as f:
        for it in items:
            if it["name"] in f:
                continue
            try:
                kw = {}
                if it["chunked"]:
                    kw["chunks"] = True
                    if it["gzip"]:
                        kw["compression"] = "gzip"
                ds = f.create_dataset(it["name"], shape=it["shape"], dtype=it["dtype"], **kw)
            except (TypeError, ValueError):
                continue  # a layout h5py itself refuses
            if it["written"] and ds.size:
                ds[...] = np.ones(it["shape"], ds.dtype)
            for k, v in it["attrs"].items():
                if v is not None:
                    ds.attrs[k] = v


@fuzz(100)
@given(items=h5_layout(), pick=st.one_of(st.none(), st.sampled_from(["d0", "g/d1", "/g/h/d2", "nope", "g"])), stride=st.integers(1, 3))
def test_hdf5_layouts(items, pick, stride):
    path = _TMP / "l.h5"
    _make_h5(path, items)
    vol = _read(path, dataset=pick, stride=stride)
    if vol is not None:
        assert all(np.isfinite(vol.spacing)) and all(np.isfinite(vol.origin))
        assert vol.fill_value is None or isinstance(vol.fill_value, float)
        np.asarray(vol.data)  # readable to the end


def test_hdf5_huge_declared_shape_is_refused_before_reading():
    """A never-written chunked dataset declares 2.7e10 voxels in a few KiB: refused, not allocated."""
    import h5py

    path = _TMP / "huge.h5"
    with h5py.File(path, "w") as f:
        f.create_dataset("v", shape=(3000, 3000, 3000), dtype="f4", chunks=(16, 16, 16))
    assert path.stat().st_size < 1 << 20
    tracemalloc.start()
    try:
        with pytest.raises(WarpgaussError, match="more than") as e:
            read_volume(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert_clear_refusal(e.value)
    assert peak < 1 << 20
    vol = read_volume(path, stride=300)  # the stride brings it within reach: read as the fill value
    assert vol.data.shape == (10, 10, 10) and vol.data.dtype == np.float32 and not vol.data.any()


@fuzz(60)
@given(st.binary(max_size=400))
def test_hdf5_random_bytes(data):
    _read(_write("r.h5", b"\x89HDF\r\n\x1a\n" + data))


# -- netCDF (classic, through scipy) ----------------------------------------------------------------


def _netcdf_bytes(shape, dtype: str, fill) -> bytes:
    from scipy.io import netcdf_file

    path = _TMP / "w.nc"
    with netcdf_file(path, "w") as f:
        dims = []
        for i, n in enumerate(shape):
            f.createDimension(f"d{i}", n)
            dims.append(f"d{i}")
        v = f.createVariable("t", dtype, tuple(dims))
        if fill is not None:
            v._FillValue = fill
        if int(np.prod(shape)):
            v[...] = np.ones(shape, dtype)
    return path.read_bytes()


@fuzz(80)
@given(
    shape=st.lists(st.integers(1, 4), min_size=1, max_size=4),
    dtype=st.sampled_from(["b", "h", "i", "f", "d"]),
    fill=st.one_of(st.none(), st.floats(-10, 10)),
    mutate=st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)), max_size=4),
    cut=st.integers(0, 64),
)
def test_netcdf_classic_files_and_damage(shape, dtype, fill, mutate, cut):
    blob = bytearray(_netcdf_bytes(shape, dtype, fill))
    for pos, byte in mutate:
        if pos < len(blob):
            blob[pos] = byte
    if cut:
        blob = blob[: max(4, len(blob) - cut)]
    _read(_write("f.nc", bytes(blob)))


@fuzz(60)
@given(st.binary(max_size=300), st.sampled_from([b"CDF\x01", b"CDF\x02", b"CDF\x05", b""]))
def test_netcdf_random_bytes(data, magic):
    _read(_write("r.nc", magic + data))


# -- MRC / CCP4 --------------------------------------------------------------------------------------


@st.composite
def mrc_file(draw):
    e = draw(st.sampled_from(["<", ">"]))
    small = st.integers(-2, 6)
    nx, ny, nz = draw(small), draw(small), draw(small)
    mode = draw(st.sampled_from([0, 1, 2, 6, 12, 3, 4, 101, -1]))
    mapcrs = draw(st.sampled_from([(1, 2, 3), (3, 1, 2), (0, 0, 0), (1, 1, 2), (4, 2, 1)]))
    nsymbt = draw(st.sampled_from([0, 80, -5, 2**31 - 1]))
    huge = draw(st.booleans())
    if huge:  # a header declaring far more data than the file has
        nx, ny, nz = 2**31 - 1, 2**31 - 1, 7
    ints = np.zeros(256, e + "i4")
    ints[0:4] = nx, ny, nz, mode
    ints[7:10] = [draw(st.integers(-1, 8)) for _ in range(3)]
    ints[16:19] = mapcrs
    ints[23] = nsymbt
    floats = ints.view(e + "f4")
    floats[10:13] = [draw(st.floats(width=32, allow_nan=True, allow_infinity=True)) for _ in range(3)]
    floats[49:52] = [draw(st.floats(width=32, allow_nan=True, allow_infinity=True)) for _ in range(3)]
    head = bytearray(ints.tobytes())
    head[208:212] = b"MAP "
    head[212:214] = draw(st.sampled_from([b"\x44\x44", b"\x11\x11", b"\x00\x00"]))
    itemsize = {0: 1, 1: 2, 2: 4, 6: 2, 12: 2}.get(mode, 4)
    need = max(nx, 0) * max(ny, 0) * max(nz, 0) * itemsize if not huge else 64
    payload = bytes(max(0, (nsymbt if 0 < nsymbt < 4096 else 0) + need + draw(st.integers(-3, 3))))
    ext = draw(st.sampled_from([".mrc", ".map", ".ccp4", ".mrc.gz", ".map.bz2"]))
    return bytes(head) + payload, ext


@fuzz(150)
@given(mrc_file())
def test_mrc_headers(f):
    blob, ext = f
    if ext.endswith(".gz"):
        blob = gzip.compress(blob, mtime=0)
    elif ext.endswith(".bz2"):
        blob = bz2.compress(blob)
    tracemalloc.start()
    try:
        vol = _read(_write("m" + ext, blob))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 8 * len(blob) + (1 << 20)  # at most the decompressed file, never the declared size
    if vol is not None:
        assert all(np.isfinite(vol.spacing)) and all(np.isfinite(vol.origin))


@fuzz(60)
@given(st.binary(max_size=1500), st.sampled_from([".mrc", ".map.gz", ".ccp4.bz2"]))
def test_mrc_random_bytes_and_broken_compression(data, ext):
    _read(_write("r" + ext, data))


# -- gOpenMol .plt -----------------------------------------------------------------------------------


@fuzz(100)
@given(
    e=st.sampled_from(["<", ">"]),
    rank=st.sampled_from([3, 2, 0, 50331648]),
    dims=st.tuples(*[st.integers(-2, 5)] * 3),
    huge=st.booleans(),
    box=st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), min_size=6, max_size=6),
    delta=st.integers(-4, 4),
)
def test_plt_headers(e, rank, dims, huge, box, delta):
    nz, ny, nx = (2**31 - 1, 2**31 - 1, 3) if huge else dims
    head = struct.pack(e + "5i", rank, 200, nz, ny, nx) + struct.pack(e + "6f", *box)
    need = 0 if huge else max(nx, 0) * max(ny, 0) * max(nz, 0) * 4
    vol = _read(_write("p.plt", head + bytes(max(0, need + delta))))
    if vol is not None:
        assert vol.data.shape == (nz, ny, nx) and all(np.isfinite(vol.spacing)) and all(np.isfinite(vol.origin))


# -- VTK and medical formats through pyvista -----------------------------------------------------------


@fuzz(30)
@given(st.binary(max_size=200), st.sampled_from([".vti", ".vtk", ".nrrd", ".mha", ".nii"]))
@example(b'<VTKFile type="ImageData"><ImageData WholeExtent="0 99999 0 99999 0 99999"></ImageData></VTKFile>', ".vti")
@example(b"NRRD0004\ntype: float\ndimension: 3\nsizes: 99999 99999 99999\nencoding: raw\n\n", ".nrrd")
def test_pyvista_formats_random_bytes(data, ext):
    _read(_write("r" + ext, data))


# -- attributes ------------------------------------------------------------------------------------------


@fuzz(60)
@given(spacing=ATTR, origin=ATTR, fill=ATTR)
def test_hdf5_spacing_origin_and_fill_attributes_of_any_type(spacing, origin, fill):
    import h5py

    path = _TMP / "attrs.h5"
    with h5py.File(path, "w") as f:
        ds = f.create_dataset("v", data=np.arange(8, dtype=np.float32).reshape(2, 2, 2))
        for k, v in (("spacing", spacing), ("origin", origin), ("_FillValue", fill)):
            if v is not None:
                ds.attrs[k] = v
    vol = _read(path)
    assert vol is not None  # metadata never makes good data unreadable
    assert all(np.isfinite(vol.spacing)) and all(np.isfinite(vol.origin))
