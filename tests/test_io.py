"""Volume readers and writers: round trips, axis order, headers, and the one-line errors."""

from __future__ import annotations

import bz2
import gzip
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from warpgauss.errors import WarpgaussError
from warpgauss.readers import Volume, parse_raw_name, read_volume, supported_extensions, write_volume

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
if not DATA.is_dir():
    DATA = Path("/work/shared/data")

RAW_DTYPES = ["uint8", "int8", "uint16", "int16", "uint32", "int32", "float32", "float64"]


def ramp(shape_zyx=(2, 3, 4), dtype=np.float32) -> np.ndarray:
    """Distinct values in every voxel, so any axis mix-up shows: v = 100 z + 10 y + x."""
    z, y, x = np.indices(shape_zyx)
    return (100 * z + 10 * y + x).astype(dtype)


# ------------------------------------------------------------------------------------------ raw


@pytest.mark.parametrize("name", RAW_DTYPES)
def test_raw_round_trip_each_dtype(tmp_path, name):
    data = ramp((2, 3, 4), np.dtype(name))
    p = write_volume(tmp_path / f"ramp_4x3x2_{name}.raw", data)
    assert p.stat().st_size == data.nbytes
    vol = read_volume(p)
    assert vol.data.dtype == np.dtype(name)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.shape_xyz == (4, 3, 2)
    assert vol.name == "ramp"
    assert vol.source_dtype == name
    assert vol.source_itemsize == np.dtype(name).itemsize
    assert vol.source_bytes == data.nbytes
    assert vol.spacing == (1.0, 1.0, 1.0)


def test_parse_raw_name():
    assert parse_raw_name("bonsai_256x256x256_uint8.raw") == ((256, 256, 256), np.dtype(np.uint8))
    assert parse_raw_name("/a/b/vortex_128x64x32_float32.raw") == ((128, 64, 32), np.dtype(np.float32))
    assert parse_raw_name("richtmyer_meshkov_2048x2048x1920_uint8.raw") == ((2048, 2048, 1920), np.dtype(np.uint8))
    assert parse_raw_name("x_5x6x7_float.raw") == ((5, 6, 7), np.dtype(np.float32))
    assert parse_raw_name("x_5x6x7_double.bin") == ((5, 6, 7), np.dtype(np.float64))
    assert parse_raw_name("X_5x6x7_INT16.RAW") == ((5, 6, 7), np.dtype(np.int16))
    assert parse_raw_name("5x6x7_uint16.raw") == ((5, 6, 7), np.dtype(np.uint16))
    assert parse_raw_name("x_5x6x7_float16.raw") is None
    assert parse_raw_name("volume.raw") is None
    assert parse_raw_name("x_5x6_uint8.raw") is None


def test_raw_big_endian(tmp_path):
    data = ramp((2, 3, 4), np.int16) * 3 - 50
    p = tmp_path / "be_4x3x2_int16.raw"
    data.astype(">i2").tofile(p)
    vol = read_volume(p, endian="big")
    np.testing.assert_array_equal(vol.data, data)
    assert vol.data.dtype.isnative and vol.source_dtype == "int16"
    # read as little-endian (the default) the bytes come out swapped
    np.testing.assert_array_equal(read_volume(p).data, data.byteswap())


def test_raw_explicit_shape_and_dtype_override_the_name(tmp_path):
    data = ramp((2, 3, 4), np.float64)
    p = tmp_path / "blob.bin"
    data.tofile(p)
    vol = read_volume(p, shape=(4, 3, 2), dtype="double")
    np.testing.assert_array_equal(vol.data, data)
    assert vol.name == "blob"
    # a name that says float32 is overridden by --dtype
    q = tmp_path / "v_4x3x2_float32.raw"
    data.tofile(q)
    np.testing.assert_array_equal(read_volume(q, dtype="float64", shape=(4, 3, 2)).data, data)


def test_raw_wrong_size_names_both_sizes(tmp_path):
    p = tmp_path / "vol_64x64x64_float32.raw"
    p.write_bytes(b"\0" * 1000)
    with pytest.raises(WarpgaussError, match=r"1000 bytes.*64x64x64 float32 needs 1048576.*--shape/--dtype") as e:
        read_volume(p)
    assert "\n" not in str(e.value)


def test_raw_without_shape_asks_for_it(tmp_path):
    p = tmp_path / "volume.raw"
    p.write_bytes(b"\0" * 8)
    with pytest.raises(WarpgaussError, match="--shape"):
        read_volume(p)
    with pytest.raises(WarpgaussError, match="unknown dtype"):
        read_volume(p, shape=(2, 2, 2), dtype="complex64")
    with pytest.raises(WarpgaussError, match="endian"):
        read_volume(p, shape=(2, 2, 2), dtype="uint8", endian="middle")


# ------------------------------------------------------------------------------------------ npy


def test_npy_round_trip_and_memmap(tmp_path):
    data = ramp((3, 4, 5), np.uint16)
    p = write_volume(tmp_path / "a.npy", data)
    vol = read_volume(p)
    assert isinstance(vol.data, np.memmap)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.shape_xyz == (5, 4, 3) and vol.source_dtype == "uint16"


@pytest.mark.parametrize(
    ("array", "match"),
    [
        (np.zeros((4, 5), np.float32), r"is 2D \(shape \(4, 5\)\); warpgauss encodes 3D volumes"),
        (np.zeros((2, 2, 3, 4), np.float32), r"is 4D"),
        (np.zeros((2, 0, 3), np.float32), r"empty axis"),
        (np.zeros((2, 2, 2), bool), r"bool.*real numbers"),
        (np.zeros((2, 2, 2), np.complex64), r"complex64.*real numbers"),
    ],
)
def test_npy_rejects_non_volumes(tmp_path, array, match):
    p = tmp_path / "bad.npy"
    np.save(p, array)
    with pytest.raises(WarpgaussError, match=match):
        read_volume(p)


# ------------------------------------------------------------------------------------------ HDF5


def test_a_spacing_of_zero_or_below_reaches_no_model(tmp_path):
    """A file's spacing of 0 (unknown) reads as the stride, a negative one (a flipped axis) as its
    size: a model file refuses a spacing that is not positive."""
    data = np.arange(2 * 3 * 4, dtype=np.float32).reshape(2, 3, 4)
    p = write_volume(tmp_path / "z.h5", data, spacing=(0.0, -2.0, 3.0))
    assert read_volume(p).spacing == (1.0, 2.0, 3.0)


def test_hdf5_round_trip_with_spacing(tmp_path):
    data = ramp((3, 4, 5), np.float32)
    p = write_volume(tmp_path / "v.h5", data, spacing=(0.5, 2.0, 3.0), origin=(1.0, -2.0, 4.0))
    vol = read_volume(p)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.spacing == (0.5, 2.0, 3.0) and vol.origin == (1.0, -2.0, 4.0)
    assert vol.fill_value is None
    q = write_volume(tmp_path / "v.hdf5", data)
    np.testing.assert_array_equal(read_volume(q, dataset="/volume").data, data)


def test_hdf5_dataset_selection_and_errors(tmp_path):
    import h5py

    p = tmp_path / "multi.h5"
    a, b = ramp((2, 3, 4)), ramp((3, 3, 3), np.int32)
    with h5py.File(p, "w") as f:
        f.create_dataset("aa_image", data=np.zeros((4, 4)))
        f.create_dataset("grp/first", data=a)
        f.create_dataset("grp/second", data=b)
        f.create_dataset("zz_series", data=np.zeros((2, 2, 2, 2)))
    np.testing.assert_array_equal(read_volume(p).data, a)  # first 3D dataset in visit order
    np.testing.assert_array_equal(read_volume(p, dataset="grp/second").data, b)
    with pytest.raises(WarpgaussError, match=r"no dataset 'nope'.*aa_image \(4, 4\).*grp/first \(2, 3, 4\).*grp/second"):
        read_volume(p, dataset="nope")
    with pytest.raises(WarpgaussError, match=r"is 2D"):
        read_volume(p, dataset="aa_image")
    q = tmp_path / "flat.h5"
    with h5py.File(q, "w") as f:
        f.create_dataset("img", data=np.zeros((4, 4)))
    with pytest.raises(WarpgaussError, match=r"no 3D dataset.*img \(4, 4\)"):
        read_volume(q)


def test_hdf5_chunked_strided_and_fill_value(tmp_path):
    import h5py

    data = ramp((6, 7, 8), np.float32)
    p = tmp_path / "c.h5"
    with h5py.File(p, "w") as f:
        ds = f.create_dataset("v", data=data, chunks=(2, 3, 4), compression="gzip")
        ds.attrs["_FillValue"] = np.float32(-999.0)
    vol = read_volume(p, stride=3)
    np.testing.assert_array_equal(vol.data, data[::3, ::3, ::3])
    assert vol.shape_xyz == (3, 3, 2) and vol.spacing == (3.0, 3.0, 3.0)
    assert vol.fill_value == -999.0


def _h5_with(path: Path, array: np.ndarray) -> Path:
    import h5py

    with h5py.File(path, "w") as f:
        f.create_dataset("v", data=array)
    return path


# ------------------------------------------------------------------------------------------ netCDF


def _write_netcdf(path: Path, variables: dict[str, tuple[tuple[str, ...], np.ndarray, dict]]) -> None:
    from scipy.io import netcdf_file

    with netcdf_file(path, "w") as f:
        for dim, n in (("time", 1), ("z", 2), ("y", 3), ("x", 4)):
            f.createDimension(dim, n)
        for name, (dims, values, attrs) in variables.items():
            v = f.createVariable(name, values.dtype.char, dims)
            v[:] = values
            for key, value in attrs.items():
                setattr(v, key, value)


def test_netcdf_first_3d_variable_drops_a_single_time_step(tmp_path):
    temp = ramp((2, 3, 4), np.float32)
    p = tmp_path / "sim.nc"
    _write_netcdf(p, {"mask": (("y", "x"), np.ones((3, 4), np.int32), {}), "temp": (("time", "z", "y", "x"), temp[None], {})})
    vol = read_volume(p)
    assert vol.data.dtype == np.float32 and vol.data.dtype.isnative  # classic netCDF is big-endian on disk
    np.testing.assert_array_equal(vol.data, temp)
    assert vol.shape_xyz == (4, 3, 2) and vol.fill_value is None and vol.name == "sim"


def test_netcdf_variable_selection_and_fill_value(tmp_path):
    temp = ramp((2, 3, 4), np.float32)
    pres = ramp((2, 3, 4), np.float64) + 0.5
    pres[0, 0, 0] = -1.0e30
    p = tmp_path / "sim.cdf"
    _write_netcdf(
        p,
        {
            "mask": (("y", "x"), np.ones((3, 4), np.int32), {}),
            "temp": (("z", "y", "x"), temp, {"missing_value": np.float32(-5.0)}),
            "pressure": (("z", "y", "x"), pres, {"_FillValue": np.float64(-1.0e30)}),
        },
    )
    vol = read_volume(p, variable="pressure")
    np.testing.assert_array_equal(vol.data, pres)
    assert vol.fill_value == -1.0e30 and vol.source_dtype == "float64"
    assert np.count_nonzero(vol.data == vol.fill_value) == 1
    vol = read_volume(p, variable="temp")
    np.testing.assert_array_equal(vol.data, temp)
    assert vol.fill_value == -5.0
    with pytest.raises(WarpgaussError, match=r"no variable 'rho'.*mask \(3, 4\).*pressure \(2, 3, 4\)"):
        read_volume(p, variable="rho")
    with pytest.raises(WarpgaussError, match="is 2D"):
        read_volume(p, variable="mask")


def test_netcdf4_falls_back_to_hdf5(tmp_path):
    import h5py

    data = ramp((2, 3, 4), np.int16)
    p = tmp_path / "nc4.nc"
    with h5py.File(p, "w") as f:
        f.create_dataset("x", data=np.arange(4.0))
        ds = f.create_dataset("density", data=data)
        ds.attrs["missing_value"] = np.int16(-1)
    vol = read_volume(p, variable="density")
    np.testing.assert_array_equal(vol.data, data)
    assert vol.fill_value == -1.0
    np.testing.assert_array_equal(read_volume(p).data, data)
    # a single time step (1, nz, ny, nx), contiguous (memory-mapped) and chunked (read strided)
    q = tmp_path / "nc4t.nc"
    with h5py.File(q, "w") as f:
        f.create_dataset("a_flat", data=np.zeros((3, 4)))
        f.create_dataset("b_temp", data=data[None])
        f.create_dataset("c_chunked", data=data[None], chunks=(1, 1, 3, 4), compression="gzip")
    np.testing.assert_array_equal(read_volume(q).data, data)
    vol = read_volume(q, variable="c_chunked", stride=2)
    np.testing.assert_array_equal(vol.data, data[::2, ::2, ::2])
    assert vol.spacing == (2.0, 2.0, 2.0)
    # a plain HDF5 file keeps its 4D shape (only netCDF drops a single time step)
    with pytest.raises(WarpgaussError, match=r"t\.h5:v is 4D \(shape \(1, 2, 3, 4\)\)"):
        read_volume(_h5_with(tmp_path / "t.h5", data[None]), dataset="v")


# ------------------------------------------------------------------------------------------ VTK and friends


def test_vti_round_trip_and_pyvista_agrees(tmp_path):
    import pyvista as pv

    data = ramp((3, 4, 5), np.float32)
    p = write_volume(tmp_path / "v.vti", data, spacing=(0.5, 1.0, 2.0), origin=(1.0, 2.0, 3.0), name="rho")
    mesh = pv.read(p)
    assert mesh.dimensions == (5, 4, 3)
    xyz = np.asarray(mesh.point_data["rho"]).reshape(mesh.dimensions, order="F")
    np.testing.assert_array_equal(xyz, data.transpose(2, 1, 0))  # [x, y, z]
    assert xyz[4, 3, 2] == 100 * 2 + 10 * 3 + 4
    vol = read_volume(p)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.data.flags.c_contiguous
    assert vol.spacing == (0.5, 1.0, 2.0) and vol.origin == (1.0, 2.0, 3.0)


@pytest.mark.parametrize("ext", [".vtk", ".nii.gz"])
def test_pyvista_written_formats(tmp_path, ext):
    import pyvista as pv

    data = ramp((3, 4, 5), np.int16)
    grid = pv.ImageData(dimensions=(5, 4, 3), spacing=(0.5, 0.25, 2.0))
    grid.point_data["v"] = data.transpose(2, 1, 0).ravel(order="F")
    grid.save(tmp_path / f"img{ext}")
    vol = read_volume(tmp_path / f"img{ext}")
    np.testing.assert_array_equal(vol.data, data)
    assert vol.shape_xyz == (5, 4, 3)
    np.testing.assert_allclose(vol.spacing, (0.5, 0.25, 2.0))
    assert vol.name == "img"


def test_metaimage_written_by_hand(tmp_path):
    data = ramp((3, 4, 5), np.float32)
    mha = tmp_path / "m.mha"
    mha.write_bytes(
        b"ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        b"Offset = 1 2 3\nElementSpacing = 0.5 1 2\nDimSize = 5 4 3\nElementType = MET_FLOAT\n"
        b"ElementDataFile = LOCAL\n" + data.astype("<f4").tobytes()
    )
    m = read_volume(mha)
    np.testing.assert_array_equal(m.data, data)
    assert m.spacing == (0.5, 1.0, 2.0) and m.origin == (1.0, 2.0, 3.0)


@pytest.mark.parametrize("nx", [5, 12])  # VTK reads a fastest NRRD axis of <= 9 samples as components
@pytest.mark.parametrize(
    "geometry",
    [b"spacings: 0.5 1 2\n", b"space dimension: 3\nspace directions: (0.5,0,0) (0,1,0) (0,0,2)\nspace origin: (1,2,3)\n"],
)
def test_nrrd_written_by_hand(tmp_path, nx, geometry):
    data = ramp((3, 4, nx), np.float32)
    head = b"NRRD0004\ntype: float\ndimension: 3\nsizes: %d 4 3\n" % nx + geometry + b"encoding: raw\nendian: little\n"
    p = tmp_path / "n.nrrd"
    p.write_bytes(head + b"\n" + data.astype("<f4").tobytes())
    vol = read_volume(p)
    np.testing.assert_array_equal(vol.data, data)
    np.testing.assert_allclose(vol.spacing, (0.5, 1.0, 2.0))
    if b"origin" in geometry:
        assert vol.origin == (1.0, 2.0, 3.0)
    # a detached header (.nhdr) pointing at the raw data
    (tmp_path / "n.dat").write_bytes(data.astype("<f4").tobytes())
    (tmp_path / "d.nhdr").write_bytes(head + b"data file: n.dat\n")
    np.testing.assert_array_equal(read_volume(tmp_path / "d.nhdr").data, data)


def test_nrrd_vector_kind_is_refused(tmp_path):
    p = tmp_path / "vec.nrrd"
    head = b"NRRD0004\ntype: float\ndimension: 4\nsizes: 3 4 4 4\nkinds: vector domain domain domain\nencoding: raw\nendian: little\n\n"
    p.write_bytes(head + np.zeros(192, "<f4").tobytes())
    with pytest.raises(WarpgaussError, match="3 components"):
        read_volume(p)


def test_multicomponent_vti_is_refused(tmp_path):
    import pyvista as pv

    grid = pv.ImageData(dimensions=(3, 3, 3))
    grid.point_data["vel"] = np.zeros((27, 3), np.float32)
    grid.save(tmp_path / "vec.vti")
    with pytest.raises(WarpgaussError, match=r"'vel' has 3 components"):
        read_volume(tmp_path / "vec.vti")


# ------------------------------------------------------------------------------------------ MRC / CCP4


def write_mrc(path: Path, vol_zyx: np.ndarray, mapcrs, spacing_xyz, start_crs=(0, 0, 0), mode=2, e="<", nsymbt=80):
    """A minimal MRC2014 file holding ``vol_zyx`` with columns/rows/sections along MAPC/MAPR/MAPS."""
    mapc, mapr, maps = mapcrs
    # file array [section, row, column]; crystal axis a (1 = x, 2 = y, 3 = z) is axis 3 - a of [z, y, x]
    file_arr = vol_zyx.transpose(3 - maps, 3 - mapr, 3 - mapc)
    ns, nr, nc = file_arr.shape
    nz, ny, nx = vol_zyx.shape
    ints = np.zeros(256, e + "i4")
    floats = ints.view(e + "f4")
    ints[0:4] = (nc, nr, ns, mode)
    ints[4:7] = start_crs
    ints[7:10] = (nx, ny, nz)  # MX, MY, MZ along x, y, z
    floats[10:13] = np.asarray(spacing_xyz) * (nx, ny, nz)
    floats[13:16] = 90.0
    ints[16:19] = mapcrs
    ints[22] = 1
    ints[23] = nsymbt
    head = bytearray(ints.tobytes())
    head[208:212] = b"MAP "
    head[212:214] = b"DA" if e == "<" else b"\x11\x11"
    dt = {0: "i1", 1: "i2", 2: "f4", 6: "u2"}[mode]
    blob = bytes(head) + b"\x07" * nsymbt + np.ascontiguousarray(file_arr).astype(e + dt).tobytes()
    opener = {".bz2": bz2.open, ".gz": gzip.open}.get(path.suffix, open)
    with opener(path, "wb") as fh:
        fh.write(blob)
    return path


@pytest.mark.parametrize("mapcrs", [(2, 1, 3), (3, 1, 2), (1, 2, 3)])
def test_mrc_axis_permutation(tmp_path, mapcrs):
    data = ramp((2, 3, 4), np.float32)  # x = 4, y = 3, z = 2
    p = write_mrc(tmp_path / "m.mrc", data, mapcrs, (0.5, 0.25, 2.0), start_crs=(1, 2, 3))
    vol = read_volume(p)
    assert vol.shape_xyz == (4, 3, 2)
    np.testing.assert_array_equal(vol.data, data)
    assert vol.data[1, 2, 3] == 123.0  # [z, y, x]
    np.testing.assert_allclose(vol.spacing, (0.5, 0.25, 2.0))
    start_xyz = [0, 0, 0]
    for axis, s in zip(mapcrs, (1, 2, 3)):
        start_xyz[axis - 1] = s
    np.testing.assert_allclose(vol.origin, np.multiply(start_xyz, (0.5, 0.25, 2.0)))


def test_mrc_2_1_3_file_layout(tmp_path):
    """MAPC/MAPR/MAPS = 2,1,3 (as 1jzv): columns run along y, rows along x; check bytes directly."""
    p = tmp_path / "m.ccp4"
    data = ramp((2, 3, 4), np.float32)
    write_mrc(p, data, (2, 1, 3), (1, 1, 1), nsymbt=0)
    raw = np.frombuffer(p.read_bytes()[1024:], "<f4")
    # the first file row is (x=0, z=0) with y = 0, 1, 2 along the columns
    np.testing.assert_array_equal(raw[:3], [0.0, 10.0, 20.0])
    vol = read_volume(p)
    np.testing.assert_array_equal(vol.data, data)


@pytest.mark.parametrize("ext", [".map.gz", ".mrc.bz2", ".ccp4"])
@pytest.mark.parametrize(("mode", "dtype", "e"), [(1, np.int16, "<"), (6, np.uint16, ">"), (0, np.int8, ">")])
def test_mrc_modes_compression_and_byte_order(tmp_path, ext, mode, dtype, e):
    data = ramp((2, 3, 4), dtype) % 120
    p = write_mrc(tmp_path / f"m{ext}", data, (3, 1, 2), (1, 1, 1), mode=mode, e=e)
    vol = read_volume(p)
    assert vol.data.dtype == np.dtype(dtype) and vol.data.dtype.isnative
    np.testing.assert_array_equal(vol.data, data)
    assert vol.name == "m"


def test_mrc_truncated_and_bad_mode(tmp_path):
    p = write_mrc(tmp_path / "t.mrc", ramp((2, 3, 4)), (1, 2, 3), (1, 1, 1), nsymbt=0)
    p.write_bytes(p.read_bytes()[:-8])
    with pytest.raises(WarpgaussError, match=r"88 bytes of data.*needs 96"):
        read_volume(p)
    q = write_mrc(tmp_path / "c.mrc", ramp((2, 3, 4)), (1, 2, 3), (1, 1, 1), nsymbt=0)
    b = bytearray(q.read_bytes())
    b[12:16] = np.int32(4).tobytes()
    q.write_bytes(bytes(b))
    with pytest.raises(WarpgaussError, match=r"MODE 4"):
        read_volume(q)


# ------------------------------------------------------------------------------------------ gOpenMol plt


def test_plt(tmp_path):
    data = ramp((2, 3, 4), np.float32)
    p = tmp_path / "w.plt"
    head = np.array([3, 200, 2, 3, 4], "<i4").tobytes() + np.array([0, 4, 1, 2.5, -1, 1], "<f4").tobytes()
    p.write_bytes(head + data.tobytes())
    vol = read_volume(p)
    np.testing.assert_array_equal(vol.data, data)
    np.testing.assert_allclose(vol.spacing, (0.5, 0.5, 2.0))  # (max - min) / n
    np.testing.assert_allclose(vol.origin, (-0.75, 1.25, 1.0))  # min + spacing / 2
    p.write_bytes(head + data.tobytes()[:-4])
    with pytest.raises(WarpgaussError, match=r"136 bytes.*needs 140"):
        read_volume(p)


# ------------------------------------------------------------------------------------------ common


def test_stride_stays_lazy_and_scales_spacing(tmp_path):
    data = ramp((5, 6, 7), np.uint8)
    p = write_volume(tmp_path / "s_7x6x5_uint8.raw", data)
    vol = read_volume(p, stride=2)
    assert isinstance(vol.data, np.memmap)
    np.testing.assert_array_equal(vol.data, data[::2, ::2, ::2])
    assert vol.shape_xyz == (4, 3, 3)
    assert vol.spacing == (2.0, 2.0, 2.0)
    assert vol.source_bytes == 4 * 3 * 3
    for bad in (0, -1, 1.5, True):
        with pytest.raises(WarpgaussError, match="stride must be a positive integer"):
            read_volume(p, stride=bad)


def test_missing_file_unknown_extension_and_foreign_options(tmp_path):
    with pytest.raises(WarpgaussError, match=r"^no such file: .*nothere\.raw$"):
        read_volume(tmp_path / "nothere.raw")
    p = tmp_path / "v.xyz"
    p.write_bytes(b"0")
    with pytest.raises(WarpgaussError, match=r"unknown extension '\.xyz'; supported: .*\.h5.*\.nii\.gz.*\.raw"):
        read_volume(p)
    with pytest.raises(WarpgaussError, match="is a directory"):
        read_volume(tmp_path)
    q = write_volume(tmp_path / "a.npy", ramp())
    with pytest.raises(WarpgaussError, match=r"--shape, --dtype do not apply to a\.npy"):
        read_volume(q, shape=(4, 3, 2), dtype="float32")
    assert {".raw", ".npy", ".h5", ".vti", ".nii.gz", ".nc", ".mrc", ".map.bz2", ".plt"} <= set(supported_extensions())


def test_write_refuses_overwrite_and_leaves_nothing_partial(tmp_path):
    data = ramp()
    p = write_volume(tmp_path / "o.npy", data)
    with pytest.raises(WarpgaussError, match="already exists"):
        write_volume(p, data + 1)
    np.testing.assert_array_equal(np.load(p), data)
    write_volume(p, data + 1, force=True)
    np.testing.assert_array_equal(np.load(p), data + 1)
    with pytest.raises(WarpgaussError, match="is 2D"):
        write_volume(tmp_path / "flat.vti", np.zeros((3, 3)))
    with pytest.raises(WarpgaussError, match=r"cannot write o\.mrc: unknown extension"):
        write_volume(tmp_path / "o.mrc", data)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["o.npy"]


def test_volume_properties():
    vol = Volume(np.zeros((2, 3, 4), np.float64), source_dtype="int16")
    assert vol.shape_xyz == (4, 3, 2)
    assert vol.source_itemsize == 2 and vol.source_bytes == 48
    assert Volume(np.zeros((1, 1, 2), np.uint8)).source_bytes == 2


def test_import_is_cheap():
    code = "import sys, warpgauss.readers; print(sorted(m for m in ('pyvista', 'h5py', 'scipy.io', 'vtk') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# ------------------------------------------------------------------------------------------ real data (optional)


def _real(name: str):
    return pytest.mark.skipif(not (DATA / name).exists(), reason=f"{name} not in shared/data")


@_real("1jzv.ccp4")
def test_real_1jzv_permuted_ccp4():
    vol = read_volume(DATA / "1jzv.ccp4")
    assert vol.shape_xyz == (76, 96, 70)
    np.testing.assert_allclose(vol.spacing, (45.8 / 84, 45.8 / 84, 89.65 / 160), rtol=1e-6)
    assert float(vol.data.min()) == pytest.approx(-0.993, abs=1e-3)
    assert float(vol.data.max()) == pytest.approx(9.050, abs=1e-3)


@_real("EMD-3001.map.bz2")
def test_real_emd3001_bz2():
    vol = read_volume(DATA / "EMD-3001.map.bz2")
    assert vol.shape_xyz == (43, 25, 73)
    np.testing.assert_allclose(vol.spacing, (0.448, 0.393, 0.459), atol=1e-3)


@_real("ispg_0.mrc")
def test_real_ispg0_mrc():
    vol = read_volume(DATA / "ispg_0.mrc", stride=2)
    assert vol.shape_xyz == (49, 49, 49) and vol.spacing == (6.0, 6.0, 6.0)


@_real("nAChR_M2_water.plt")
def test_real_plt():
    vol = read_volume(DATA / "nAChR_M2_water.plt")
    assert vol.shape_xyz == (46, 46, 78)
    np.testing.assert_allclose(vol.spacing, (1.0, 1.0, 1.0), atol=1e-5)
    assert float(np.mean(vol.data, dtype=np.float64)) == pytest.approx(0.540, abs=1e-3)
    assert float(np.mean(vol.data == 0)) == pytest.approx(0.380, abs=1e-3)


@_real("mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz")
def test_real_nifti():
    vol = read_volume(DATA / "mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz")
    assert vol.shape_xyz == (197, 233, 189) and vol.source_dtype == "uint8"
    assert float(np.mean(vol.data, dtype=np.float64)) == pytest.approx(38.44, abs=0.01)
    # the template is left-right (x) mirror-symmetric: a wrong axis order would break this
    d = vol.data.astype(np.float64)
    assert np.abs(d - d[:, :, ::-1]).mean() < 0.1 * np.abs(d - d[:, ::-1, :]).mean()


def test_an_empty_or_foreign_zarr_folder_is_refused_in_words(tmp_path):
    """An empty store showed zarr's own StorePath(LocalStore, ...) (#34)."""
    pytest.importorskip("zarr")
    empty = tmp_path / "empty.zarr"
    empty.mkdir()
    with pytest.raises(WarpgaussError, match="empty.zarr is an empty folder, not a Zarr store") as e:
        read_volume(empty)
    foreign = tmp_path / "foreign.zarr"
    (foreign / "sub").mkdir(parents=True)
    with pytest.raises(WarpgaussError, match="cannot open foreign.zarr as a Zarr store: no Zarr array or group metadata") as e:
        read_volume(foreign)
    assert "StorePath" not in str(e.value)
