"""The bounded residual (encode --max-error): every valid voxel decodes within the bound, on any
reader whose float64 prediction differs by less than the margin; the float64
predictor against a numpy float64 reference; the file keeps it strict."""

from __future__ import annotations

import json
import math
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

import warpgauss
from warpgauss.cli.main import app
from warpgauss.errors import WarpgaussError
from warpgauss.format import interpolation as I
from warpgauss.format import planes as P
from warpgauss.format import residual as R
from warpgauss.format.wgs import PREFIX, PREFIX_SIZE, read_wgs


# -- the float64 predictor -------------------------------------------------------------------
def _reference_prediction(params: np.ndarray, shape_xyz) -> np.ndarray:
    """V~ in float64 by numpy, all pairs (the 5-sigma cut on m, the RHO0 floor, clamped to [0, 1])."""
    p = params.astype(np.float64)
    nx, ny, nz = shape_xyz
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), z.ravel()], 1).astype(np.float64)
    num = np.zeros(len(pts))
    den = np.zeros(len(pts))
    for r in p:
        qx, qy, qz, qw = r[6:10] / np.linalg.norm(r[6:10])
        rot = np.array(
            [
                [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
                [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
                [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
            ]
        )
        s = np.exp(np.clip(r[3:6], -9.0, 12.0))
        m = (((pts - r[:3]) @ rot) ** 2 / s**2).sum(1)
        g = np.where(m < 25.0, np.exp(-0.5 * np.minimum(m, 60.0)), 0.0)
        num += r[11] * r[10] * g
        den += r[11] * g
    return np.clip(num / np.maximum(den, 0.05), 0.0, 1.0).reshape(nz, ny, nx)


@pytest.fixture(scope="module")
def small_model():
    return warpgauss.encode(example="vortex", example_size=16, budget=120, iterations=30, device="cpu", evaluate=False)


def test_the_float64_predictor_matches_a_numpy_float64_reference(small_model):
    from warpgauss.field.gaussians import GaussianField

    m = small_model
    values, fragile = GaussianField(m.params, m.shape_xyz, device="cpu").predict(m.params)
    ref = _reference_prediction(m.params, m.shape_xyz)
    assert values.dtype == np.float64 and values.shape == ref.shape
    assert np.abs(values - ref).max() < 1e-12  # float64 rounding only (a float32 decode differs by ~1e-7)
    assert not fragile.any()  # no pair of this model sits within 1e-9 of the cut


def test_a_pair_on_the_cut_marks_its_voxel_fragile():
    from warpgauss.field.gaussians import GaussianField

    # one axis-aligned primitive of sigma 1 at the origin: voxel (5, 0, 0) lies at m = 25 exactly
    p = np.array([[0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 0.5, 1.0]], np.float32)
    values, fragile = GaussianField(p, (8, 8, 8), device="cpu").predict(p)
    assert fragile[0, 0, 5] and fragile.sum() == np.count_nonzero(np.isclose(_dist2((8, 8, 8)), 25.0, rtol=1e-9, atol=0))
    assert values[0, 0, 0] == 0.5


def _dist2(shape_xyz):
    nx, ny, nz = shape_xyz
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return (x * x + y * y + z * z).astype(np.float64)


# -- the bound, for any volume and bound ------------------------------------------------------
KINDS = ("float32", "float32-extremes", "constant", "noisy", "masked", "int16", "uint8", "float64")


@st.composite
def volumes(draw):
    kind = draw(st.sampled_from(KINDS))
    shape = tuple(draw(st.integers(2, 9)) for _ in range(3))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    smooth = np.cumsum(np.cumsum(rng.normal(size=shape), 0), 1)
    if kind == "float32":
        v = smooth.astype(np.float32)
    elif kind == "float32-extremes":
        v = (smooth / np.abs(smooth).max() * draw(st.sampled_from([3.0e38, 1.0e-30, 1.0e20]))).astype(np.float32)
    elif kind == "constant":
        v = np.full(shape, draw(st.sampled_from([0.0, 7.5, -1e6])), np.float32)
    elif kind == "noisy":
        v = rng.normal(size=shape).astype(np.float32)
    elif kind == "masked":
        v = smooth.astype(np.float32)
        v[rng.random(shape) < 0.3] = np.nan
    elif kind == "int16":
        v = np.clip(smooth * 300, -32768, 32767).astype(np.int16)
    elif kind == "uint8":
        v = rng.integers(0, 256, shape).astype(np.uint8)
    else:
        v = smooth * 1e3 + 1e9  # float64, a range small against its magnitude
    rel = 10.0 ** draw(st.floats(-6.0, -1.0))
    return v, rel, rng


def _predict_like_a_model(v: np.ndarray, valid: np.ndarray, rng) -> tuple[np.ndarray, tuple[float, float]]:
    """A smooth-ish prediction in the source's range (what a model gives), plus the range."""
    x = v.astype(np.float64)
    lo, hi = (float(x[valid].min()), float(x[valid].max())) if valid.any() else (0.0, 1.0)
    base = np.where(valid, x, lo)
    pred = np.clip(base + rng.normal(0.0, 0.05 * (hi - lo) + 1e-30, v.shape), lo, hi)
    return pred, (lo, hi)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(volumes())
def test_every_valid_voxel_decodes_within_the_bound_on_any_reader(case):
    v, rel, rng = case
    valid = np.isfinite(v) if v.dtype.kind == "f" else np.ones(v.shape, bool)
    pred, (lo, hi) = _predict_like_a_model(v, valid, rng)
    span = hi - lo if hi > lo else max(abs(lo), 1.0)
    bound = rel * span
    fragile = rng.random(v.shape) < 0.05
    res, facts = R.code_residual(v, None if valid.all() else valid, pred, fragile, bound, (lo, hi))
    out = R.apply_residual(res, pred)
    err = np.abs(out.astype(np.float64) - v.astype(np.float64))[valid]
    assert err.size == 0 or err.max() <= bound, (err.max(), bound, res.info)
    if not valid.all():
        assert np.isnan(out[~valid]).all()  # masked voxels carry nothing: NaN back (no fill value given)
    # another reader: its prediction differs by less than the margin everywhere (and arbitrarily at
    # the fragile voxels, where it may count a pair the encoder did not): still within the bound
    margin = res.info["margin"]
    other = pred + rng.uniform(-1.0, 1.0, v.shape) * margin
    other[fragile] += rng.normal(0.0, 0.01 * span, int(fragile.sum()))
    again = R.apply_residual(res, other)
    err = np.abs(again.astype(np.float64) - v.astype(np.float64))[valid]
    assert err.size == 0 or err.max() <= bound, (err.max(), bound, res.info)
    if res.info["predictor"] == "interp":  # the Gaussians unused: the same bits whatever the prediction
        assert np.array_equal(out, again, equal_nan=True)


def test_a_bound_below_the_dtype_resolution_decodes_the_source_exactly():
    v = np.linspace(1000.0, 1001.0, 8 * 8 * 8, dtype=np.float32).reshape(8, 8, 8)  # ulp 6e-5 at 1000
    pred = v.astype(np.float64) + 0.01
    res, facts = R.code_residual(v, None, pred, np.zeros(v.shape, bool), 1e-6, (1000.0, 1001.0))
    out = R.apply_residual(res, pred)
    assert np.array_equal(out, v)  # the float32 nearest to a value within 1e-6 of v is v


def test_an_integer_source_keeps_its_dtype_on_the_integer_lattice_and_goes_float_where_coarser():
    rng = np.random.default_rng(1)
    v = rng.integers(0, 646, (10, 11, 12)).astype(np.int16)
    pred = v + rng.normal(0, 3, v.shape)
    none = np.zeros(v.shape, bool)
    res, _ = R.code_residual(v, None, pred, none, 6.46, (0.0, 646.0))
    out = R.apply_residual(res, pred)
    assert out.dtype == np.int16 and res.info["step"] == 13 and np.abs(out.astype(int) - v).max() <= 6
    res, _ = R.code_residual(v, None, pred, none, 0.646, (0.0, 646.0))  # below 1: the float lattice is coarser than lossless
    out = R.apply_residual(res, pred)
    assert out.dtype == np.float32 and np.abs(out.astype(float) - v).max() <= 0.646


def test_the_smallest_predictor_is_chosen_and_a_good_prediction_pays():
    rng = np.random.default_rng(2)
    v = rng.normal(size=(16, 16, 16)).astype(np.float32)
    none = np.zeros(v.shape, bool)
    good = v.astype(np.float64) + rng.normal(0, 1e-3, v.shape)
    res, facts = R.code_residual(v, None, good, none, 1e-2, (float(v.min()), float(v.max())))
    assert res.info["predictor"] == min(facts["sizes"], key=facts["sizes"].get) != "interp"
    useless = np.zeros(v.shape)
    res2, facts2 = R.code_residual(v, None, useless, none, 1e-2, (float(v.min()), float(v.max())))
    assert res.nbytes < res2.nbytes


@pytest.mark.parametrize("axes", R.ORDERS)
@pytest.mark.parametrize("levels", [R.FLAT, (1.5, 4.0)])
def test_every_axis_order_decodes_what_the_encoder_decoded(axes, levels):
    """The interpolation passes in any axis order, with flat or level-wise bounds, visit every
    point once, from known neighbours only: a reader's decode of the q's equals the encoder's, bit
    for bit, and within the bound, on the float and on the integer lattice."""
    rng = np.random.default_rng(4)
    t = rng.normal(size=(9, 14, 11)).cumsum(axis=2)
    skip = np.zeros(t.shape, bool)
    q, dec = I.feedback(t, skip, 0.02, False, "cubic", axes, levels)
    assert np.array_equal(I.decoded(q, 0.02, False, "cubic", axes, levels), dec)
    assert np.abs(dec - t).max() <= 0.01 + 1e-12
    ti = np.rint(t * 100).astype(np.int64)
    q, dec = I.feedback(ti, skip, 7.0, True, "linear", axes, levels)  # the odd integer step: |error| <= 3
    assert np.array_equal(I.decoded(q, 7.0, True, "linear", axes, levels), dec) and np.abs(dec - ti).max() <= 3
    seen = np.zeros(t.shape, int)
    seen[(slice(0, 1),) * 3] += 1
    for _, _, sel in I.interp_passes(t.shape, axes):
        seen[sel] += 1
    assert (seen == 1).all()


def test_the_axis_order_and_layout_are_chosen_stored_and_a_file_without_them_reads_as_before(monkeypatch):
    """The coder picks the interpolation's axis order and level-wise bounds on a central block and
    the q's storage order by size; all go in the header (checked on reading). Files written before
    carry none and decode as z, y, x, flat bounds, in the raster order."""
    from warpgauss.readers.synthetic import generate

    v = generate("interface", 20, seed=1)
    v = np.ascontiguousarray(v[:, :, ::-1].transpose(2, 0, 1))  # anisotropic along another axis
    pred, none = np.zeros(v.shape), np.zeros(v.shape, bool)
    res, facts = R.code_residual(v, None, pred, none, 1e-3, (0.0, 1.0))
    assert res.info["axes"] in R.ORDERS and res.info["layout"] in R.ORDERS and facts["axes"] == res.info["axes"]
    assert tuple(res.info["levels"]) in I.LEVELWISE
    assert np.abs(R.apply_residual(res, pred) - v).max() <= 1e-3
    for key, value in (("axes", "011"), ("layout", "011"), ("levels", [0.5, 2.0]), ("levels", [1.5])):
        bad = dict(res.info, **{key: value})
        with pytest.raises(WarpgaussError, match=f"residual {key}"):
            R.apply_residual(R.Residual(bad, res.data), pred)
    from warpgauss.format import residual_coding

    monkeypatch.setattr(residual_coding, "ORDERS", (R.AXES,))  # what the coder wrote before it chose
    monkeypatch.setattr(residual_coding, "LEVELWISE", (R.FLAT,))
    old, _ = R.code_residual(v, None, pred, none, 1e-3, (0.0, 1.0))
    info = {k: val for k, val in old.info.items() if k not in ("axes", "layout", "levels")}
    monkeypatch.undo()
    assert np.array_equal(R.apply_residual(R.Residual(info, old.data), pred), R.apply_residual(old, pred))


# -- end to end: encode, file, decode, CLI ----------------------------------------------------
@pytest.fixture(scope="module")
def bounded(tmp_path_factory):
    d = tmp_path_factory.mktemp("bounded")
    rng = np.random.default_rng(3)
    z, y, x = np.meshgrid(*(np.linspace(-1, 1, 18),) * 3, indexing="ij")
    vol = (800 * np.exp(-4 * (x * x + y * y + z * z)) + rng.normal(0, 5, x.shape)).astype(np.int16)
    np.save(d / "vol.npy", vol)
    kw = dict(budget=150, iterations=30, device="cpu", max_error=2.0)
    m = warpgauss.encode(vol, output=d / "v.wgs", **kw)
    m2 = warpgauss.encode(vol, output=d / "v2.wgs", **kw)
    return d, vol, m, m2


def test_encode_with_max_error_writes_one_file_whose_decode_keeps_the_bound(bounded):
    d, vol, m, m2 = bounded
    rep = m.run_report["residual"]
    assert rep["max_abs_error"] <= 2.0 and rep["bound"] == 2.0
    assert (d / "v.wgs").stat().st_size == rep["file_bytes"]
    assert (d / "v.wgs").read_bytes() == (d / "v2.wgs").read_bytes()  # same seed, same device: same file
    loaded = warpgauss.Model.load(d / "v.wgs")
    out = loaded.decode(device="cpu")
    assert out.dtype == np.int16 and np.abs(out.astype(int) - vol).max() <= 2
    alone = loaded.decode(device="cpu", residual=False)
    assert alone.dtype == np.float32 and np.abs(alone - vol).max() > 2  # the Gaussians alone do not hold it
    with pytest.raises(WarpgaussError, match="encoded grid"):
        loaded.decode(shape_xyz=(9, 9, 9), device="cpu", residual=True)
    from warpgauss.field.evaluate import evaluate_against

    r = evaluate_against(loaded, d / "vol.npy", device="cpu")
    assert r["max_abs_error_source"] <= 2.0 and r["bound"] == 2.0


def test_cli_info_decode_and_eval_show_and_apply_the_residual(bounded):
    d, vol, m, _ = bounded
    run = CliRunner()
    res = run.invoke(app, ["info", str(d / "v.wgs"), "--verify"])
    assert res.exit_code == 0 and "bounded residual" in res.output and "within 2" in res.output, res.output
    res = run.invoke(app, ["decode", str(d / "v.wgs"), "-o", str(d / "out.npy"), "--device", "cpu"])
    assert res.exit_code == 0 and "within 2" in res.output, res.output
    assert np.abs(np.load(d / "out.npy").astype(int) - vol).max() <= 2
    res = run.invoke(app, ["decode", str(d / "v.wgs"), "-o", str(d / "alone.npy"), "--device", "cpu", "--no-residual"])
    assert res.exit_code == 0 and np.load(d / "alone.npy").dtype == np.float32, res.output
    res = run.invoke(app, ["eval", str(d / "v.wgs"), str(d / "vol.npy"), "--device", "cpu", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.output)["max_abs_error_source"] <= 2.0


@pytest.mark.parametrize(
    "args, says",
    [
        (["--max-error", "0"], "--max-error must be a positive finite number"),
        (["--max-error", "nan"], "--max-error must be a positive finite number"),
        (["--max-error-rel", "-1e-3"], "--max-error-rel must be a positive finite number"),
        (["--max-error", "1", "--max-error-rel", "1e-3"], "give one of"),
        (["--psnr", "40", "--max-error", "1"], "give one of"),
        (["--psnr", "inf"], "--psnr must be a positive finite number"),
        (["--max-error", "1", "--stride", "2"], "does not combine"),
        (["--max-error", "1", "--bricks", "2x2x2"], "does not combine"),
        (["--max-error", "1", "--ladder", "10,20"], "does not combine"),
    ],
)
def test_bound_requests_that_cannot_hold_are_refused_before_any_work(tmp_path, args, says):
    out = tmp_path / "x.wgs"
    res = CliRunner().invoke(app, ["encode", "--example", "vortex", "--size", "12", "--budget", "20", "-o", str(out), *args])
    assert res.exit_code == 2 and says in res.output and len(res.output.strip().splitlines()) == 1, res.output
    assert not out.exists()


def _rewrite_header(src, dst, change) -> None:
    data = src.read_bytes()
    magic, version, hlen, _ = PREFIX.unpack_from(data)
    header = json.loads(data[PREFIX_SIZE : PREFIX_SIZE + hlen])
    change(header)
    area = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    rest = data[PREFIX_SIZE + hlen :]
    dst.write_bytes(PREFIX.pack(magic, version, len(area), zlib.crc32(area)) + area + rest)


def test_a_crafted_residual_is_refused_in_one_line(bounded, tmp_path):
    d, vol, m, _ = bounded
    src = d / "v.wgs"

    def wider(h):  # symbols claimed wider than the frame holds
        h["residual"]["symbol_bytes"] = 8

    _rewrite_header(src, tmp_path / "bomb.wgs", wider)
    with pytest.raises(WarpgaussError, match="where the header says"):
        warpgauss.Model.load(tmp_path / "bomb.wgs").decode(device="cpu")

    def lie(h):
        h["residual"]["literals"] = 10**12

    _rewrite_header(src, tmp_path / "lie.wgs", lie)
    with pytest.raises(WarpgaussError, match="more literals"):
        warpgauss.Model.load(tmp_path / "lie.wgs")
    damaged = bytearray(src.read_bytes())
    damaged[-3] ^= 0xFF  # inside the residual: its checksum catches it when a decode reads it
    (tmp_path / "dmg.wgs").write_bytes(bytes(damaged))
    with pytest.raises(WarpgaussError, match="residual checksum"):
        warpgauss.Model.load(tmp_path / "dmg.wgs").decode(device="cpu")
    params, header = read_wgs(src)
    assert header["residual"]["bound"] == 2.0 and params.shape == (m.n, 12)


def test_the_claimed_symbols_are_bounded_by_what_zstandard_can_produce():
    frame = P.compress(bytes(1000))
    with pytest.raises(WarpgaussError, match="more than Zstandard can produce"):
        P.decompress(frame, len(frame) * P.ZSTD_MAX_RATIO * 2, "symbols")
    assert P.decompress(frame, 1000, "symbols") == bytes(1000)
    assert math.isfinite(R.MARGIN_REL)


def test_bzip2_codes_the_chosen_symbols_where_smaller_and_a_damaged_frame_is_refused():
    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 48, seed=0)
    zero = np.zeros(v.shape)
    res, facts = R.code_residual(v, None, zero, np.zeros(v.shape, bool), 1e-2, (0.0, 1.0))
    assert res.info["symbols_codec"] == "bzip2" and res.nbytes < min(facts["sizes"].values())
    assert np.abs(R.apply_residual(res, zero) - v).max() <= 1e-2
    bad = bytearray(res.data)
    bad[len(bad) // 4] ^= 0x55  # inside the bzip2 symbols
    with pytest.raises(WarpgaussError, match="do not decompress|hold"):
        R.apply_residual(R.Residual(res.info, bytes(bad)), zero)


def test_bzip2_in_parts_decodes_the_same_values_and_refuses_a_cut_or_swelled_frame(monkeypatch):
    """Symbols longer than planes.BZIP2_PART are coded in parts on threads (codec "bzip2-parts": a
    table of the parts' lengths, then their streams): a reader decodes the parts at once into the
    same q's; a frame cut inside a part, a part's bytes changed, a table that does not describe the
    frame, or parts that yield more or less than the header declares are refused."""
    import struct

    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 48, seed=0)
    zero = np.zeros(v.shape)
    whole, _ = R.code_residual(v, None, zero, np.zeros(v.shape, bool), 1e-2, (0.0, 1.0))
    monkeypatch.setattr(P, "BZIP2_PART", 50_000)
    res, _ = R.code_residual(v, None, zero, np.zeros(v.shape, bool), 1e-2, (0.0, 1.0))
    assert whole.info["symbols_codec"] == "bzip2" and res.info["symbols_codec"] == "bzip2-parts"
    assert np.array_equal(R.apply_residual(res, zero), R.apply_residual(whole, zero))
    n = res.info["streams"]["symbols"]
    frame = res.data[:n]
    size = 48**3 * res.info["symbol_bytes"]
    part, count = struct.unpack_from("<II", frame)
    assert (part, count) == (50_000, 3) and frame.count(b"BZh9") == 3  # one stream a part
    assert P.decompress(frame, size, "symbols", "bzip2-parts") == P.decompress(
        whole.data[: whole.info["streams"]["symbols"]], size, "symbols", "bzip2"
    )
    for bad_size in (size - 1, size + 1, size + 50_000):  # other shares than the parts hold
        with pytest.raises(WarpgaussError, match="do not decompress"):
            P.decompress(frame, bad_size, "symbols", "bzip2-parts")
    with pytest.raises(WarpgaussError, match="do not decompress"):  # read as one stream: the table is no bzip2 header
        P.decompress(frame, size, "symbols", "bzip2")
    with pytest.raises(WarpgaussError, match="do not decompress"):  # cut inside a part
        P.decompress(frame[: n // 2], size, "symbols", "bzip2-parts")
    lengths = bytearray(frame)
    struct.pack_into("<I", lengths, 8, struct.unpack_from("<I", frame, 8)[0] + 1)  # a length the frame does not hold
    with pytest.raises(WarpgaussError, match="do not decompress"):
        P.decompress(bytes(lengths), size, "symbols", "bzip2-parts")
    bad = bytearray(res.data)
    bad[n // 2] ^= 0x55
    with pytest.raises(WarpgaussError, match="do not decompress|hold"):
        R.apply_residual(R.Residual(res.info, bytes(bad)), zero)


def test_the_paraview_reader_shows_the_gaussians_unless_asked_for_the_residual(bounded, monkeypatch):
    pytest.importorskip("vtkmodules")
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from warpgauss.paraview import warpgauss_reader as pv

    monkeypatch.setattr(pv, "_use_cli", lambda: False)
    d, vol, m, _ = bounded
    shape = m.shape_xyz
    for residual, within in ((False, False), (True, True)):
        img, _, _ = pv.decode_image(str(d / "v.wgs"), shape, "cpu", residual)
        values = vtk_to_numpy(img.GetPointData().GetArray(0)).reshape(vol.shape)
        assert (np.abs(values.astype(float) - vol).max() <= 2.0) == within


def test_a_residual_this_machine_cannot_hold_is_refused_before_the_encode(monkeypatch, tmp_path):
    import warpgauss.core.limits as limits

    monkeypatch.setattr(limits, "available_memory", lambda: 1 << 20)  # 1 MiB free
    out = tmp_path / "x.wgs"
    res = CliRunner().invoke(
        app, ["encode", "--example", "vortex", "--size", "32", "--budget", "50", "--max-error", "0.01", "-o", str(out)]
    )
    assert res.exit_code == 2 and "coding a bounded residual of" in res.output, res.output
    assert not out.exists()


def test_the_bounded_benchmark_and_its_plot_run_on_the_cpu(tmp_path):
    import importlib.util

    root = Path(__file__).resolve().parent.parent / "benchmarks" / "bounded"

    def load(name):
        spec = importlib.util.spec_from_file_location(name, root / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    out = tmp_path / "b.json"
    load("bounded_rd").main(
        ["--size", "16", "--fields", "vortex", "--mris", "", "--gaussian-ratios", "", "--device", "cpu", "--out", str(out)]
    )
    result = json.loads(out.read_text())
    assert result["device"] == "cpu" and result["warp_version"] and result["date"]
    assert [r["bound_rel"] for r in result["rows"]] == [1e-2, 1e-3, 1e-4]
    assert all(r["max_abs_error"] <= r["bound"] for r in result["rows"])
    pytest.importorskip("matplotlib")  # the bench extra only
    load("plot_bounded").main([str(out), "-o", str(tmp_path / "b.png")])
    assert (tmp_path / "b.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_render_shows_the_gaussians_or_with_residual_the_bounded_decode(bounded, tmp_path):
    d, vol, m, _ = bounded
    run = CliRunner()
    for extra, method in (([], "cached"), (["--residual"], "bounded")):
        png = tmp_path / f"r{len(extra)}.png"
        res = run.invoke(app, ["render", str(d / "v.wgs"), "-o", str(png), "--size", "32", "--device", "cpu", "--json", *extra])
        assert res.exit_code == 0 and json.loads(res.output)["method"] == method, res.output
        assert png.read_bytes()[:4] == b"\x89PNG"
    plain = tmp_path / "plain.wgs"
    warpgauss.Model(m.params, m.header).save(plain)  # the same Gaussians, no residual
    res = run.invoke(app, ["render", str(plain), "-o", str(tmp_path / "x.png"), "--residual", "--device", "cpu"])
    assert res.exit_code == 2 and "has no residual" in res.output, res.output


def test_psnr_asks_for_the_largest_bound_whose_decode_reaches_it():
    from warpgauss.readers.synthetic import generate

    v = generate("interface", 32, seed=0)
    zero = np.zeros(v.shape)
    res, facts, check = R.code_for_psnr(v, None, zero, np.zeros(v.shape, bool), 60.0, (0.0, 1.0))
    assert check["psnr_db"] >= 60.0
    tried = check["psnr_search"]["bounds_tried"]
    assert tried[0] == pytest.approx(1e-3)  # the bound that guarantees 60 dB (MSE <= E^2) comes first
    assert res.info["bound"] in tried and res.info["bound"] > tried[0]  # a uniform error reaches 60 dB at a larger one
    out = R.apply_residual(res, zero)
    assert np.abs(out - v).max() <= res.info["bound"]


REAL = next((p for p in (Path(__file__).resolve().parents[2] / "shared" / "data", Path("/work/shared/data")) if p.is_dir()), None)


@pytest.mark.skipif(REAL is None or not (REAL / "inia19-t1-brain.nii.gz").exists(), reason="inia19-t1-brain.nii.gz not in shared/data")
def test_a_real_volume_decodes_within_the_bound_on_the_cpu(tmp_path):
    """A real brain (168x206x128 float32, analytic model only, to stay small): every voxel within
    1e-3 of the range after a CPU decode of the file."""
    from warpgauss.readers import ReadOptions

    assert REAL is not None
    src = REAL / "inia19-t1-brain.nii.gz"
    warpgauss.encode(src, iterations=0, device="cpu", max_error_rel=1e-3, output=tmp_path / "b.wgs", evaluate=False)
    m = warpgauss.Model.load(tmp_path / "b.wgs")
    vol = ReadOptions().read(src).data.astype(np.float64)
    out = m.decode(device="cpu").astype(np.float64)
    assert m.residual is not None and np.abs(out - vol).max() <= m.residual.info["bound"]


def test_view_and_the_page_draw_the_bounded_decode_of_a_model_with_a_residual(bounded, tmp_path):
    pytest.importorskip("pyvista")
    from warpgauss.render.renderers import RenderSettings, make_renderer
    from warpgauss.render.viewer import Viewer

    d, vol, m, _ = bounded
    loaded = warpgauss.Model.load(d / "v.wgs")
    settings = RenderSettings(width=32, height=24)
    bounded_frame = make_renderer(loaded, "bounded", "cpu").render(None, None, settings)
    gauss_frame = make_renderer(loaded, "march", "cpu").render(None, None, settings)
    assert bounded_frame.method == "bounded" and np.abs(bounded_frame.rgb - gauss_frame.rgb).max() > 0.0
    v = Viewer([loaded], [str(d / "v.wgs")], device="cpu", method="bounded")  # what serve --method bounded shows
    v.resize(32, 24)
    assert v.frame().shape[:2] == (24, 32) and v.state.method == "bounded"
    shot = tmp_path / "view.png"
    res = CliRunner().invoke(
        app, ["view", str(d / "v.wgs"), "--method", "bounded", "--screenshot", str(shot), "--size", "32x24", "--device", "cpu"]
    )
    assert res.exit_code == 0 and shot.is_file(), res.output
    plain = tmp_path / "plain.wgs"
    warpgauss.Model(m.params, m.header).save(plain)
    with pytest.raises(WarpgaussError, match="no residual"):
        make_renderer(warpgauss.Model.load(plain), "bounded", "cpu")


@pytest.mark.parametrize(
    "field,value,says",
    [
        ("step", 7, "does not hold its bound"),  # an integer step wider than 2 x bound + 1
        ("step", 4, "does not hold its bound"),  # even: no integer sits at its centre
        ("bound", 1.0, "does not hold its bound"),  # a tighter bound than the step gives
        ("bound_rel", 0, "relative bound"),
        ("dtype", "float32", "integer-lattice residual decodes to its source's integers"),
        ("source_dtype", "complex64", "source dtype"),
        ("lattice", "float", "float-lattice residual decodes to floats"),
    ],
)
def test_a_description_that_claims_a_bound_its_fields_do_not_hold_is_refused(bounded, tmp_path, field, value, says):
    """Every field of the residual's description is checked against the others before a decode
    (and ``info``) states its bound: a step that would let a voxel stray past the bound, a bound
    tighter than the step gives, a dtype its lattice cannot decode to."""
    d, vol, m, _ = bounded
    out = tmp_path / "crafted.wgs"

    def change(h):
        h["residual"][field] = value

    _rewrite_header(d / "v.wgs", out, change)
    for read in (warpgauss.Model.load, warpgauss.Model.load_header):
        with pytest.raises(WarpgaussError, match=says):
            read(out)
    res = CliRunner().invoke(app, ["info", str(out)])
    assert res.exit_code == 2 and says in res.output and len(res.output.strip().splitlines()) == 1, res.output


def test_float_lattice_claims_are_checked_against_step_and_margin():
    """A float-lattice description holds its bound where step <= 2 (bound - margin): what the
    encoder writes passes, a step one part in 10^6 wider or a margin past the bound is refused."""
    from warpgauss.readers.synthetic import generate

    v = generate("vortex", 16, seed=0)
    zero = np.zeros(v.shape)
    res, _ = R.code_residual(v, None, zero, np.zeros(v.shape, bool), 1e-2, (0.0, 1.0))
    info = dict(res.info)
    assert info["lattice"] == "float" and R.check_info(info, v.size) is None
    assert "do not hold its bound" in R.check_info({**info, "step": info["step"] * (1 + 1e-6) + 2 * info["margin"]}, v.size)
    assert "do not hold its bound" in R.check_info({**info, "margin": info["bound"]}, v.size)
    streams = dict(info["streams"], symbols=3)
    assert "cannot hold" in R.check_info({**info, "streams": streams, "payload_bytes": sum(streams.values())}, v.size)
