"""Layout 2 of the coded payload (``.wgs`` format version 3): centres as sorted Morton key gaps,
attributes as top-aligned byte planes. Exact round trips against layout 1 (the same codes),
earlier files still read, determinism, and refusal of damaged or crafted payloads."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
import zstandard
from test_wgs import _craft, _valid_header, make_header, realistic_params

from warpgauss.errors import WarpgaussError
from warpgauss.format import coded, coded_keys
from warpgauss.format.wgs import (
    CODED_KEYS_VERSION,
    FORMAT_VERSION,
    PREFIX,
    PREFIX_SIZE,
    _coded_placeholder,
    read_wgs,
    read_wgs_bytes,
    wgs_bytes,
    write_wgs,
)


def _both(p: np.ndarray, bits=None) -> tuple[np.ndarray, bytes, bytes]:
    """(decoded layout 2, payload 2, payload 1), after checking both layouts decode to the projected
    model in the same order."""
    one, q1, o1 = coded.encode_coded(p, bits, layout=1)
    two, q2, o2 = coded.encode_coded(p, bits)
    assert q2["layout"] == 2 and "layout" not in q1
    np.testing.assert_array_equal(o1, o2)
    d2 = coded.decode_coded(two, len(p), q2)
    np.testing.assert_array_equal(d2, coded.decode_coded(one, len(p), q1))
    np.testing.assert_array_equal(d2, coded.project_coded(p, bits)[o2])
    return d2, two, one


def _structured(n: int, seed: int = 0) -> np.ndarray:
    """A model like a refined one: centres on a jittered lattice in a 64^3 box, scales that follow
    the spacing, smooth values."""
    rng = np.random.default_rng(seed)
    p = realistic_params(rng, n, box=64.0)
    side = int(np.ceil(n ** (1 / 3)))
    g = np.stack(np.unravel_index(np.arange(n), (side, side, side)), 1) * (64.0 / side)
    p[:, :3] = g + rng.normal(0, 0.7, (n, 3))
    p[:, 3:6] = np.log(64.0 / side) + rng.normal(0, 0.3, (n, 3))
    p[:, 10] = np.sin(p[:, 0] / 9.0) * np.cos(p[:, 1] / 7.0)
    return p


def test_lift_and_unlift_are_inverse():
    rng = np.random.default_rng(0)
    for n in (0, 1, 2, 3, 5, 8, 9, 100, 1023, 1024, 1025):
        c = rng.integers(-(1 << 52), 1 << 52, n)
        r = coded_keys.lift(c)
        np.testing.assert_array_equal(coded_keys.unlift(r), c)
    smooth = np.round(1000 * np.sin(np.arange(4000) / 50.0)).astype(np.int64)
    assert np.median(np.abs(coded_keys.lift(smooth))) <= 2  # a smooth column leaves small residuals (but at coarse levels)


def test_lifting_rows_at_once_is_lifting_each_row():
    """coded_keys.lift of a (k, n) array (the encoder lifts every attribute column at once, one a
    row) gives each row's own residuals, and unlift inverts it, at lengths that are and are not
    powers of two."""
    rng = np.random.default_rng(2)
    for n in (1, 2, 3, 5, 8, 33, 1000):
        c = rng.integers(-(1 << 40), 1 << 40, (9, n))
        r = coded_keys.lift(c)
        np.testing.assert_array_equal(r, np.stack([coded_keys.lift(row) for row in c]))
        np.testing.assert_array_equal(coded_keys.unlift(r), c)


def test_a_column_smooth_along_the_curve_is_stored_as_residuals():
    p = _structured(4000, 8)
    payload, quant, _ = coded.encode_coded(p, {"mu": 3, "log_s": 5, "q": 6, "a": 12, "w": 6})
    mask = int.from_bytes(zstandard.ZstdDecompressor().decompress(payload)[:2], "little")
    assert mask >> 10 & 1  # the value (a smooth function of the centre) is predicted
    assert not mask >> 7 & 1  # a random rotation component is not
    _both(p, {"mu": 3, "log_s": 5, "q": 6, "a": 12, "w": 6})


@pytest.mark.parametrize("n", [1, 2, 3, 40, 2500])
def test_round_trips_equal_layout_1(n):
    _both(realistic_params(np.random.default_rng(n), n))
    _both(_structured(n, n), {"mu": 6, "log_s": 8, "q": 10, "a": 12, "w": 10})


def test_no_primitives_codes_and_decodes():
    p = np.zeros((0, 12), np.float32)
    payload, quant, order = coded.encode_coded(p)
    assert len(order) == 0 and coded.decode_coded(payload, 0, quant).shape == (0, 12)


def test_duplicate_centres_and_extreme_codes():
    rng = np.random.default_rng(3)
    p = realistic_params(rng, 300)
    p[100:200, :3] = p[100, :3]  # a hundred Gaussians on one centre: gaps of 0
    p[:50, 10] = rng.choice([-1e6, 1e6], 50)  # amplitudes 40 bits wide at 12 bits
    p[50:60, 3:6] = 30.0
    _both(p, {"mu": 8, "log_s": 8, "q": 16, "a": 12, "w": 24})
    # centres 2^21 - 1 codes apart on every axis: keys up to 2^63 - 1, gaps of 63 bits
    p2 = realistic_params(rng, 2)
    p2[0, :3], p2[1, :3] = 0.0, float((1 << 21) - 1)
    d, payload, _ = _both(p2, {"mu": 0, "log_s": 4, "q": 5, "a": 7, "w": 5})
    assert d[-1, 0] == (1 << 21) - 1


def test_a_centre_range_beyond_the_keys_falls_back_to_layout_1(tmp_path):
    p = realistic_params(np.random.default_rng(1), 20)
    p[0, 0], p[1, 0] = float(1 << 21), 0.0  # 2^21 + 1 codes at mu 0 bits: no 21-bit key
    payload, quant, _ = coded.encode_coded(p, {"mu": 0, "log_s": 4, "q": 5, "a": 7, "w": 5})
    assert "layout" not in quant
    with pytest.raises(WarpgaussError, match="no layout 2"):
        coded.encode_coded(p, {"mu": 0, "log_s": 4, "q": 5, "a": 7, "w": 5}, layout=2)
    data = wgs_bytes(p, make_header(), encoding="coded", bits={"mu": 0, "log_s": 4, "q": 5, "a": 7, "w": 5})
    assert PREFIX.unpack(data[:PREFIX_SIZE])[1] == FORMAT_VERSION  # a layout-1 file is a version-1 file
    with pytest.raises(WarpgaussError, match="unknown coded layout 3"):
        coded.encode_coded(p, layout=3)


def test_layout_2_codes_smaller_than_layout_1_on_structured_models():
    for n, bits in ((3000, None), (20000, {"mu": 3, "log_s": 5, "q": 6, "a": 9, "w": 6})):
        _, two, one = _both(_structured(n, 7), bits)
        assert len(two) < 0.97 * len(one), (n, len(two), len(one))


def test_coding_is_deterministic_and_independent_of_input_order():
    p = _structured(3000, 2)
    a = coded.encode_coded(p)[0]
    assert coded.encode_coded(p)[0] == a
    assert coded.encode_coded(p[np.random.default_rng(0).permutation(len(p))])[0] == a


def test_a_coding_on_threads_writes_the_bytes_of_one_thread(monkeypatch):
    """coded_keys.CODING_THREADS: quantising (canonical turns, every attribute's grid, the
    rotations' edge fix), lifting and each column's form run by rows and columns on threads
    from PARALLEL_MIN_ROWS primitives; the payload, description and order are those of one
    thread (here from 64 rows, so that a small model takes the threaded path, with turns near
    the canonical edges and a value column that lifts)."""
    p = _structured(5000, 3)
    rng = np.random.default_rng(5)
    p[::7, 6:10] = rng.normal(size=(len(p[::7]), 4))  # any turn: many are turned to canonical
    monkeypatch.setattr(coded_keys, "PARALLEL_MIN_ROWS", 64)
    monkeypatch.setattr(coded_keys, "CODING_THREADS", 8)
    chunks = coded_keys.row_chunks(len(p))
    assert len(chunks) == coded_keys.CODING_THREADS and chunks[-1].stop == len(p)
    assert [c.start for c in chunks[1:]] == [c.stop for c in chunks[:-1]]
    for bits in (None, {"mu": 4, "log_s": 6, "q": 9, "a": 10, "w": 7}):
        monkeypatch.setattr(coded_keys, "CODING_THREADS", 1)
        one = coded.encode_coded(p, bits)
        np.testing.assert_array_equal(coded.canonical(p), coded._canonical(p))
        monkeypatch.setattr(coded_keys, "CODING_THREADS", 8)
        many = coded.encode_coded(p, bits)
        assert one[0] == many[0] and one[1] == many[1]
        np.testing.assert_array_equal(one[2], many[2])
        assert one[1]["columns"] and any(c[1] for c in one[1]["columns"][3:])
        np.testing.assert_array_equal(coded.canonical(p), coded._canonical(p))


def test_old_layout_files_still_read_and_new_files_are_version_3(tmp_path):
    p = _structured(2000, 4)
    old, new = tmp_path / "old.wgs", tmp_path / "new.wgs"
    write_wgs(old, p, make_header(), encoding="coded", layout=1)
    write_wgs(new, p, make_header(), encoding="coded")
    assert PREFIX.unpack(old.read_bytes()[:PREFIX_SIZE])[1] == FORMAT_VERSION
    assert PREFIX.unpack(new.read_bytes()[:PREFIX_SIZE])[1] == CODED_KEYS_VERSION
    a, ha = read_wgs(old)
    b, hb = read_wgs(new)
    np.testing.assert_array_equal(a, b)
    assert "layout" not in ha["payload"]["quant"] and hb["payload"]["quant"]["layout"] == 2
    assert new.stat().st_size < old.stat().st_size
    # a layout-2 payload under version 1, or a layout-1 payload under version 3: refused
    data = new.read_bytes()
    hlen = PREFIX.unpack(data[:PREFIX_SIZE])[2]
    header = json.loads(data[PREFIX_SIZE : PREFIX_SIZE + hlen])
    _craft(tmp_path / "v1.wgs", header, data[PREFIX_SIZE + hlen :], version=FORMAT_VERSION)
    with pytest.raises(WarpgaussError, match="version 1 file with a layout 2 coded payload"):
        read_wgs(tmp_path / "v1.wgs")


def test_the_reserved_header_holds_the_widest_layout_2_description():
    widest = {"bits": {k: 24 for k in coded.CODED_BITS}, "columns": [[-(1 << 52), 53]] * 12, "layout": 2}
    dump = lambda d: len(json.dumps(d, sort_keys=True, separators=(",", ":")))  # noqa: E731
    assert dump(widest) <= dump(_coded_placeholder())


def _file(tmp_path, p, payload, quant):
    header, _ = _valid_header(p, payload, encoding="coded", bytes_per_primitive=None, payload_bytes=len(payload), quant=quant)
    path = tmp_path / "bad.wgs"
    _craft(path, header, payload, version=CODED_KEYS_VERSION)
    return path


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda q: {**q, "layout": 7}, "version 3 file without a layout 2 coded payload"),
        (lambda q: {**q, "columns": q["columns"][:-1]}, "column list"),
        (lambda q: {**q, "columns": [*q["columns"][:3], [q["columns"][3][0], 54], *q["columns"][4:]]}, "width"),
        (lambda q: {**q, "columns": [[q["columns"][0][0], 22], *q["columns"][1:]]}, "width"),
        (lambda q: {**q, "columns": [[q["columns"][0][0], -1], *q["columns"][1:]]}, "width"),
        (lambda q: {**q, "columns": [[2**60, q["columns"][0][1]], *q["columns"][1:]]}, "2\\^52"),
        (lambda q: {**q, "columns": [*q["columns"][:3], [q["columns"][3][0], q["columns"][3][1] + 8], *q["columns"][4:]]}, "bytes of bits"),
        (lambda q: {**q, "columns": [[q["columns"][0][0], 1], *q["columns"][1:]]}, "beyond its declared"),
    ],
)
def test_crafted_descriptions_rejected(tmp_path, mutate, match):
    p = realistic_params(np.random.default_rng(5), 40)
    payload, quant, _ = coded.encode_coded(p)
    read_wgs(_file(tmp_path, p, payload, quant))  # the unmutated file reads
    with pytest.raises(WarpgaussError, match=match):
        read_wgs(_file(tmp_path, p, payload, mutate(quant)))


@pytest.mark.parametrize("layout", [7, True, "2", None])
def test_an_unknown_layout_is_refused(layout):
    p = realistic_params(np.random.default_rng(5), 40)
    payload, quant, _ = coded.encode_coded(p)
    with pytest.raises(WarpgaussError, match="unknown coded layout"):
        coded.decode_coded(payload, len(p), {**quant, "layout": layout})


def test_crafted_payloads_rejected(tmp_path):
    p = realistic_params(np.random.default_rng(6), 40)
    n = len(p)
    payload, quant, _ = coded.encode_coded(p)
    blob = zstandard.ZstdDecompressor().decompress(payload)  # mask (2), symbols (n), bits, planes
    z = zstandard.ZstdCompressor(level=3)
    widths = [w for _, w in quant["columns"]]
    packed = len(blob) - 2 - n - n * sum((w + 7) // 8 for w in widths[3:])
    planes = 2 + n + packed

    def edit(at: int, value: int) -> bytes:
        b = bytearray(blob)
        b[at] = value
        return z.compress(bytes(b))

    nbits = sum(max(s // 2 - 2, 0) for s in blob[2 : 2 + n])
    cases = [
        (z.compress(b"\0" * (len(blob) * 1000)), "claims 40 primitives"),
        (b"not a zstd frame at all but long enough to claim 40 primitives", "does not decompress"),
        (zstandard.ZstdCompressor(write_content_size=False).compress(blob), "frame holds"),
        (z.compress(blob[:-1]), "frame holds|bytes of bits"),
        (edit(1, blob[1] | 0x80), "marks columns"),  # column 15 predicted
        (edit(0, blob[0] | 0x01), "marks columns"),  # a centre column predicted
        (edit(2, 2 * 64), "symbols outside"),  # a gap of 64 bits
        (edit(2, 1), "symbols outside"),  # a second bit on a gap of 0 bits
        (edit(2, blob[2] + 16), "bytes of bits"),  # a byte more than the packed bits hold
        (edit(planes - 1, blob[planes - 1] | 1) if nbits % 8 else None, "gaps end in padding bits"),
        (edit(planes, 0xFF) if widths[3] % 8 else None, "padding bits that are not 0"),
    ]
    assert sum(bad is not None for bad, _ in cases) >= len(cases) - 1
    # a rotation index of 7 (the column is constant 3: width 0, so give it a width)
    q = {**quant, "columns": [*quant["columns"][:6], [0, 3], *quant["columns"][7:]]}
    at = planes + n * sum((w + 7) // 8 for w in widths[3:6])
    b = bytearray(blob)
    b[at:at] = bytes([3 << 5] * n)
    b[at] = 7 << 5
    cases.append((z.compress(bytes(b)), "rotations hold codes outside"))
    for bad, match in cases:
        if bad is None:
            continue
        with pytest.raises(WarpgaussError, match=match):
            read_wgs(_file(tmp_path, p, bad, q if "rotations" in match else quant))
    b = bytearray(blob)
    b[at:at] = bytes([3 << 5] * n)
    np.testing.assert_array_equal(read_wgs(_file(tmp_path, p, z.compress(bytes(b)), q))[0], read_wgs(_file(tmp_path, p, payload, quant))[0])


def test_keys_that_overflow_are_refused():
    """Gaps that add past 2^63 (each valid alone) are refused rather than wrapped."""
    sym = bytes([0, 0, 2 * 63, 2 * 63])  # no column predicted; two gaps of 63 bits: 2^62 + ... twice
    bits = np.packbits(np.ones(2 * 61, np.uint8)).tobytes()
    blob = sym + bits
    quant = {
        "bits": dict(coded.CODED_BITS),
        "columns": [[0, 21]] * 3 + [[0, 0]] * 3 + [[3, 0], [0, 0], [0, 0], [0, 0], [0, 0], [1, 0]],
        "layout": 2,
    }
    with pytest.raises(WarpgaussError, match="keys overflow"):
        coded.decode_coded(zstandard.ZstdCompressor().compress(blob), 2, quant)


def test_the_model_bytes_read_back_through_the_container():
    p = _structured(500, 9)
    data = wgs_bytes(p, make_header(), encoding="coded")
    got, header = read_wgs_bytes(data)
    np.testing.assert_array_equal(got, coded.as_stored(p))
    assert header["payload"]["quant"]["layout"] == coded_keys.LAYOUT


LAYOUT1_FILE = Path(__file__).parent / "golden" / "coded_layout1.wgs"
# written by warpgauss 5babf2b (before layout 2) from these parameters; the sha256 of the float32
# parameters that version read back from it
LAYOUT1_BITS = {"mu": 3, "log_s": 5, "q": 6, "a": 9, "w": 6}
LAYOUT1_PARAMS_SHA256 = "402a839f1449fa1ef807445342f3e276747def0cb9c5710b71138af9dd10ca89"


def _layout1_params() -> np.ndarray:
    from conftest import uniform_params

    return uniform_params(np.random.default_rng(53), 300, centre=(0.0, 64.0), log_scale=(-1.0, 2.5), weight=(0.01, 1.0))


def test_a_file_written_before_layout_2_reads_as_it_did():
    params, header = read_wgs(LAYOUT1_FILE)
    assert hashlib.sha256(params.tobytes()).hexdigest() == LAYOUT1_PARAMS_SHA256
    assert "layout" not in header["payload"]["quant"]
    p = _layout1_params()
    np.testing.assert_array_equal(params, coded.as_stored(p, LAYOUT1_BITS))
    # the layout-1 writer is the one that wrote it: the same bytes; layout 2 holds the same model
    hdr = {k: v for k, v in header.items() if k not in ("n", "payload")}
    assert wgs_bytes(p, hdr, encoding="coded", bits=LAYOUT1_BITS, layout=1) == LAYOUT1_FILE.read_bytes()
    new = wgs_bytes(p, hdr, encoding="coded", bits=LAYOUT1_BITS)
    np.testing.assert_array_equal(read_wgs_bytes(new)[0], params)
    assert len(new) < len(LAYOUT1_FILE.read_bytes())


def test_mutated_frames_decode_or_are_refused_in_one_line():
    """Bytes changed, dropped or added inside a valid frame (the file's SHA-256 set aside), and
    widths changed in the description: a model or a WarpgaussError, never another exception."""
    rng = np.random.default_rng(11)
    z = zstandard.ZstdCompressor(level=1)
    refused = 0
    for _ in range(150):
        n = int(rng.integers(1, 40))
        p = realistic_params(rng, n)
        payload, quant, _ = coded.encode_coded(p)
        blob = bytearray(zstandard.ZstdDecompressor().decompress(payload))
        for _ in range(int(rng.integers(1, 4))):
            blob[int(rng.integers(0, len(blob)))] = int(rng.integers(0, 256))
        if rng.random() < 0.2:
            blob = blob[:-1] if rng.random() < 0.5 else blob + bytes([int(rng.integers(0, 256))])
        q = {**quant, "columns": [list(c) for c in quant["columns"]]}
        if rng.random() < 0.3:
            q["columns"][int(rng.integers(0, 12))][1] = int(rng.integers(0, 60))
        try:
            out = coded.decode_coded(z.compress(bytes(blob)), n, q)
            assert out.shape == (n, 12) and np.isfinite(out).all()
        except WarpgaussError as e:
            assert "\n" not in str(e)
            refused += 1
    assert refused > 50


def test_bit_lengths_are_exact_across_float64s_precision():
    """coded_keys._bit_length takes float64 exponents below 2^53 and halving above: equal to
    Python's int.bit_length on every value, those at and around 2^53 and 2^64 - 1 included."""
    rng = np.random.default_rng(3)
    edges = [0, 1, 2, 3, 7, 8, (1 << 53) - 1, 1 << 53, (1 << 53) + 1, (1 << 63) - 1, 1 << 63, (1 << 64) - 1]
    v = np.concatenate(
        [np.array(edges, np.uint64), rng.integers(0, 1 << 63, 5000, dtype=np.uint64), rng.integers(0, 1 << 20, 5000).astype(np.uint64)]
    )
    np.testing.assert_array_equal(coded_keys._bit_length(v), [int(x).bit_length() for x in v.tolist()])


def test_the_storage_orders_keys_are_the_stored_centres_keys():
    """encode_coded reuses the Morton keys the storage order sorted by: in storage order they are
    centre_keys of the stored centre codes (the offsets of a permutation are the same)."""
    codes = coded.quantise(_structured(3000, seed=4))
    order, key = coded._order_and_keys(codes)
    np.testing.assert_array_equal(order, coded.coded_order(codes))
    np.testing.assert_array_equal(key[order], coded_keys.centre_keys(codes[order, 0:3]))


def test_a_fits_codings_keep_the_centres_order_and_write_the_same_bytes():
    """Inside a fit (coded._FitCodes) the centres' sort and gap streams are kept by rows and centre
    depth: codings that change other depths, rows (a pruned subset) or the centre depth give the
    bytes they give outside a fit, ties included (duplicated centres)."""
    p = _structured(2500, seed=6)
    p[100:160] = p[40:100]  # shared centres: rows whose keys tie
    p[100:160, 10] += 0.25  # resolved by their other codes
    b = dict(coded.CODED_BITS)
    trials = [b, {**b, "q": b["q"] + 1}, {**b, "a": b["a"] - 1}, {**b, "mu": b["mu"] + 1}, b]
    want = [coded.encode_coded(p, t)[0] for t in trials]
    with coded._FitCodes(coded.canonical(p).astype(np.float32)) as fit:
        got = [coded.encode_coded(fit.base, t)[0] for t in trials]
        assert len(fit.orders) == 2  # two centre depths, each sorted once
        sub = fit.subset(np.arange(0, 2500, 3))
        got_sub = [coded.encode_coded(sub, t)[0] for t in trials[:3]]
    assert got == [coded.encode_coded(coded.canonical(p).astype(np.float32), t)[0] for t in trials]
    assert [len(x) for x in got] == [len(x) for x in want]
    rows = coded.canonical(p).astype(np.float32)[np.arange(0, 2500, 3)]
    assert got_sub == [coded.encode_coded(rows, t)[0] for t in trials[:3]]


def test_a_fits_codings_work_out_only_the_columns_whose_depth_changed(monkeypatch):
    """Inside a fit each attribute column's stored form is kept while the storage order stays the
    same: a coding that changes one attribute's depth works out that attribute's columns alone,
    and writes the bytes it writes outside a fit; where a depth reorders rows whose centres tie
    (ordered by every code) the kept forms are dropped and every column worked out again."""
    p = _structured(3000, seed=8)
    p[200:260] = p[40:100]  # shared centres, resolved by their values
    p[200:260, 10] -= 0.003  # first by a fine value grid; a coarse one ties them: the original order
    base = coded.canonical(p).astype(np.float32)
    b = {"mu": 3, "log_s": 5, "q": 7, "a": 10, "w": 6}
    trials = [b, {**b, "w": 7}, {**b, "a": 11}, {**b, "q": 8, "a": 11}, b, {**b, "a": 3}]
    want = [coded.encode_coded(base, t)[0] for t in trials]
    calls = []
    real = coded_keys._column
    monkeypatch.setattr(coded_keys, "_column", lambda c: calls.append(1) or real(c))
    got, worked = [], []
    with coded._FitCodes(base) as fit:
        for t in trials:
            calls.clear()
            got.append(coded.encode_coded(fit.base, t)[0])
            worked.append(len(calls))
    assert got == want
    columns = {"log_s": 3, "q": 4, "a": 1, "w": 1}
    assert worked[0] >= 9  # every column (and the residuals of those stored)
    # the columns whose depth differs from the coding before (a form kept for the latest depth only)
    assert worked[1] <= 2 * columns["w"] and worked[2] <= 2 * (columns["a"] + columns["w"])
    assert worked[3] <= 2 * columns["q"] and worked[4] <= 2 * (columns["q"] + columns["a"])
    assert worked[5] >= 9  # a value grid too coarse to tell the tied rows apart: a new order, every column
