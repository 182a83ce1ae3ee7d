"""The numcodecs codec (warpgauss.codec): Zarr chunks as models, on the CPU device."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

numcodecs = pytest.importorskip("numcodecs")
zarr = pytest.importorskip("zarr")

from warpgauss import Model, WarpgaussError, psnr  # noqa: E402
from warpgauss.codec import CONSTANT_MAGIC, WarpGauss  # noqa: E402

FAST = {"iterations": 20, "device": "cpu"}


def _volume(shape=(24, 24, 72)) -> np.ndarray:
    z, y, x = np.meshgrid(*(np.linspace(0.0, 1.0, s) for s in shape), indexing="ij")
    return (np.sin(7 * x) * np.cos(5 * y) + 0.8 * np.exp(-((x - 0.6) ** 2 + (y - 0.4) ** 2 + (z - 0.5) ** 2) / 0.02)).astype(np.float32)


def _zarr_v2(a: np.ndarray, codec: WarpGauss, chunks=(24, 24, 24), stored: dict | None = None):
    store = zarr.storage.MemoryStore({} if stored is None else stored)
    arr = zarr.create_array(store=store, shape=a.shape, chunks=chunks, dtype=a.dtype, compressors=codec, zarr_format=2, fill_value=0)
    arr[:] = a
    return arr


def test_zarr_array_of_three_chunks_round_trips():
    a = _volume()
    codec = WarpGauss(ratio=8, **FAST)
    stored: dict = {}
    back = _zarr_v2(a, codec, stored=stored)[:]
    assert back.shape == a.shape and back.dtype == a.dtype
    assert sorted(k for k in stored if not k.startswith(".")) == ["0.0.0", "0.0.1", "0.0.2"]
    for i in range(3):
        chunk = np.ascontiguousarray(a[:, :, 24 * i : 24 * (i + 1)])
        data = stored[f"0.0.{i}"].to_bytes()
        got = back[:, :, 24 * i : 24 * (i + 1)]
        assert Model.from_bytes(data).shape_xyz == (24, 24, 24) and len(data) <= chunk.nbytes / 8
        assert psnr(got, chunk) > 25.0  # a 20-iteration fit at CR 8; the mean as a constant scores 13.5 dB
        assert data == codec.encode(chunk), "Zarr stores the codec's bytes, the same for the same chunk"
        assert np.array_equal(got, codec.decode(data))
    assert not np.array_equal(back, a)  # lossy: the test would see a pass-through


def test_same_chunk_same_bytes_and_the_bytes_are_a_model():
    a = np.ascontiguousarray(_volume()[:, :, :24])
    codec = WarpGauss(ratio=8, **FAST)
    one, two = codec.encode(a), codec.encode(a)
    assert one == two
    m = Model.from_bytes(one)
    assert m.shape_xyz == (24, 24, 24) and m.header["source"]["dtype"] == "float32"
    assert len(one) <= a.nbytes / 8 and m.to_bytes() == one


@pytest.mark.parametrize("dtype", [np.float32, np.int16])
def test_bounded_mode_holds_the_bound_on_every_voxel(dtype):
    a = _volume((24, 24, 48))
    if dtype is np.int16:
        a = np.rint(a * 1000).astype(np.int16)
    bound = 0.01 * float(a.max() - a.min())
    codec = WarpGauss(max_error=bound, **FAST)
    back = _zarr_v2(a, codec)[:]
    assert back.dtype == a.dtype and back.shape == a.shape
    err = np.abs(back.astype(np.float64) - a.astype(np.float64))
    assert err.max() <= bound
    assert err.max() > 0 or dtype is np.int16  # not stored exactly: the bound is what holds


def test_decode_into_out_and_a_2d_chunk_is_one_slice():
    a = _volume((1, 32, 64))[0]
    codec = WarpGauss(ratio=3, **FAST)
    data = codec.encode(a)
    assert Model.from_bytes(data).shape_xyz == (64, 32, 1)
    out = np.empty_like(a)
    got = codec.decode(data, out=out)
    assert got is out and psnr(out, a) > 20.0
    assert codec.decode(data).shape == (1, 32, 64)


def test_constant_chunks_are_records_that_decode_exactly():
    codec = WarpGauss(ratio=8, **FAST)
    for a in (np.full((24, 24, 24), 7, np.uint8), np.full((8, 8, 8), np.nan, np.float32)):
        data = codec.encode(a)
        assert data.startswith(CONSTANT_MAGIC) and len(data) < 200
        back = codec.decode(data)
        assert back.dtype == a.dtype and np.array_equal(back, a, equal_nan=True)
    with pytest.raises(WarpgaussError, match="damaged"):
        codec.decode(data[:-3])


def test_config_round_trips_and_the_registry_finds_the_codec():
    codec = WarpGauss(ratio=12.5, max_error=0.25, iterations=30, samples=1024, preset="fast", format="float32", seed=3, device="cpu")
    config = codec.get_config()
    assert json.loads(json.dumps(config)) == config and config["id"] == "warpgauss"
    again = WarpGauss.from_config({k: v for k, v in config.items() if k != "id"})
    assert again.get_config() == config
    found = numcodecs.get_codec(config)
    assert isinstance(found, WarpGauss) and found.get_config() == config
    assert numcodecs.registry.codec_registry["warpgauss"] is WarpGauss


def test_the_entry_point_finds_the_codec_without_an_import():
    # a fresh interpreter that never imports warpgauss.codec: numcodecs loads it by its id
    code = "import numcodecs, sys; c = numcodecs.get_codec({'id': 'warpgauss', 'ratio': 4}); print(type(c).__module__, 'warpgauss.codec' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["warpgauss.codec", "True"]


@pytest.mark.parametrize(
    "config, says",
    [
        ({"ratio": -1}, "ratio=...) must be a positive finite number"),
        ({"ratio": "8"}, "ratio=...) must be a positive finite number"),
        ({"max_error": float("nan")}, "max_error=...) must be a positive"),
        ({"budget": 2.5}, "budget=...) must be a positive integer"),
        ({"iterations": -3}, "iterations=...) must be a non-negative integer"),
        ({"ratio": 8, "budget": 100}, "one of ratio= and budget="),
        ({"preset": "fastest"}, "preset='fastest') is not one of"),
        ({"format": "zip"}, "format='zip') is not one of"),
        ({"device": 0}, "device=...) must be a Warp device name"),
    ],
)
def test_bad_configs_are_refused_in_one_line(config, says):
    with pytest.raises(WarpgaussError, match=None) as e:
        numcodecs.get_codec({"id": "warpgauss", **config})
    assert says in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize(
    "chunk, says",
    [
        (np.zeros(64, np.float32), "3-D chunks (2-D as one slice), got a 1-D"),
        (np.zeros((2, 4, 4, 4), np.float32), "got a 4-D"),
        (np.zeros((8, 8, 8), np.complex64), "integer and float chunks"),
        (np.zeros((8, 8, 8), ">f4"), "native byte order"),
    ],
)
def test_bad_chunks_are_refused_in_one_line(chunk, says):
    with pytest.raises(WarpgaussError) as e:
        WarpGauss(**FAST).encode(chunk)
    assert says in str(e.value) and "\n" not in str(e.value)


def test_a_chunk_too_small_for_the_ratio_is_refused_and_damaged_bytes_too():
    with pytest.raises(WarpgaussError, match="largest possible ratio"):
        WarpGauss(ratio=20, **FAST).encode(_volume((16, 16, 16)))
    data = bytearray(WarpGauss(ratio=8, **FAST).encode(np.ascontiguousarray(_volume()[:, :, :24])))
    data[-1] ^= 0xFF
    with pytest.raises(WarpgaussError, match="the model bytes: payload checksum mismatch"):
        WarpGauss(**FAST).decode(bytes(data))


def test_without_numcodecs_warpgauss_imports_and_the_codec_says_what_to_install():
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] == 'numcodecs': raise ImportError(name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import warpgauss\n"
        "try:\n"
        "    import warpgauss.codec\n"
        "except warpgauss.WarpgaussError as e:\n"
        "    print(e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out == "warpgauss.codec needs numcodecs: pip install 'warpgauss[zarr]'\n"
