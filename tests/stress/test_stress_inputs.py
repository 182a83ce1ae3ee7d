"""Stress: pathological volumes end in a finite model or a clear refusal (issue #7, part 1).

Each case states its outcome: either ``warpgauss.encode`` refuses with a WarpgaussError whose
message says what is wrong, or it returns exactly N primitives whose parameters are finite and
valid (unit quaternions, weights in (0, 1], log-scales in range), whose decode is finite in both
normalised and source units, and whose report is sane. Stage P runs with every numpy warning
turned into an error, so an overflow or a 0 * inf on the way is a failure, not a NaN later.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import normalise
from warpgauss.readers import ReadOptions

ITER, SAMPLES = 20, 128  # a short refinement: every stage runs, CPU time stays small


def smooth(shape_zyx=(8, 8, 8), seed=0) -> np.ndarray:
    """A smooth positive field in [0, 1] with structure along every axis of length > 1."""
    nz, ny, nx = shape_zyx
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    ph = np.random.default_rng(seed).uniform(0, 2 * np.pi, 3)
    v = 0.5 + 0.45 * np.sin(0.9 * x + ph[0]) * np.cos(0.7 * y + ph[1]) * np.cos(0.5 * z + ph[2])
    return v.astype(np.float64)


def strict(fn, *args, **kw):
    """Run fn with numpy floating-point warnings raised as errors."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with np.errstate(over="raise", invalid="raise", divide="raise", under="ignore"):  # underflow to 0 is fine
            return fn(*args, **kw)


def encode(volume, budget, *, iterations=ITER, **kw):
    return strict(
        warpgauss.encode,
        volume,
        budget=budget,
        iterations=iterations,
        samples=SAMPLES,
        device=kw.pop("device", "cpu"),
        seed=0,
        full_eval=True,
        **kw,
    )


def assert_valid_model(m, budget, shape_zyx, *, min_psnr=None):
    """The outcome every accepted case must have."""
    p = m.params
    assert m.n == budget and p.shape == (budget, 12)
    assert np.isfinite(p).all(), p
    np.testing.assert_allclose(np.linalg.norm(p[:, 6:10], axis=1), 1.0, atol=1e-5)
    assert (p[:, 11] > 0).all() and (p[:, 11] <= 1).all()
    assert (p[:, 3:6] > -9.5).all() and (p[:, 3:6] < 12).all()  # within the kernels' scale clamp
    assert tuple(m.header["grid"]["shape_xyz"]) == tuple(shape_zyx[::-1])
    v = m.decode(device="cpu", normalised=True)
    assert v.shape == tuple(shape_zyx) and np.isfinite(v).all()
    u = m.decode(device="cpu")
    assert u.shape == tuple(shape_zyx) and np.isfinite(u).all()
    rep = m.report
    ev = rep["evaluation"]["final"]
    assert math.isfinite(ev["psnr_db"]) and math.isfinite(ev["max_abs_error"])
    if rep["refinement"]["iterations"]:
        assert rep["refinement"]["skipped_nonfinite_updates"] == 0
        assert all(math.isfinite(r["total"]) for r in rep["refinement"]["loss_history"])
    if min_psnr is not None:
        assert ev["psnr_db"] >= min_psnr, ev
    return v, u


# -- refusals ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "volume, budget, match",
    [
        (np.full((8, 8, 8), 3.0, np.float32), 1, "constant"),
        (np.full((8, 8, 8), np.nan, np.float32), 1, "no finite value"),
        (np.where(np.arange(512).reshape(8, 8, 8) % 2, np.inf, -np.inf).astype(np.float32), 1, "no finite value"),
        (np.ones((1, 1, 1), np.float32), 1, "constant"),
        # an interior spike: central differences are 0 at an isolated maximum, so no detail candidate
        # (N_max = floor(min(0 / 0.55, 1 / 0.45)) = 0, SPEC section 4)
        (np.pad(np.ones((1, 1, 1), np.float32), 4), 1, "too few to place any primitive"),
        (smooth().astype(np.float32), 0, "--budget must be a positive whole number"),
        (smooth().astype(np.float32), -3, "--budget must be a positive whole number"),
        (np.zeros((8, 8, 8), np.bool_), 1, "not a real number type"),
        (np.zeros((8, 8, 8), np.complex64), 1, "not a real number type"),
        (np.zeros((8, 8), np.float32), 1, "3D"),
        (np.zeros((2, 2, 2, 2), np.float32), 1, "3D"),
    ],
    ids=["constant", "all-nan", "all-inf", "one-voxel", "interior-spike", "budget-0", "budget-negative", "bool", "complex", "2d", "4d"],
)
def test_refused_with_a_clear_message(volume, budget, match):
    with pytest.raises(WarpgaussError, match=match) as e:
        encode(volume, budget)
    assert "\n" not in str(e.value)


def test_isolated_valid_voxels_have_no_gradient_and_are_refused():
    """A checkerboard NaN mask leaves no valid neighbour on any axis: no detail seed anywhere."""
    v = smooth().astype(np.float32)
    v[np.indices(v.shape).sum(0) % 2 == 1] = np.nan
    with pytest.raises(WarpgaussError, match="0 with a non-zero gradient"):
        encode(v, 1)


# -- spikes and budgets --------------------------------------------------------------------------


def test_corner_spike_budget_one():
    """A spike at the corner has a one-sided gradient: N_max = 1, one primitive is placed on it."""
    v = np.zeros((8, 8, 8), np.float32)
    v[0, 0, 0] = 5.0
    # 100 iterations: after its first re-bin the lone primitive moves and grows, and the fit dips
    # below the all-zero model for a few dozen steps before it climbs well past it (39 dB)
    m = encode(v, 1, iterations=100)
    dec, _ = assert_valid_model(m, 1, v.shape, min_psnr=10 * math.log10(512))  # beats the all-zero model
    assert m.report["budget"]["n_max"] == 1
    assert dec[0, 0, 0] > 0.3 and dec[0, 0, 0] >= dec.max() - 1e-6 and np.abs(m.params[0, :3]).max() < 1.0
    with pytest.raises(WarpgaussError, match=r"N_max = 1\b.*--budget 1"):
        encode(v, 2)


def test_budget_equal_to_the_seed_limit_and_one_past_it():
    v = np.zeros((10, 10, 10), np.float32)
    v[3:5, 4:6, 2:6] = smooth((2, 2, 4))  # a small occupied block: N_max is small
    f = normalise(v)
    n_max = min(100 * f.eligible // 55, 100 * f.occupied // 45)
    assert 5 < n_max < 40
    m = encode(v, n_max)
    assert_valid_model(m, n_max, v.shape)
    assert m.report["budget"]["n_max"] == n_max
    with pytest.raises(WarpgaussError, match=rf"N_max = {n_max}\b.*--ratio"):
        encode(v, n_max + 1)


def test_budget_one_on_a_smooth_field():
    v = smooth((8, 8, 8))
    m = encode(v, 1)
    assert_valid_model(m, 1, v.shape)


# -- textures ------------------------------------------------------------------------------------


def test_white_noise():
    v = np.random.default_rng(1).random((12, 12, 12)).astype(np.float32)
    m = encode(v, 40)
    # predicting the mean of U(0, 1) gives 10 log10(12) = 10.8 dB; the model must not be worse
    assert_valid_model(m, 40, v.shape, min_psnr=10.0)


def test_checkerboard():
    v = (np.indices((12, 12, 12)).sum(0) % 2).astype(np.float32)
    m = encode(v, 40)
    assert m.report["input"]["masked_voxels"] == 0
    assert_valid_model(m, 40, v.shape, min_psnr=5.5)  # 0.5 everywhere gives 6.0 dB


# -- value ranges, denormals, dtypes at their extremes --------------------------------------------


def _normalised_reference(v: np.ndarray) -> np.ndarray:
    """(v - lo) / (hi - lo) in exact rational arithmetic, rounded once to float64."""
    from fractions import Fraction

    lo, hi = Fraction(float(v.min())), Fraction(float(v.max()))
    flat = [float((Fraction(float(x)) - lo) / (hi - lo)) for x in v.ravel()]
    return np.array(flat, np.float64).reshape(v.shape)


CASES = {
    "log-range 1e-30..1e30 f64": (np.logspace(-30, 30, 512).reshape(8, 8, 8), 2e-7),
    "log-range 1e-30..1e30 f32": (np.logspace(-30, 30, 512).reshape(8, 8, 8).astype(np.float32), 2e-7),
    "signed log-range f64": (np.sign(smooth() - 0.5) * 10.0 ** (60 * smooth() - 30), 2e-7),
    "f32 extremes": ((2 * smooth() - 1) * np.finfo(np.float32).max, 2e-7),
    "f64 extremes": ((2 * smooth() - 1) * np.finfo(np.float64).max, 6e-8),
    "f32 denormals": ((smooth() * 1e-40).astype(np.float32), 1e-4),
    "f32 smallest denormals": ((np.round(smooth() * 7) * 1.4e-45).astype(np.float32), 1e-7),
    "f64 denormals": (smooth() * 1e-320, 6e-8),
    "f16 extremes": ((2 * smooth() - 1) * 65504.0, 1e-3),
}


@pytest.mark.parametrize("name", sorted(CASES))
def test_normalisation_is_exact_without_overflow(name):
    """Stage P maps any finite range onto [0, 1] without overflow, NaN or lost scale."""
    v, tol = CASES[name]
    if name.startswith("f16"):
        v = v.astype(np.float16)
    f = strict(normalise, v)
    assert np.isfinite(f.values).all() and f.values.min() == 0.0 and f.values.max() == 1.0
    np.testing.assert_allclose(f.values, _normalised_reference(v), rtol=0, atol=tol)
    assert f.vmin == float(v.min()) and f.vmax == float(v.max())
    # and back: denormalising the exact normalised field returns the source values
    back = f.to_original(_normalised_reference(v))
    assert np.isfinite(back).all()
    big = max(abs(float(v.min())), abs(float(v.max())))
    np.testing.assert_allclose(back.astype(np.float64), v.astype(np.float64), rtol=1e-6, atol=1e-6 * big)


@pytest.mark.parametrize("name", ["log-range 1e-30..1e30 f64", "f32 extremes", "f64 extremes", "f32 denormals", "f64 denormals"])
def test_extreme_ranges_encode_and_decode_in_source_units(name):
    v, _ = CASES[name]
    budget = 2 if name.startswith("log") else 12  # the log range leaves 2 voxels above 0.02
    m = encode(v, budget)
    dec, src = assert_valid_model(m, budget, v.shape)
    assert m.header["values"] == {"min": float(v.min()), "max": float(v.max())}
    big = max(abs(float(v.min())), abs(float(v.max())))
    if big > float(np.finfo(np.float32).max):
        assert src.dtype == np.float64  # float32 cannot hold these values
    # source units are the normalised decode mapped through the header's range
    lo, hi = float(v.min()), float(v.max())
    expect = lo / 2 * (1 - dec.astype(np.float64)) * 2 + hi / 2 * dec.astype(np.float64) * 2
    if hi - lo < float(np.finfo(np.float32).tiny):
        assert src.dtype == np.float64  # float32 would hold these values in a few subnormal steps
    ulp = 2 * float(np.finfo(src.dtype).smallest_subnormal)  # subnormal outputs are quantised
    np.testing.assert_allclose(src.astype(np.float64), expect, rtol=1e-5, atol=1e-6 * big + ulp)


INTS = [np.int8, np.uint8, np.int16, np.uint16, np.int32, np.uint32, np.int64, np.uint64]


@pytest.mark.parametrize("dtype", INTS, ids=lambda d: np.dtype(d).name)
def test_integer_sources_at_their_extremes(dtype):
    info = np.iinfo(dtype)
    t = smooth()
    v = np.where(t > 0.5, info.max, info.min).astype(dtype)
    v[t > 0.8] = info.max // 2 + (info.min // 2 if info.min < 0 else 0)
    f = strict(normalise, v)
    np.testing.assert_allclose(f.values, _normalised_reference(v), atol=2e-7)
    m = encode(v, 12)
    assert_valid_model(m, 12, v.shape)
    assert m.header["values"] == {"min": float(info.min), "max": float(info.max)}
    assert m.header["source"]["itemsize"] == np.dtype(dtype).itemsize
    assert m.header["source"]["bytes"] == v.size * np.dtype(dtype).itemsize


def test_float64_source_keeps_its_itemsize_and_range():
    v = smooth() * 1e300 - 5e299
    m = encode(v, 12)
    assert_valid_model(m, 12, v.shape)
    assert m.header["source"]["itemsize"] == 8 and m.header["source"]["dtype"] == "float64"


# -- masks: NaN / Inf, fill values, a land-sea mask -------------------------------------------------


def _check_mask_respected(m, valid: np.ndarray):
    """Seeds of the analytic model sit on valid voxels; metrics count valid voxels only."""
    rep = m.report
    assert rep["input"]["masked_voxels"] == int((~valid).sum())
    assert rep["structure"]["valid_voxels"] == int(valid.sum())
    assert rep["evaluation"]["final"]["points"] == int(valid.sum())  # full grid, masked voxels left out


def _seed_voxels(params: np.ndarray, shape_zyx) -> tuple:
    idx = np.clip(np.rint(params[:, :3]).astype(int), 0, np.array(shape_zyx[::-1]) - 1)
    return idx[:, 2], idx[:, 1], idx[:, 0]


def test_nan_and_inf_voxels_are_masked():
    v = smooth((10, 10, 10)).astype(np.float32)
    rng = np.random.default_rng(3)
    bad = rng.random(v.shape) < 0.15
    v[bad] = rng.choice(np.array([np.nan, np.inf, -np.inf], np.float32), int(bad.sum()))
    analytic = encode(v, 30, iterations=0, format="full")  # unquantised centres: the seeds themselves
    assert_valid_model(analytic, 30, v.shape)
    _check_mask_respected(analytic, ~bad)
    assert (~bad[_seed_voxels(analytic.params, v.shape)]).all()
    refined = encode(v, 30)
    assert_valid_model(refined, 30, v.shape)
    _check_mask_respected(refined, ~bad)
    assert refined.header["values"]["max"] == float(np.nanmax(np.where(np.isinf(v), np.nan, v)))


def ocean(shape_zyx=(6, 24, 32), fill=np.float32(9.96921e36)):
    """A synthetic climatology: temperature over lat x lon x depth, land and sea floor set to a fill value.

    The land mask is the same at every depth plus a sea floor that rises towards the coasts,
    like World Ocean Atlas fields; the fill value is netCDF's default float fill.
    """
    nz, ny, nx = shape_zyx
    z, y, x = np.meshgrid(np.arange(nz), np.linspace(-70, 70, ny), np.arange(nx), indexing="ij")
    temp = 28 * np.cos(np.radians(y)) ** 2 * np.exp(-z / 4.0) + 2 - 0.1 * z + 0.5 * np.sin(x / 3.0)
    lon = np.arange(nx)
    land2d = (np.abs(lon[None, :] - 10) < 3 + 2 * np.cos(np.linspace(0, 6, ny))[:, None]) | (np.abs(np.linspace(-70, 70, ny))[:, None] > 60)
    coast = np.minimum(np.abs(lon - 10) - 3, 30)[None, :]  # distance to the continent, in columns
    floor = np.broadcast_to(coast, (ny, nx)) * 0.8  # depth levels available
    land = land2d[None] | (np.arange(nz)[:, None, None] > floor[None])
    data = np.where(land, fill, temp).astype(np.float32)
    return data, ~land


@pytest.mark.parametrize("how", ["fill-value option", "hdf5 _FillValue attribute"])
def test_land_sea_mask_by_fill_value(how, tmp_path):
    data, sea = ocean()
    assert 0.2 < sea.mean() < 0.8
    if how == "fill-value option":
        m = encode(data, 60, read=ReadOptions(fill_value=float(np.float32(9.96921e36))))
    else:
        import h5py

        path = tmp_path / "woa.h5"
        with h5py.File(path, "w") as f:
            ds = f.create_dataset("t_an", data=data, chunks=(2, 8, 8))  # (depth, lat, lon)
            ds.attrs["_FillValue"] = np.float32(9.96921e36)
        m = encode(str(path), 60, read=ReadOptions(dataset="t_an"))
    dec, src = assert_valid_model(m, 60, data.shape, min_psnr=15.0)
    _check_mask_respected(m, sea)
    assert m.report["input"]["fill_value"] == pytest.approx(9.96921e36, rel=1e-6)
    t = data[sea]
    assert m.header["values"] == {"min": float(t.min()), "max": float(t.max())}  # the fill never sets the range
    # the fill never leaks into the decode: a 20-iteration model is close on average (its worst
    # voxel, an overshoot at the coast, moves with the sampling and is bounded by the clamp)
    assert np.abs(src[sea] - data[sea]).mean() < 0.05 * (t.max() - t.min())
    assert src.min() >= t.min() and src.max() <= t.max()
    occ = m.report["evaluation"]["final"]["psnr_occupied_db"]
    assert occ is not None and math.isfinite(occ)


def test_fill_value_at_the_minimum_is_masked_not_normalised():
    v = smooth().astype(np.float32) * 10 + 5
    v[:2] = -999.0
    m = encode(v, 20, read=ReadOptions(fill_value=-999.0))
    assert_valid_model(m, 20, v.shape)
    assert m.header["values"]["min"] == pytest.approx(float(v[2:].min()))
    _check_mask_respected(m, v != -999.0)


# -- shapes ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "shape_zyx, budget",
    [
        ((1, 12, 12), 20),
        ((2, 12, 12), 20),
        ((12, 12, 1), 20),
        ((12, 1, 12), 20),
        ((1, 1, 16), 4),
        ((3, 7, 29), 20),
        ((2, 2, 2), 1),
        ((1, 1, 2), 1),
        ((4, 4, 4), 8),
    ],
    ids=lambda s: "x".join(map(str, s)) if isinstance(s, tuple) else f"n{s}",
)
def test_thin_tiny_and_non_cubic_volumes(shape_zyx, budget):
    v = smooth(shape_zyx, seed=sum(shape_zyx))
    if v.size == 2:
        v = np.array([0.0, 1.0]).reshape(shape_zyx)
    m = encode(v.astype(np.float32), budget)
    assert_valid_model(m, budget, shape_zyx)
    assert m.report["input"]["shape_xyz"] == list(shape_zyx[::-1])
    # decode at another resolution stays finite and has the requested shape
    out = m.decode(shape_xyz=(3, 2, 5), device="cpu")
    assert out.shape == (5, 2, 3) and np.isfinite(out).all()


def test_same_seed_same_model_on_an_awkward_volume():
    """Determinism holds on a masked, thin, non-cubic volume too."""
    v = smooth((2, 9, 13)).astype(np.float32)
    v[:, 3:5, 4:9] = np.nan
    a, b = encode(v, 15), encode(v, 15)
    assert np.array_equal(a.params, b.params)


@pytest.mark.parametrize("fill", [1e300, -1e39, float("inf"), float("nan")])
def test_fill_values_no_voxel_can_hold_are_harmless(fill):
    """A --fill-value beyond the dtype's range (or inf, or NaN) masks nothing extra and warns about nothing."""
    v = smooth().astype(np.float32)
    v[0, 0, 0] = np.inf
    f = strict(normalise, v, fill_value=fill)
    assert f.n_valid == v.size - 1
