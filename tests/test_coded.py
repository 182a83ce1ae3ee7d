"""The coded payload: quantiser error bounds, Morton storage order, exact file round trips,
determinism, and strict refusal of damaged or crafted payloads."""

from __future__ import annotations

import numpy as np
import pytest
import zstandard
from reference.field_ref import covariances
from test_wgs import _craft, _valid_header, make_header, realistic_params

from warpgauss.errors import WarpgaussError
from warpgauss.format import coded, coded_keys, ratefit
from warpgauss.format.wgs import header_size, read_wgs, wgs_bytes, write_wgs


def _rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrices of (n, 4) quaternions (x, y, z, w), float64."""
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)


@pytest.mark.parametrize(
    "bits", [coded.CODED_BITS, {"mu": 0, "log_s": 2, "q": 3, "a": 4, "w": 2}, {"mu": 8, "log_s": 8, "q": 10, "a": 12, "w": 12}]
)
def test_quantiser_errors_stay_within_half_a_step(bits):
    rng = np.random.default_rng(1)
    p = realistic_params(rng, 3000)
    p[:5, 6:10] = [[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [0, 0, 0, 0]]  # axis-aligned, sign, zero
    q = coded.project_coded(p, bits).astype(np.float64)
    p64 = coded.canonical(p)  # the same Gaussians as stored: turned nearest the identity (tested below)
    tol = 1e-6
    assert np.abs(q[:, 0:3] - p64[:, 0:3]).max() <= 2.0 ** -(bits["mu"] + 1) * (1 + tol) + 1e-4
    assert np.abs(q[:, 3:6] - p64[:, 3:6]).max() <= 2.0 ** -(bits["log_s"] + 1) * (1 + tol) + 1e-6
    assert np.abs(q[:, 10] - p64[:, 10]).max() <= 2.0 ** -(bits["a"] + 1) * (1 + tol) + 1e-6
    w_err = np.abs(q[:, 11] - p64[:, 11])
    assert np.all((w_err <= 2.0 ** -(bits["w"] + 1) * (1 + tol) + 1e-6) | (q[:, 11] == 2.0 ** -bits["w"]))  # or lifted to the least code
    assert np.all(q[:, 11] > 0)
    assert np.allclose(np.linalg.norm(q[:, 6:10], axis=1), 1.0, atol=1e-6)
    # rotation error: each smaller component within half a level, so the matrices stay close
    levels = 2 ** bits["q"] - 2
    step = np.sqrt(2.0) / levels
    r = np.abs(_rot(q[5:, 6:10]) - _rot(p64[5:, 6:10])).max()
    assert r <= 6 * step + 1e-6
    np.testing.assert_allclose(_rot(q[:3, 6:10]), _rot(p64[:3, 6:10]), atol=1e-6)  # axis-aligned orientations survive exactly
    np.testing.assert_array_equal(q[[0, 1, 2, 4], 6:10], np.tile([0.0, 0.0, 0.0, 1.0], (4, 1)))  # a box's axes and zero: the identity


def test_each_gaussian_is_stored_as_its_turn_nearest_the_identity():
    """canonical(): the same covariance (float64 reference, to 1e-12), a quaternion in the truncated
    cube |x|, |y|, |z| <= tan(pi/8) w, |x| + |y| + |z| <= w, and the same result from any of a
    Gaussian's 24 equivalent forms (its axes turned onto themselves, scales moved along); on the
    coded grids that saves about log2(24) bits a Gaussian (a smaller coding of the same model)."""
    rng = np.random.default_rng(11)
    p = realistic_params(rng, 2000).astype(np.float64)
    c = coded.canonical(p)
    np.testing.assert_allclose(covariances(c), covariances(p), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(c[:, [0, 1, 2, 10, 11]], p[:, [0, 1, 2, 10, 11]])
    q = c[:, 6:10]
    v = np.abs(q[:, :3])
    assert np.all(q[:, 3] > 0) and np.all(v.max(1) <= (np.sqrt(2) - 1) * q[:, 3] + 1e-12) and np.all(v.sum(1) <= q[:, 3] + 1e-12)
    for k in range(24):  # every equivalent form of the same Gaussians
        g = np.tile(coded.OCTAHEDRAL_Q[k], (len(p), 1))
        other = p.copy()
        other[:, 6:10] = coded._hamilton(p[:, 6:10] / np.linalg.norm(p[:, 6:10], axis=1, keepdims=True), g)
        other[:, 3:6] = p[:, 3:6][:, coded.OCTAHEDRAL_AXES[k]]
        np.testing.assert_allclose(covariances(other), covariances(p), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(coded.canonical(other), c, atol=1e-12)
    flipped = p.copy()
    flipped[:, 6:10] *= -3.0  # sign and length of a quaternion: the same rotation
    np.testing.assert_allclose(coded.canonical(flipped), c, atol=1e-12)
    assert (coded.quantise(p)[:, 6] == 3).all()  # the index is always w's


def test_storing_the_turn_nearest_the_identity_codes_smaller(monkeypatch):
    """Against the same quantiser without the turn (random rotations, as a refined model's): at
    least 3.5 % fewer bytes (log2(24) = 4.6 bits of about 60)."""
    p = realistic_params(np.random.default_rng(12), 4000)
    turned = len(coded.encode_coded(p)[0])
    monkeypatch.setattr(coded, "canonical", lambda x: np.asarray(x, np.float64))
    monkeypatch.setattr(coded, "_outside_canonical", lambda q: np.zeros(len(q), bool))
    plain = len(coded.encode_coded(p)[0])
    assert turned < 0.965 * plain


def test_file_round_trip_is_the_projected_model_in_morton_order(tmp_path):
    rng = np.random.default_rng(2)
    p = realistic_params(rng, 2500)
    path = tmp_path / "m.wgs"
    size = write_wgs(path, p, make_header(), encoding="coded")
    got, hdr = read_wgs(path)
    _, _, order = coded.encode_coded(p)
    np.testing.assert_array_equal(got, coded.project_coded(p)[order])
    h = path.stat().st_size - hdr["payload"]["payload_bytes"]
    assert size == path.stat().st_size and h <= header_size(make_header(), len(p), encoding="coded") < h + 400
    assert hdr["payload"]["encoding"] == "coded" and hdr["payload"]["bytes_per_primitive"] is None
    assert size < 12 * len(p) + header_size(make_header(), len(p), compact=True)  # smaller than compact96
    # stored along a Morton curve: consecutive primitives are near each other
    step = np.linalg.norm(np.diff(got[:, 0:3], axis=0), axis=1)
    shuffled = np.linalg.norm(np.diff(p[:, 0:3], axis=0), axis=1)
    assert np.median(step) < 0.25 * np.median(shuffled)
    # the projection is idempotent: a decoded model saved again is the same file (nothing drifts,
    # and a model refined on the grid is stored exactly)
    again = tmp_path / "again.wgs"
    write_wgs(again, got, hdr, encoding="coded")
    assert again.read_bytes() == path.read_bytes()
    np.testing.assert_array_equal(coded.project_coded(got), got)


def test_coding_is_deterministic_and_independent_of_input_order():
    rng = np.random.default_rng(3)
    p = realistic_params(rng, 800)
    a = wgs_bytes(p, make_header(), encoding="coded")
    b = wgs_bytes(p[rng.permutation(len(p))], make_header(), encoding="coded")
    assert a == b


@pytest.mark.parametrize("spread", [1, 3, 50])
def test_storage_order_is_the_full_lexsort(spread):
    """The one-key sort with ties re-sorted equals a lexsort over the key and every code, for
    codes with many shared centres (spread 1: every row the same) and few."""
    rng = np.random.default_rng(spread)
    c = rng.integers(-spread, spread + 1, size=(2000, 12)).astype(np.int64)
    c[:, 6] = rng.integers(0, 4, len(c))
    mu = c[:, 0:3] - c[:, 0:3].min(0)
    key = (
        coded_keys._part1by2(mu[:, 0]) | (coded_keys._part1by2(mu[:, 1]) << np.uint64(1)) | (coded_keys._part1by2(mu[:, 2]) << np.uint64(2))
    )
    full = np.lexsort([*[c[:, k] for k in range(11, 2, -1)], mu[:, 0], mu[:, 1], mu[:, 2], key])
    np.testing.assert_array_equal(coded.coded_order(c), full)


def test_each_plane_is_a_block_and_the_smaller_level_is_kept(monkeypatch):
    """The payload is one frame whose planes end blocks of their own, at the smaller of ZSTD_LEVELS;
    it codes smaller than one compression of the planes' concatenation (one literal table for all
    columns) on a model of a few thousand primitives, and any level decodes to the same model."""
    zstd = coded.zstandard_module()
    p = realistic_params(np.random.default_rng(5), 3000)
    payload, quant, _ = coded.encode_coded(p)
    sizes = {}
    for level in (1, 9, 19):
        monkeypatch.setattr(coded, "ZSTD_LEVELS", (level,))
        one, quant_l, _ = coded.encode_coded(p)
        assert quant_l == quant
        np.testing.assert_array_equal(coded.decode_coded(one, len(p), quant_l), coded.decode_coded(payload, len(p), quant))
        sizes[level] = len(one)
    assert len(payload) == min(sizes[1], sizes[9])
    blob = zstd.ZstdDecompressor().decompress(payload)  # the frame declares its size
    joint = zstd.ZstdCompressor(level=19, write_checksum=True).compress(blob)  # the layout before blocks
    assert len(payload) < 0.97 * len(joint)
    np.testing.assert_array_equal(coded.decode_coded(joint, len(p), quant), coded.decode_coded(payload, len(p), quant))


def test_a_single_primitive_and_huge_values():
    p = realistic_params(np.random.default_rng(4), 1)
    payload, quant, order = coded.encode_coded(p)
    np.testing.assert_array_equal(coded.decode_coded(payload, 1, quant), coded.project_coded(p))
    p[0, 0] = 1e30
    with pytest.raises(WarpgaussError, match="too large for the coded format"):
        coded.encode_coded(p)


def _coded_file(tmp_path, name, p, payload, quant):
    header, _ = _valid_header(p, payload, encoding="coded", bytes_per_primitive=None, payload_bytes=len(payload), quant=quant)
    _craft(tmp_path / name, header, payload)
    return tmp_path / name


@pytest.mark.parametrize(
    "mutate, match",
    [
        (lambda q: {**q, "bits": {**q["bits"], "q": 1}}, "bit depth 'q'"),
        (lambda q: {k: v for k, v in q.items() if k != "bits"}, "bit depths"),
        (lambda q: {**q, "raw_bytes": q["raw_bytes"] + 1}, "raw bytes"),
        (lambda q: {**q, "columns": q["columns"][:-1]}, "column list"),
        (lambda q: {**q, "columns": [[q["columns"][0][0]], *q["columns"][1:]]}, "column list"),
        (lambda q: {**q, "columns": [[q["columns"][0][0], 9], *q["columns"][1:]]}, "width"),
        (lambda q: {**q, "columns": [[q["columns"][0][0], True], *q["columns"][1:]]}, "width"),
        (lambda q: {**q, "columns": [[2**60, q["columns"][0][1]], *q["columns"][1:]]}, "2\\^52"),
        (lambda q: {**q, "columns": [["0", q["columns"][0][1]], *q["columns"][1:]]}, "offset"),
    ],
)
def test_crafted_coded_description_rejected(tmp_path, mutate, match):
    p = realistic_params(np.random.default_rng(5), 40)
    payload, quant, _ = coded.encode_coded(p, layout=1)  # layout 2's: tests/test_coded_keys.py
    with pytest.raises(WarpgaussError, match=match):
        read_wgs(_coded_file(tmp_path, "bad.wgs", p, payload, mutate(quant)))
    read_wgs(_coded_file(tmp_path, "ok.wgs", p, payload, quant))  # the unmutated file reads


def test_crafted_coded_payloads_rejected(tmp_path):
    p = realistic_params(np.random.default_rng(6), 40)
    payload, quant, _ = coded.encode_coded(p, layout=1)  # layout 2's: tests/test_coded_keys.py
    raw = quant["raw_bytes"]
    z = zstandard.ZstdCompressor(level=3)
    noise = np.random.default_rng(1).integers(0, 256, raw, dtype=np.uint8).tobytes()  # incompressible
    cases = [
        # a bomb (far more than the columns, in 38 bytes): refused before it is decompressed, since
        # 40 primitives cannot fit in fewer than 40 bytes (coded.MIN_PAYLOAD_PER_PRIMITIVE)
        (z.compress(b"\0" * (raw * 1000)), "claims 40 primitives"),
        (z.compress(noise + bytes(raw * 1000)), "frame holds"),  # declares far more than the columns
        (z.compress(noise[: raw - 1]), "frame holds"),
        (b"not a zstd frame at all but long enough to claim 40 primitives", "does not decompress"),
        (zstandard.ZstdCompressor(write_content_size=False).compress(noise), "frame holds"),
    ]
    # codes outside their ranges: a rotation index of 7 in an otherwise valid payload
    blob = bytearray(zstandard.ZstdDecompressor().decompress(payload))
    at = sum(w for _, w in quant["columns"][:6]) * len(p)
    blob[at] = 7 - quant["columns"][6][0]
    cases.append((z.compress(bytes(blob)), "rotations hold codes outside"))
    for bad, match in cases:
        with pytest.raises(WarpgaussError, match=match):
            read_wgs(_coded_file(tmp_path, "bad.wgs", p, bad, quant))


def test_flipped_payload_byte_is_caught(tmp_path):
    p = realistic_params(np.random.default_rng(7), 200)
    path = tmp_path / "m.wgs"
    write_wgs(path, p, make_header(), encoding="coded")
    data = bytearray(path.read_bytes())
    data[-10] ^= 0x40
    path.write_bytes(bytes(data))
    with pytest.raises(WarpgaussError, match="payload checksum mismatch"):
        read_wgs(path)


def test_device_projection_lands_on_the_coded_grids(device):
    """The refiner's projection kernel moves training parameters onto the grids the encoder
    quantises to: the numpy quantiser then finds them on a level (nothing moves by more than
    float32 rounding), and their codes are the numpy projection's except where a value sat on a
    rounding boundary."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import field as kf
    from warpgauss.kernels import optim as ko

    wp = warp()
    p = realistic_params(np.random.default_rng(8), 4000)
    p[:3, 6:10] = [[0, 0, 0, 1], [0.70710677, 0.70710677, 0, 0], [0.5, 0.5, 0.5, 0.5]]  # ties
    p[3, 11] = 1.0  # a weight of exactly 1 stays finite as a logit
    b = coded.CODED_BITS
    model = wp.array(p, dtype=kf.vec12, device=device)
    raw = wp.empty_like(model)
    wp.launch(ko.to_raw, dim=len(p), inputs=[model], outputs=[raw], device=device)
    g = ko.QuantGrid()
    g.on, g.mu, g.s, g.q, g.a, g.w = 1, b["mu"], b["log_s"], b["q"], b["a"], b["w"]
    wp.launch(ko.project_coded, dim=len(p), inputs=[raw, g], device=device)
    out = wp.empty_like(model)
    wp.launch(ko.to_model, dim=len(p), inputs=[raw], outputs=[out], device=device)
    got = out.numpy()
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(coded.project_coded(got), got, atol=1e-6)
    same = np.all(coded.quantise(got) == coded.quantise(p), axis=1)
    assert same.mean() > 0.97
    # while quantisation-aware, evaluation reads the stored Gaussian in the training parameters' own
    # axes and quaternion sign (straight-through gradients step them): the covariance of the
    # stored one, each log-scale within half a step of its own, the quaternion on its side
    wp.launch(ko.to_raw, dim=len(p), inputs=[model], outputs=[raw], device=device)
    seen = wp.empty_like(model)
    wp.launch(ko.project_copy, dim=len(p), inputs=[raw, g], outputs=[seen], device=device)
    wp.launch(ko.to_model, dim=len(p), inputs=[seen], outputs=[out], device=device)
    ev = out.numpy().astype(np.float64)
    np.testing.assert_allclose(covariances(ev[same]), covariances(coded.project_coded(p)[same].astype(np.float64)), rtol=1e-4, atol=1e-4)
    assert np.abs(ev[:, 3:6] - p[:, 3:6]).max() <= 2.0 ** -(b["log_s"] + 1) + 1e-5
    assert np.all(np.sum(ev[:, 6:10] * p[:, 6:10], axis=1) >= 0)


def test_device_turns_are_the_coders():
    """The kernels' table of the 24 turns of a box is warpgauss.format.coded's (quaternions, axes, margin)."""
    from warpgauss.kernels import optim as ko

    np.testing.assert_allclose(np.array(ko.OCTAHEDRAL_Q, np.float64).reshape(24, 4), coded.OCTAHEDRAL_Q, atol=1e-7)
    np.testing.assert_array_equal(np.array(ko.OCTAHEDRAL_AXES).reshape(24, 3), coded.OCTAHEDRAL_AXES)
    assert float(ko.CANONICAL_MARGIN) == coded.CANONICAL_MARGIN
    assert abs(float(ko.TAN_EIGHTH) - coded._TAN_EIGHTH) < 1e-12


def test_coded_encode_returns_the_stored_model(tmp_path, cpu):
    """format="coded" with an explicit N: the model ends on the coded grids, the returned model is
    the file's (same order, same values), same seed gives the same bytes, and the file is smaller
    than compact96 at the same N."""
    import warpgauss
    from warpgauss.format.model import Model
    from warpgauss.readers.synthetic import generate

    vol = generate("bubbles", 24, seed=1)
    kw = dict(budget=400, iterations=30, samples=512, device=cpu, self_test=False)
    a = warpgauss.encode(vol, **kw, format="coded", output=tmp_path / "a.wgs")
    warpgauss.encode(vol, **kw, format="coded", output=tmp_path / "b.wgs")
    assert (tmp_path / "a.wgs").read_bytes() == (tmp_path / "b.wgs").read_bytes()
    back = Model.load(tmp_path / "a.wgs")
    np.testing.assert_array_equal(back.params, a.params)
    np.testing.assert_array_equal(coded.project_coded(a.params, a.coded_bits), a.params)  # the grids its accuracy needs
    bud = a.report["budget"]
    assert bud["format"] == "coded" and bud["bytes"] == (tmp_path / "a.wgs").stat().st_size
    assert bud["bytes"] < bud["compact_bytes"] and bud["bytes_per_primitive"] < 12
    assert read_wgs(tmp_path / "a.wgs")[1]["payload"]["quant"]["bits"] == a.coded_bits
    assert a.coded_bits == ratefit.bits_for_psnr(a.report["refinement"]["loss_history"][-1]["sample_psnr_db"])[0]
    assert "lut_rgba8" not in a.header["transfer_function"]  # regenerated from the colormap: bytes saved
    with pytest.raises(WarpgaussError, match="unknown model format"):
        warpgauss.encode(vol, **kw, format="jpeg")


def test_more_accurate_models_get_finer_grids(tmp_path, cpu):
    """One bit on every attribute per 6 dB above 40 dB (at most 4): the coded noise stays below a
    model's own error (a 51 dB model lost 2.07 dB at the default depths, 0.14 dB at +2)."""
    import warpgauss
    from warpgauss.readers.synthetic import generate

    assert ratefit.bits_for_psnr(None) == (coded.CODED_BITS, 0)
    assert ratefit.bits_for_psnr(30.0) == (coded.CODED_BITS, 0)
    bits, extra = ratefit.bits_for_psnr(52.5)
    assert extra == 2 and all(bits[k] == coded.CODED_BITS[k] + 2 for k in bits)
    assert ratefit.bits_for_psnr(200.0)[1] == 4
    vol = generate("vortex", 24, seed=0)
    m = warpgauss.encode(
        vol, budget=300, iterations=60, samples=1024, device=cpu, self_test=False, evaluate=False, output=tmp_path / "v.wgs"
    )
    note = m.report["budget"]["coded_bits_from_accuracy"]
    assert note["bits"] == ratefit.bits_for_psnr(note["sample_psnr_db"])[0]
    assert read_wgs(tmp_path / "v.wgs")[1]["payload"]["quant"]["bits"] == note["bits"]


def test_refit_fixes_the_geometry_on_its_grids_and_refits_values(cpu):
    """quantise_mode="refit": from quantise_from on, centres, scales and rotations sit on the coded
    grids and no longer move, while a and w keep training; the run ends with everything on the
    grids, the same on a rerun."""
    from warpgauss.encoding.refine import RefineConfig, Refiner
    from warpgauss.field.analysis import DeviceVolume, normalise
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 20, seed=0))
    dv = DeviceVolume(f, cpu)
    p = realistic_params(np.random.default_rng(10), 150, box=20.0)
    cfg = RefineConfig(iterations=40, samples=512, quantise=dict(coded.CODED_BITS), quantise_from=0.5, quantise_mode="refit")
    r = Refiner(dv, p, cfg, 0, 0.3, 4.0)
    for _ in range(21):
        r.step()
    mid = r.model_params()
    np.testing.assert_allclose(coded.project_coded(mid)[:, :10], mid[:, :10], atol=2e-6)  # geometry on the grids
    for _ in range(19):
        r.step()
    late = r.model_params()
    np.testing.assert_allclose(late[:, :10], mid[:, :10], atol=1e-6)  # and fixed there (to rounding)
    assert np.abs(late[:, 10:] - mid[:, 10:]).max() > 0  # while a and w train
    r.run()  # nothing left to run: ends with the projection
    end = r.model_params()
    np.testing.assert_allclose(coded.project_coded(end), end, atol=2e-6)
    r2 = Refiner(dv, p, cfg, 0, 0.3, 4.0)
    r2.run()
    assert r2.model_params().tobytes() == end.tobytes()


class _Serial:
    """A stand-in for ThreadPoolExecutor that runs every task at once, in order (the serial search)."""

    def __init__(self, max_workers=None):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def submit(self, fn, *args, **kwargs):
        from concurrent.futures import Future

        f: Future = Future()
        f.set_result(fn(*args, **kwargs))
        return f

    def map(self, fn, items):
        return [fn(x) for x in items]


def test_the_rate_control_on_threads_and_with_kept_columns_fits_as_the_serial_search(monkeypatch):
    """A fit's codings share their code columns (a subset's codes are the rows of the whole set's)
    and the export choice's alternatives and the Zstandard levels run on threads: the same codes,
    the same choice, the same bytes as a serial search that quantises every coding afresh, at a
    budget that prunes and one that drops bits."""
    p = realistic_params(np.random.default_rng(11), 4000)
    fit = coded._FitCodes(coded.canonical(p).astype(np.float32))
    rows = np.sort(np.random.default_rng(1).choice(len(p), 1500, replace=False))
    sub = fit.subset(rows)
    with fit:
        for bits in (coded.CODED_BITS, {"mu": 2, "log_s": 3, "q": 4, "a": 5, "w": 3}):
            np.testing.assert_array_equal(coded.quantise(fit.base, bits), _plain(fit.base, bits))
            np.testing.assert_array_equal(coded.quantise(sub, bits), _plain(sub, bits))
    full = len(coded.encode_coded(p)[0])
    score = lambda stored, bits: float(np.abs(stored[:, 10]).sum() % 7.0)  # noqa: E731 - any deterministic rating
    results = {}
    for mode in ("threads", "serial"):
        if mode == "serial":
            monkeypatch.setattr(coded, "ThreadPoolExecutor", _Serial)  # the Zstandard levels
            monkeypatch.setattr(ratefit, "ThreadPoolExecutor", _Serial)  # the export choice's alternatives
            monkeypatch.setattr(coded._FitCodes, "codes", lambda self, params, b: None)
        for budget in (int(0.8 * full), int(0.45 * full)):
            stored, bits, info = ratefit.fit_bytes(p, budget, score=score)
            results[(mode, budget)] = (stored.tobytes(), bits, info["steps"], info["pruned"], info.get("chosen"), info["codings"])
    for budget in (int(0.8 * full), int(0.45 * full)):
        assert results[("threads", budget)] == results[("serial", budget)]
    assert any(r[3] > 0 for r in results.values())  # a budget that prunes


def _plain(params, bits):
    """quantise with no fit active (every column computed afresh)."""
    return coded.quantise(np.array(params), bits)
