"""The .wgs model file: exact round trips, exact sizes, compact error bounds, rejection of any damage."""

from __future__ import annotations

import hashlib
import json
import math
import struct
import tracemalloc
import warnings
import zlib

import numpy as np
import pytest
from conftest import uniform_params

from warpgauss.errors import WarpgaussError
from warpgauss.format.compact import COMPACT_BITS, decode_compact, encode_compact
from warpgauss.format.wgs import (
    HEADER_BLOCK,
    MAGIC,
    PARAM_NAMES,
    PREFIX_SIZE,
    header_size,
    read_wgs,
    write_wgs,
)


def realistic_params(rng: np.random.Generator, n: int, box: float = 256.0) -> np.ndarray:
    """Centres in a box^3 volume, log-scales in [-1, 2.5], random unit quaternions, a in [0,1], w in [0.01,1]."""
    return uniform_params(rng, n, centre=(0.0, box), log_scale=(-1.0, 2.5), weight=(0.01, 1.0))


def make_header() -> dict:
    return {
        "format": "warpgauss",
        "name": "vortex µ-test",  # non-ASCII survives (UTF-8 JSON)
        "grid": {"shape_xyz": [256, 128, 64], "spacing": [1.0, 0.5, 0.1], "origin": [-1.5, 0.0, 2.25]},
        "values": {"min": -3.25, "max": 1.0e5},
        "source": {"dtype": "float32", "itemsize": 4, "bytes": 256 * 128 * 64 * 4},
        "encoding": {"iterations": 1500, "samples": 3072, "lr": 8e-3},
        "seed": 1234,
        "transfer_function": {"colormap": "viridis", "lut_rgba8": "ab" * 1024},
    }


@pytest.fixture
def params() -> np.ndarray:
    p = realistic_params(np.random.default_rng(7), 257)
    p[0, 10] = -0.0  # sign of zero, subnormals and extremes must survive bit-exactly
    p[1, 10] = np.float32(1e-45)
    p[2, 10] = np.finfo(np.float32).max
    p[3, 11] = np.finfo(np.float32).tiny
    return p


def _bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, np.float32).view(np.uint32)


def _prefix(path) -> tuple[bytes, int, int, int]:
    with open(path, "rb") as f:
        return struct.unpack("<8sIII", f.read(PREFIX_SIZE))


def _craft(path, header: dict | str, payload: bytes, *, version: int = 1, pad_to: int = HEADER_BLOCK) -> None:
    """A file with a valid prefix and CRC around an arbitrary JSON header (a dict gets a correct sha256)."""
    if isinstance(header, dict):
        header = json.dumps(header, sort_keys=True)
    area = header.encode("utf-8")
    area += b" " * (-(PREFIX_SIZE + len(area)) % pad_to)
    path.write_bytes(struct.pack("<8sIII", MAGIC, version, len(area), zlib.crc32(area)) + area + payload)


def _valid_header(p: np.ndarray, payload: bytes | None = None, **payload_fields) -> tuple[dict, bytes]:
    payload = p.astype("<f4").tobytes() if payload is None else payload
    info = {
        "encoding": "float32",
        "bytes_per_primitive": 48,
        "layout": list(PARAM_NAMES),
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    info.update(payload_fields)
    return {"n": len(p), "payload": info}, payload


# ---------------------------------------------------------------------------------------------
# round trips and sizes
# ---------------------------------------------------------------------------------------------
def test_full_precision_round_trip_is_bit_exact(tmp_path, params):
    hdr = make_header()
    path = tmp_path / "m.wgs"
    size = write_wgs(path, params, hdr)
    out, h = read_wgs(path)
    assert out.dtype == np.float32 and out.shape == params.shape and out.flags.writeable
    np.testing.assert_array_equal(_bits(out), _bits(params))
    for key, value in hdr.items():
        assert h[key] == value
    assert h["n"] == len(params)
    assert h["payload"]["encoding"] == "float32" and h["payload"]["bytes_per_primitive"] == 48
    assert h["payload"]["layout"] == list(PARAM_NAMES) and len(PARAM_NAMES) == 12
    assert h["payload"]["sha256"] == hashlib.sha256(params.astype("<f4").tobytes()).hexdigest()
    assert size == path.stat().st_size


@pytest.mark.parametrize("compact, bpp", [(False, 48), (True, 12)])
def test_file_size_is_exactly_bpp_n_plus_h(tmp_path, params, compact, bpp):
    hdr = make_header()
    n = len(params)
    path = tmp_path / "m.wgs"
    size = write_wgs(path, params, hdr, compact=compact)
    H = header_size(hdr, n, compact=compact)
    magic, version, hlen, _ = _prefix(path)
    assert (magic, version) == (MAGIC, 1)
    assert PREFIX_SIZE + hlen == H and H % HEADER_BLOCK == 0
    assert size == path.stat().st_size == bpp * n + H
    # H is known before the budget: it depends on neither n nor the parameter values
    assert header_size(hdr, 1, compact=compact) == header_size(hdr, 1 << 40, compact=compact) == H
    assert header_size(hdr, n) <= header_size(hdr, n, compact=True)


@pytest.mark.parametrize("compact", [False, True])
def test_header_size_matches_the_file_across_a_block_boundary(tmp_path, compact):
    p = realistic_params(np.random.default_rng(0), 5)
    base = header_size({"pad": ""}, 5, compact=compact)
    # the smallest padding string that pushes the header into the next block
    k = next(k for k in range(HEADER_BLOCK + 1) if header_size({"pad": "x" * k}, 5, compact=compact) > base)
    for kk in (k - 1, k, k + 1):
        hdr = {"pad": "x" * kk}
        path = tmp_path / f"m{kk}.wgs"
        size = write_wgs(path, p, hdr, compact=compact)
        H = header_size(hdr, 5, compact=compact)
        assert H == (base if kk < k else base + HEADER_BLOCK)
        assert size == (12 if compact else 48) * 5 + H
        assert read_wgs(path)[1]["pad"] == "x" * kk


@pytest.mark.parametrize("compact", [False, True])
def test_same_input_gives_identical_bytes(tmp_path, params, compact):
    hdr = make_header()
    reordered = dict(reversed(list(hdr.items())))  # key order does not matter: sorted keys
    write_wgs(tmp_path / "a.wgs", params, hdr, compact=compact)
    write_wgs(tmp_path / "b.wgs", params.copy(), reordered, compact=compact)
    assert (tmp_path / "a.wgs").read_bytes() == (tmp_path / "b.wgs").read_bytes()


def test_owned_keys_are_overwritten_and_numpy_values_converted(tmp_path, params):
    hdr = {"n": 5, "payload": "junk", "vmin": np.float32(0.5), "shape": np.array([3, 4, 5]), "k": np.int64(9)}
    write_wgs(tmp_path / "m.wgs", params, hdr)
    _, h = read_wgs(tmp_path / "m.wgs")
    assert h["n"] == len(params) and h["payload"]["encoding"] == "float32"
    assert h["vmin"] == 0.5 and h["shape"] == [3, 4, 5] and h["k"] == 9
    assert hdr["n"] == 5  # the caller's dict is not modified


@pytest.mark.parametrize("bad", [{"x": float("nan")}, {"x": {1, 2}}, {1: "a", "b": 2}, "not a dict"])
def test_unserialisable_header_rejected(tmp_path, params, bad):
    with pytest.raises(WarpgaussError, match="header"):
        write_wgs(tmp_path / "m.wgs", params, bad)
    assert not list(tmp_path.iterdir())


def test_explicit_header_size_honoured_and_too_small_rejected(tmp_path, params):
    hdr = make_header()
    n = len(params)
    for H in (10_000, 3 * HEADER_BLOCK):
        path = tmp_path / f"m{H}.wgs"
        assert write_wgs(path, params, hdr, header_size=H) == 48 * n + H == path.stat().st_size
        out, h = read_wgs(path)
        np.testing.assert_array_equal(_bits(out), _bits(params))
        assert h["seed"] == hdr["seed"]
    with pytest.raises(WarpgaussError, match="header_size"):
        write_wgs(tmp_path / "small.wgs", params, hdr, header_size=100)
    with pytest.raises(WarpgaussError, match="header_size"):
        write_wgs(tmp_path / "small.wgs", params, hdr, header_size=2.5)
    assert not (tmp_path / "small.wgs").exists()


# ---------------------------------------------------------------------------------------------
# compact96
# ---------------------------------------------------------------------------------------------
def _half_step(lo, hi, bits: int) -> np.ndarray:
    return (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)) / (2 * ((1 << bits) - 1))


def _angle_bound_deg(bits: int) -> float:
    """Worst rotation error of "smallest three" with centred levels over [-1/sqrt2, 1/sqrt2].

    Each small component is off by <= d = (1/sqrt2) / (2**bits - 2), so the 3-vector s by
    e = sqrt(3) d. The largest component l = sqrt(1 - |s|^2) >= 1/2 is recomputed; on |s| <= r =
    sqrt(3)/2 + e it is Lipschitz with L = r / sqrt(1 - r^2), so the chord between the unit
    quaternions is <= e sqrt(1 + L^2), their angle 2 asin(chord/2), the rotation twice that.
    """
    d = (1 / math.sqrt(2)) / ((1 << bits) - 2)
    e = math.sqrt(3) * d
    r = math.sqrt(3) / 2 + e
    chord = e * math.sqrt(1 + (r / math.sqrt(1 - r * r)) ** 2)
    return math.degrees(4 * math.asin(chord / 2))


def _rotation_error_deg(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    dot = np.abs(np.sum(q0 * q1.astype(np.float64), axis=1))
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


def test_compact_allocation_is_96_bits():
    b = COMPACT_BITS
    assert 3 * b["mu"] + 3 * b["log_s"] + b["q_index"] + 3 * b["q"] + b["a"] + b["w"] == 96


def test_compact_round_trip_within_derived_bounds(tmp_path):
    p = realistic_params(np.random.default_rng(3), 50_000)
    hdr = make_header()
    path = tmp_path / "c.wgs"
    size = write_wgs(path, p, hdr, compact=True)
    assert size == 12 * len(p) + header_size(hdr, len(p), compact=True) == path.stat().st_size
    d, h = read_wgs(path)
    assert h["payload"]["encoding"] == "compact96" and h["payload"]["bytes_per_primitive"] == 12
    assert h["payload"]["quant"]["bits"] == COMPACT_BITS
    assert d.dtype == np.float32 and d.shape == p.shape

    b = COMPACT_BITS
    slack = lambda x: 2.0**-22 * np.abs(x) + 1e-12  # noqa: E731  float32 rounding of the decoded value
    err = np.abs(d.astype(np.float64) - p)
    mu_bound = _half_step(p[:, :3].min(0), p[:, :3].max(0), b["mu"])
    assert np.all(err[:, :3] <= mu_bound + slack(p[:, :3]))
    assert np.all(err[:, 3:6] <= _half_step(p[:, 3:6].min(), p[:, 3:6].max(), b["log_s"]) + slack(p[:, 3:6]))
    assert np.all(err[:, 10] <= _half_step(p[:, 10].min(), p[:, 10].max(), b["a"]) + slack(p[:, 10]))
    assert np.all(err[:, 11] <= _half_step(p[:, 11].min(), p[:, 11].max(), b["w"]) + slack(p[:, 11]))
    ang = _rotation_error_deg(p[:, 6:10].astype(np.float64), d[:, 6:10])
    assert ang.max() <= _angle_bound_deg(b["q"]) + 1e-3
    np.testing.assert_allclose(np.linalg.norm(d[:, 6:10].astype(np.float64), axis=1), 1.0, atol=1e-6)
    # the bounds are tight, not vacuous: a large sample comes close to them
    assert err[:, :3].max() > 0.9 * mu_bound.max() and ang.max() > 0.5 * _angle_bound_deg(b["q"])
    # in numbers, for a 256^3 box: centre <= 0.0157 voxel, log-scale <= 0.0138, a, w <= 0.002, angle <= 4.9 deg
    assert mu_bound.max() < 0.0157 and _angle_bound_deg(b["q"]) < 4.9

    # the file agrees with the in-memory codec, and the decoded model is a plain float32 model
    payload, quant = encode_compact(p)
    assert len(payload) == 12 * len(p) and quant == h["payload"]["quant"]
    np.testing.assert_array_equal(_bits(decode_compact(payload, len(p), quant)), _bits(d))
    write_wgs(tmp_path / "full.wgs", d, h)
    again, h2 = read_wgs(tmp_path / "full.wgs")
    np.testing.assert_array_equal(_bits(again), _bits(d))
    assert h2["grid"] == hdr["grid"]


def test_compact_exact_cases_and_degenerate_ranges():
    p = np.zeros((6, 12), np.float32)
    p[:, 0:3] = (10.5, -3.0, 7.25)  # all centres equal: zero-width ranges
    p[:, 3:6] = 0.3
    p[:, 6:10] = [
        [0, 0, 0, 1],
        [0, 0, 0, -1],
        [1, 0, 0, 0],
        [0, -1, 0, 0],
        [0, 0.70710677, 0, 0.70710677],
        [0, 0, 0, 2.0],  # unnormalised input is normalised
    ]
    p[:, 10], p[:, 11] = 0.4, 0.9
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no divide-by-zero on degenerate ranges
        payload, quant = encode_compact(p)
        d = decode_compact(payload, 6, quant)
    cols = [0, 1, 2, 3, 4, 5, 10, 11]
    np.testing.assert_array_equal(d[:, cols], p[:, cols])
    expected_q = np.array([[0, 0, 0, 1], [0, 0, 0, 1], [1, 0, 0, 0], [0, 1, 0, 0]], np.float32)
    np.testing.assert_array_equal(d[:4, 6:10], expected_q)  # axis-aligned orientations are exact
    assert _rotation_error_deg(p[4:5, 6:10].astype(np.float64), d[4:5, 6:10])[0] < 0.05  # float32 floor
    np.testing.assert_array_equal(d[5, 6:10], [0, 0, 0, 1])


def test_compact_range_ends_are_exact():
    p = realistic_params(np.random.default_rng(11), 1000)
    payload, quant = encode_compact(p)
    d = decode_compact(payload, len(p), quant)
    for cols in ([0], [1], [2], [3, 4, 5], [10], [11]):
        assert d[:, cols].min() == p[:, cols].min() and d[:, cols].max() == p[:, cols].max()


# ---------------------------------------------------------------------------------------------
# N edge cases, invalid parameters, overwrite
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("compact", [False, True])
def test_zero_primitives_rejected_and_one_primitive_round_trips(tmp_path, compact):
    with pytest.raises(WarpgaussError, match="at least one primitive"):
        write_wgs(tmp_path / "zero.wgs", np.zeros((0, 12), np.float32), {}, compact=compact)
    assert not (tmp_path / "zero.wgs").exists()
    p = realistic_params(np.random.default_rng(1), 1)
    p[0, 6:10] = (0.0, 0.0, 0.0, 1.0)
    path = tmp_path / "one.wgs"
    assert write_wgs(path, p, {}, compact=compact) == (12 if compact else 48) + header_size({}, 1, compact=compact)
    out, h = read_wgs(path)
    assert h["n"] == 1
    # one primitive: every range is degenerate, so exact, except the three log-scales (one shared range)
    exact = [0, 1, 2, 6, 7, 8, 9, 10, 11]
    np.testing.assert_array_equal(_bits(out[:, exact]), _bits(p[:, exact]))
    assert np.abs(out[0, 3:6] - p[0, 3:6]).max() <= np.ptp(p[0, 3:6]) / (2 * 127) + 1e-6


@pytest.mark.parametrize("col", [0, 4, 8, 10, 11])
@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
def test_non_finite_params_rejected_at_write(tmp_path, params, col, value):
    p = params.copy()
    p[5, col] = value
    for compact in (False, True):
        with pytest.raises(WarpgaussError, match=rf"non-finite.*primitive 5 \({PARAM_NAMES[col]}"):
            write_wgs(tmp_path / "m.wgs", p, {}, compact=compact)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("bad", [np.zeros((4, 11), np.float32), np.zeros(12, np.float32), np.array([[1e39] * 12]), np.full((2, 12), "a")])
def test_bad_param_arrays_rejected_at_write(tmp_path, bad):
    with pytest.raises(WarpgaussError):
        write_wgs(tmp_path / "m.wgs", bad, {})
    assert not list(tmp_path.iterdir())


def test_refuses_to_overwrite_without_force(tmp_path, params):
    path = tmp_path / "m.wgs"
    write_wgs(path, params, {"v": 1})
    before = path.read_bytes()
    with pytest.raises(WarpgaussError, match="force"):
        write_wgs(path, params[:3], {"v": 2})
    assert path.read_bytes() == before
    write_wgs(path, params[:3], {"v": 2}, force=True)
    out, h = read_wgs(path)
    assert h["v"] == 2 and len(out) == 3
    assert [q.name for q in tmp_path.iterdir()] == ["m.wgs"]  # no temporary files left behind


# ---------------------------------------------------------------------------------------------
# damage: every byte, truncation, trailing bytes, garbage, crafted headers
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("compact", [False, True])
def test_any_flipped_byte_is_rejected(tmp_path, compact):
    p = realistic_params(np.random.default_rng(5), 4)
    good = tmp_path / "good.wgs"
    write_wgs(good, p, {"grid": {"shape_xyz": [8, 8, 8]}, "name": "flip"}, compact=compact)
    data = good.read_bytes()
    hlen = _prefix(good)[2]
    json_end = PREFIX_SIZE + len(data[PREFIX_SIZE : PREFIX_SIZE + hlen].rstrip(b" "))
    assert json_end < PREFIX_SIZE + hlen - 1000  # most of the JSON area is padding
    rng = np.random.default_rng(0)
    # every byte of the prefix, the JSON text and the payload; 200 random bytes of the padding
    # (a flip there is caught by the same CRC as one in the JSON text)
    positions = [*range(json_end), *range(PREFIX_SIZE + hlen, len(data))]
    positions += rng.choice(np.arange(json_end, PREFIX_SIZE + hlen), 200, replace=False).tolist()
    bad = tmp_path / "bad.wgs"
    for pos in positions:
        for mask in (0xFF, 1 << int(rng.integers(8))):  # the byte inverted, and one random bit flipped
            buf = bytearray(data)
            buf[pos] ^= mask
            bad.write_bytes(bytes(buf))
            with pytest.raises(WarpgaussError):
                read_wgs(bad)
    read_wgs(good)  # and the undamaged file reads


def test_truncated_and_appended_files_rejected(tmp_path, params):
    good = tmp_path / "good.wgs"
    write_wgs(good, params, {})
    data = good.read_bytes()
    H = header_size({}, len(params))
    bad = tmp_path / "bad.wgs"
    for cut in (0, 1, 8, 19, 20, 21, 100, H - 1, H, H + 47, len(data) - 48, len(data) - 1):
        bad.write_bytes(data[:cut])
        with pytest.raises(WarpgaussError) as e:
            read_wgs(bad)
        if cut >= H:
            assert "truncated" in str(e.value) and f"expected {len(data)}" in str(e.value)
    for extra in (b"\x00", b" " * 48, data[H : H + 48]):
        bad.write_bytes(data + extra)
        with pytest.raises(WarpgaussError, match=f"{len(extra)} trailing bytes"):
            read_wgs(bad)


def test_random_garbage_rejected(tmp_path):
    rng = np.random.default_rng(2)
    bad = tmp_path / "bad.wgs"
    for size in (0, 5, 19, 20, 64, 4096, 10_000):
        bad.write_bytes(rng.integers(0, 256, size, dtype=np.uint8).tobytes())
        with pytest.raises(WarpgaussError, match="not a warpgauss model file"):
            read_wgs(bad)
        bad.write_bytes(MAGIC + rng.integers(0, 256, size, dtype=np.uint8).tobytes())
        with pytest.raises(WarpgaussError):
            read_wgs(bad)
    bad.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    with pytest.raises(WarpgaussError, match="bad magic"):
        read_wgs(bad)
    with pytest.raises(WarpgaussError, match="no such model file"):
        read_wgs(tmp_path / "missing.wgs")
    with pytest.raises(WarpgaussError, match="directory"):
        read_wgs(tmp_path)


def test_huge_declared_header_length_rejected_without_allocating(tmp_path):
    bad = tmp_path / "bad.wgs"
    bad.write_bytes(struct.pack("<8sIII", MAGIC, 1, 0xFFFFFFFF, 0) + b"{}" + b" " * 100)
    tracemalloc.start()
    try:
        with pytest.raises(WarpgaussError, match="header length 4294967295 exceeds"):
            read_wgs(bad)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20


def test_huge_declared_n_rejected_without_allocating(tmp_path):
    p = realistic_params(np.random.default_rng(0), 2)
    header, payload = _valid_header(p)
    header["n"] = 1 << 50
    _craft(tmp_path / "bad.wgs", header, payload)
    tracemalloc.start()
    try:
        with pytest.raises(WarpgaussError, match="truncated"):
            read_wgs(tmp_path / "bad.wgs")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20


def test_crafted_file_with_valid_checksums_reads(tmp_path):
    """The crafting helper itself produces a readable file, so the rejections below are specific."""
    p = realistic_params(np.random.default_rng(0), 3)
    header, payload = _valid_header(p)
    _craft(tmp_path / "ok.wgs", header, payload)
    out, h = read_wgs(tmp_path / "ok.wgs")
    np.testing.assert_array_equal(_bits(out), _bits(p))


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda h: "[1, 2, 3]", "not a JSON object"),
        (lambda h: '{"n": 3, "payload": ', "not valid UTF-8 JSON"),
        (lambda h: b"\xff\xfe".decode("latin-1"), "not valid UTF-8 JSON"),
        (lambda h: {k: v for k, v in h.items() if k != "n"}, "lacks the required key 'n'"),
        (lambda h: {k: v for k, v in h.items() if k != "payload"}, "lacks the required key 'payload'"),
        (lambda h: {**h, "n": -1}, "not a non-negative integer"),
        (lambda h: {**h, "n": 3.0}, "not a non-negative integer"),
        (lambda h: {**h, "n": True}, "not a non-negative integer"),
        (lambda h: {**h, "n": "3"}, "not a non-negative integer"),
        (lambda h: {**h, "payload": [1]}, "not an object"),
        (lambda h: {**h, "payload": {**h["payload"], "encoding": "float16"}}, "unknown payload encoding"),
        (lambda h: {**h, "payload": {**h["payload"], "bytes_per_primitive": 12}}, "bytes per primitive"),
        (lambda h: {**h, "payload": {**h["payload"], "layout": list(reversed(PARAM_NAMES))}}, "layout"),
        (lambda h: {**h, "payload": {**h["payload"], "sha256": 5}}, "sha256"),
        (lambda h: {**h, "payload": {k: v for k, v in h["payload"].items() if k != "sha256"}}, "lacks 'sha256'"),
        (lambda h: {**h, "payload": {**h["payload"], "sha256": "0" * 64}}, "payload checksum mismatch"),
    ],
)
def test_crafted_headers_rejected(tmp_path, mutate, match):
    p = realistic_params(np.random.default_rng(0), 3)
    header, payload = _valid_header(p)
    _craft(tmp_path / "bad.wgs", mutate(header), payload)
    with pytest.raises(WarpgaussError, match=match):
        read_wgs(tmp_path / "bad.wgs")


def test_unsupported_version_and_empty_model_rejected(tmp_path):
    p = realistic_params(np.random.default_rng(0), 3)
    header, payload = _valid_header(p)
    _craft(tmp_path / "v4.wgs", header, payload, version=4)
    with pytest.raises(WarpgaussError, match="unsupported .wgs format version 4"):
        read_wgs(tmp_path / "v4.wgs")
    _craft(tmp_path / "v3.wgs", header, payload, version=3)  # version 3 is a coded payload in layout 2
    with pytest.raises(WarpgaussError, match="version 3 file without a layout 2 coded payload"):
        read_wgs(tmp_path / "v3.wgs")
    _craft(tmp_path / "v2.wgs", header, payload, version=2)  # version 2 is a file with a residual
    with pytest.raises(WarpgaussError, match="version 2 file without a residual"):
        read_wgs(tmp_path / "v2.wgs")
    header, payload = _valid_header(p[:0])
    _craft(tmp_path / "empty.wgs", header, payload)
    with pytest.raises(WarpgaussError, match="no primitives"):
        read_wgs(tmp_path / "empty.wgs")


def test_non_finite_payload_with_valid_checksum_rejected(tmp_path):
    p = realistic_params(np.random.default_rng(0), 3)
    p[1, 3] = np.inf
    header, payload = _valid_header(p)
    _craft(tmp_path / "bad.wgs", header, payload)
    with pytest.raises(WarpgaussError, match=r"non-finite.*primitive 1 \(log_sx"):
        read_wgs(tmp_path / "bad.wgs")


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda q: None, "quantisation ranges"),
        (lambda q: {**q, "bits": {**q["bits"], "mu": 14}}, "bit allocation"),
        (lambda q: {k: v for k, v in q.items() if k != "bits"}, "bit allocation"),
        (lambda q: {**q, "a_lo": float("nan")}, "a_lo"),
        (lambda q: {**q, "w_hi": "1"}, "w_hi"),
        (lambda q: {**q, "mu_lo": [0.0, 1.0]}, "mu_lo"),
        (lambda q: {**q, "mu_hi": [0.0, 1.0, float("inf")]}, "mu_hi"),
        (lambda q: {**q, "log_s_lo": q["log_s_hi"] + 1.0}, "lo > hi"),
    ],
)
def test_crafted_compact_quant_rejected(tmp_path, mutate, match):
    p = realistic_params(np.random.default_rng(0), 3)
    payload, quant = encode_compact(p)
    header, _ = _valid_header(p, payload, encoding="compact96", bytes_per_primitive=12)
    q = mutate(quant)
    if q is not None:
        header["payload"]["quant"] = q
    _craft(tmp_path / "bad.wgs", header, payload)
    with pytest.raises(WarpgaussError, match=match):
        read_wgs(tmp_path / "bad.wgs")
    header["payload"]["quant"] = quant  # and the unmutated file reads
    _craft(tmp_path / "ok.wgs", header, payload)
    np.testing.assert_array_equal(read_wgs(tmp_path / "ok.wgs")[0], decode_compact(payload, 3, quant))


def test_error_messages_are_one_line(tmp_path, params):
    bad = tmp_path / "bad.wgs"
    write_wgs(bad, params, make_header())
    data = bytearray(bad.read_bytes())
    data[-1] ^= 0xFF
    bad.write_bytes(bytes(data))
    with pytest.raises(WarpgaussError) as e:
        read_wgs(bad)
    msg = str(e.value)
    assert "\n" not in msg and "payload checksum mismatch: the file is damaged" in msg and str(bad) in msg


@pytest.mark.parametrize("alias, encoding", [("full", "float32"), ("compact", "compact96"), ("float32", "float32")])
def test_format_aliases_are_one_table(tmp_path, params, alias, encoding):
    """The names the command line takes ("full", "compact") are the file API's too: one table
    (wgs.FORMAT_ALIASES) serves warpgauss.encode, Model.save and write_wgs; an unknown name is
    refused in one line naming the choices."""
    from warpgauss.format.model import Model

    path = tmp_path / "m.wgs"
    write_wgs(path, params, make_header(), encoding=alias)
    assert read_wgs(path)[1]["payload"]["encoding"] == encoding
    m = Model(params, {**make_header(), "values": {"min": 0.0, "max": 1.0}})
    m.save(tmp_path / "s.wgs", encoding=alias)
    assert read_wgs(tmp_path / "s.wgs")[1]["payload"]["encoding"] == encoding
    with pytest.raises(WarpgaussError, match="unknown model format 'jpeg'; use coded, full"):
        write_wgs(tmp_path / "x.wgs", params, make_header(), encoding="jpeg")
