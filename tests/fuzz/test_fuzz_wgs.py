"""Fuzz the .wgs parser: random bytes, truncations, bit flips, huge declared lengths, crafted headers.

Invariant: ``read_wgs`` / ``Model.load`` either return exactly what was written, or raise a
one-line WarpgaussError; nothing else escapes, nothing is allocated from a length the file
declares but does not hold, and a model that loads can be described, sized and decoded.
"""

from __future__ import annotations

import hashlib
import json
import struct
import tempfile
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from conftest import uniform_params
from fuzz_support import assert_clear_refusal, fuzz
from hypothesis import assume, example, given
from hypothesis import strategies as st

from warpgauss.errors import WarpgaussError
from warpgauss.format.model import Model, make_header
from warpgauss.format.wgs import HEADER_BLOCK, MAGIC, PREFIX_SIZE, read_wgs, write_wgs

_TMP = Path(tempfile.mkdtemp(prefix="wgs-fuzz-"))


def _params(n: int, seed: int = 0) -> np.ndarray:
    return uniform_params(np.random.default_rng(seed), n, centre=(0, 8), log_scale=(-1, 1))


def _header() -> dict:
    return make_header(
        shape_xyz=(8, 8, 8),
        spacing=(1, 1, 1),
        origin=(0, 0, 0),
        vmin=-1.0,
        vmax=2.0,
        source_dtype="float32",
        source_itemsize=4,
        name="fuzz",
        encoding={"stride": 1},
        seed=0,
    )


def _valid_bytes(n: int, compact: bool) -> bytes:
    path = _TMP / f"valid_{n}_{int(compact)}.wgs"
    if not path.exists():
        write_wgs(path, _params(n), _header(), compact=compact)
    return path.read_bytes()


VALID = {(n, c): _valid_bytes(n, c) for n in (1, 3) for c in (False, True)}


def _load(data: bytes, name: str = "f.wgs"):
    path = _TMP / name
    path.write_bytes(data)
    return Model.load(path)


def _refused(data: bytes) -> WarpgaussError:
    with pytest.raises(WarpgaussError) as e:
        _load(data)
    assert_clear_refusal(e.value)
    return e.value


@fuzz(150)
@given(st.binary(max_size=6000), st.booleans())
def test_random_bytes_are_refused(data, with_magic):
    if with_magic:
        data = MAGIC + data
    _refused(data)


@fuzz(120)
@given(st.sampled_from(sorted(VALID)), st.data())
def test_truncations_and_trailing_bytes_are_refused(key, data):
    good = VALID[key]
    cut = data.draw(st.integers(0, len(good) - 1), label="cut")
    _refused(good[:cut])
    extra = data.draw(st.binary(min_size=1, max_size=64), label="extra")
    _refused(good + extra)


@fuzz(200)
@given(st.sampled_from(sorted(VALID)), st.data())
def test_bit_flips_anywhere_are_refused(key, data):
    good = bytearray(VALID[key])
    flips = data.draw(st.lists(st.integers(0, 8 * len(good) - 1), min_size=1, max_size=8, unique=True), label="bits")
    for bit in flips:
        good[bit // 8] ^= 1 << (bit % 8)
    _refused(bytes(good))


def _prefix(hlen: int, area: bytes, version: int = 1) -> bytes:
    return struct.pack("<8sIII", MAGIC, version, hlen, zlib.crc32(area))


@fuzz(100)
@given(
    hlen=st.integers(0, 2**32 - 1),
    n=st.one_of(st.integers(0, 2**64), st.integers(-(2**63), -1)),
    bpp=st.sampled_from([48, 12]),
)
@example(hlen=2**32 - 1, n=1, bpp=48)
@example(hlen=100, n=2**62, bpp=48)
def test_huge_declared_lengths_are_refused_without_allocating(hlen, n, bpp):
    """A prefix or header that declares more than the file holds never drives an allocation."""
    enc = "float32" if bpp == 48 else "compact96"
    head = {
        "n": n,
        "payload": {"encoding": enc, "bytes_per_primitive": bpp, "layout": list(_layout()), "sha256": "0" * 64},
    }
    area = json.dumps(head).encode()
    area += b" " * (-(PREFIX_SIZE + len(area)) % HEADER_BLOCK)
    crafted = [
        _prefix(hlen, area) + area,  # declared header length vs the real one
        _prefix(len(area), area) + area + b"\0" * 96,  # declared n vs the payload
    ]
    for blob in crafted:
        path = _TMP / "huge.wgs"
        path.write_bytes(blob)
        tracemalloc.start()
        try:
            with pytest.raises(WarpgaussError) as e:
                read_wgs(path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert_clear_refusal(e.value)
        assert peak < 4 * len(blob) + (1 << 20), peak


def _layout():
    from warpgauss.format.wgs import PARAM_NAMES

    return PARAM_NAMES


# JSON values of every kind, to put where the reader expects a specific one
JSON = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats(allow_nan=False, allow_infinity=False) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=8,
)

FIELDS = [
    ("n",),
    ("payload",),
    ("payload", "encoding"),
    ("payload", "bytes_per_primitive"),
    ("payload", "layout"),
    ("payload", "sha256"),
    ("payload", "quant"),
    ("grid",),
    ("grid", "shape_xyz"),
    ("grid", "spacing"),
    ("grid", "origin"),
    ("values",),
    ("values", "min"),
    ("values", "max"),
    ("source",),
    ("source", "bytes"),
    ("source", "itemsize"),
    ("source", "dtype"),
    ("encoding",),
    ("encoding", "stride"),
    ("transfer_function",),
    ("transfer_function", "lut_rgba8"),
    ("transfer_function", "opacity"),
    ("name",),
    ("seed",),
]
SHAPES = st.lists(st.integers(-3, 2**40), min_size=0, max_size=4)


def _craft(header: dict, payload: bytes, *, fix_sha: bool) -> bytes:
    if fix_sha and isinstance(header.get("payload"), dict):
        header["payload"]["sha256"] = hashlib.sha256(payload).hexdigest()
    area = json.dumps(header).encode()
    area += b" " * (-(PREFIX_SIZE + len(area)) % HEADER_BLOCK)
    return _prefix(len(area), area) + area + payload


def _use(m: Model) -> None:
    """What info, decode and eval do with a loaded model: none of it may raise anything else."""
    from warpgauss.render import transfer

    m.shape_xyz, m.value_range, m.source_bytes  # noqa: B018
    m.file_size(), m.file_size(compact=True), m.compression_ratio  # noqa: B018
    m.decoded_spacing(), m.decoded_origin(), m.decoded_spacing((2, 3, 4)), m.decoded_origin((2, 3, 4))  # noqa: B018
    transfer.from_header(m.header)
    v = m.decode(shape_xyz=(3, 2, 2), device="cpu")
    assert np.isfinite(v).all()


@fuzz(250)
@given(
    key=st.sampled_from(sorted(VALID)),
    field=st.sampled_from(FIELDS),
    value=st.one_of(JSON, SHAPES, st.just([8, 8, 8]), st.just([1e308, 1.0, 1.0]), st.just([0, 0, 0])),
    fix_sha=st.booleans(),
)
def test_crafted_headers_with_valid_checksums_load_or_are_refused(key, field, value, fix_sha):
    """The checksums prove the bytes are as written, not that the writer filled the fields sensibly."""
    good = VALID[key]
    hlen = struct.unpack("<8sIII", good[:PREFIX_SIZE])[2]
    header = json.loads(good[PREFIX_SIZE : PREFIX_SIZE + hlen])
    payload = good[PREFIX_SIZE + hlen :]
    node = header
    for k in field[:-1]:
        node = node[k]
    node[field[-1]] = value
    blob = _craft(header, payload, fix_sha=fix_sha)
    try:
        m = _load(blob)
    except WarpgaussError as e:
        assert_clear_refusal(e)
        return
    _use(m)  # it loaded: every accessor works and the decode is finite


def test_crafted_header_with_a_huge_grid_is_refused_before_decoding():
    good = VALID[(1, False)]
    hlen = struct.unpack("<8sIII", good[:PREFIX_SIZE])[2]
    header = json.loads(good[PREFIX_SIZE : PREFIX_SIZE + hlen])
    header["grid"]["shape_xyz"] = [100_000, 100_000, 100_000]
    with pytest.raises(WarpgaussError, match="more than"):
        _load(_craft(header, good[PREFIX_SIZE + hlen :], fix_sha=True))


@fuzz(60)
@given(st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), min_size=12, max_size=12), st.booleans())
def test_any_float_payload_with_valid_checksums_loads_finite_or_is_refused(row, compact):
    """A non-finite parameter is refused by name; a finite one loads and decodes finite."""
    p = np.array([row], np.float32)
    good = VALID[(1, False)]
    hlen = struct.unpack("<8sIII", good[:PREFIX_SIZE])[2]
    header = json.loads(good[PREFIX_SIZE : PREFIX_SIZE + hlen])
    blob = _craft(header, p.astype("<f4").tobytes(), fix_sha=True)
    try:
        m = _load(blob)
    except WarpgaussError as e:
        assert_clear_refusal(e)
        assert not np.isfinite(p).all()
        return
    assert np.isfinite(p).all() and np.array_equal(m.params, p)
    assume(np.abs(p[0, 3:6]).max() < 30)  # decode cost does not depend on it, but keep the grid sane
    _use(m)


@pytest.mark.parametrize("a, w, expect", [(3e38, 1.0, 1e15), (0.5, 3e38, 0.5), (-3e38, 2e38, -1e15)])
def test_extreme_but_finite_values_and_weights_decode_finite(a, w, expect):
    """Two coincident primitives whose products overflow float32: the evaluation bound keeps V~ finite."""
    p = _params(2)
    p[:, :3] = 4.0
    p[:, 10], p[:, 11] = a, w
    good = VALID[(1, False)]
    hlen = struct.unpack("<8sIII", good[:PREFIX_SIZE])[2]
    header = json.loads(good[PREFIX_SIZE : PREFIX_SIZE + hlen])
    header["n"] = 2
    m = _load(_craft(header, p.astype("<f4").tobytes(), fix_sha=True))
    v = m.field("cpu").evaluate(np.array([[4.0, 4.0, 4.0]], np.float32))
    assert np.isfinite(v).all() and v[0] == pytest.approx(expect, rel=1e-5)
    _use(m)
