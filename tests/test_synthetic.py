"""Built-in example volumes: contract (shape, dtype, exact [0, 1], determinism, errors) and character.

The character checks recompute the SPEC section 5 statistics with plain numpy, independently of
``warpgauss.field.analysis``: occupancy, gradient top-10 % share, S(1)/S(16), and for ``turbulence`` the
slope of the radially averaged power spectrum.
"""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.errors import WarpgaussError
from warpgauss.readers.synthetic import EXAMPLES, generate, raw_name

NAMES = ["vortex", "bubbles", "turbulence", "interface"]
OCCUPIED = 0.02


def occupancy(v: np.ndarray) -> float:
    return float((v > OCCUPIED).mean())


def grad_top10(v: np.ndarray) -> float:
    """Share of the summed |grad V| over occupied voxels carried by the top 10 % of them."""
    g = np.sqrt(sum(d**2 for d in np.gradient(v.astype(np.float64))))
    g = np.sort(g[v > OCCUPIED])[::-1]
    top = int(np.ceil(0.1 * g.size))
    return float(g[:top].sum() / g.sum())


def structure(v: np.ndarray, lag: int) -> float:
    """S(lag): mean |V(x + lag e_k) - V(x)| over occupied x and the three axes."""
    v = v.astype(np.float64)
    total = count = 0.0
    for axis in range(3):
        n = v.shape[axis]
        a = np.take(v, np.arange(n - lag), axis=axis)
        b = np.take(v, np.arange(lag, n), axis=axis)
        occ = a > OCCUPIED
        total += np.abs(b - a)[occ].sum()
        count += occ.sum()
    return total / count


def spectrum_slope(v: np.ndarray, k_lo: int, k_hi: int) -> float:
    """Least-squares slope of log P(|k|) over integer shells k_lo..k_hi of a cube."""
    n = v.shape[0]
    power = np.abs(np.fft.rfftn(v - v.mean())) ** 2
    k = np.fft.fftfreq(n, 1.0 / n)
    kx = np.arange(n // 2 + 1)
    shell = np.rint(np.sqrt(k[:, None, None] ** 2 + k[None, :, None] ** 2 + kx[None, None, :] ** 2)).astype(int)
    p = np.bincount(shell.ravel(), power.ravel()) / np.maximum(np.bincount(shell.ravel()), 1)
    ks = np.arange(k_lo, k_hi + 1)
    return float(np.polyfit(np.log(ks), np.log(p[ks]), 1)[0])


def block_mean(v: np.ndarray) -> np.ndarray:
    nz, ny, nx = v.shape
    return v.reshape(nz // 2, 2, ny // 2, 2, nx // 2, 2).mean(axis=(1, 3, 5))


def lowpass(v: np.ndarray, kmax: int) -> np.ndarray:
    n = v.shape[0]
    f = np.fft.rfftn(v - v.mean())
    k = np.abs(np.fft.fftfreq(n, 1.0 / n))
    keep = (k[:, None, None] <= kmax) & (k[None, :, None] <= kmax) & (np.arange(n // 2 + 1)[None, None, :] <= kmax)
    return np.fft.irfftn(f * keep, s=v.shape, axes=(0, 1, 2))


# --- contract -------------------------------------------------------------------------------


def test_examples_table_names_every_generator():
    assert sorted(EXAMPLES) == sorted(NAMES)
    assert all(isinstance(d, str) and d and "\n" not in d for d in EXAMPLES.values())


@pytest.mark.parametrize("name", NAMES)
def test_shape_dtype_and_exact_unit_range(name):
    v = generate(name, 32, seed=0)
    assert v.shape == (32, 32, 32) and v.dtype == np.float32 and v.flags.c_contiguous
    assert np.isfinite(v).all()
    assert v.min() == 0.0 and v.max() == 1.0


@pytest.mark.parametrize("name", NAMES)
def test_non_cubic_size_is_x_y_z_and_array_is_z_y_x(name):
    v = generate(name, (40, 24, 36), seed=2)
    assert v.shape == (36, 24, 40) and v.dtype == np.float32 and v.flags.c_contiguous
    assert v.min() == 0.0 and v.max() == 1.0


@pytest.mark.parametrize("name", NAMES)
def test_same_seed_is_bit_identical_and_seeds_differ(name):
    a = generate(name, (36, 32, 28), seed=5)
    b = generate(name, (36, 32, 28), seed=5)
    assert a.tobytes() == b.tobytes()
    c = generate(name, (36, 32, 28), seed=6)
    assert np.abs(a - c).mean() > 1e-3


def test_default_size_is_64_cube():
    assert generate("vortex").shape == (64, 64, 64)


def test_smallest_size_works():
    for name in NAMES:
        v = generate(name, 4, seed=0)
        assert v.shape == (4, 4, 4) and v.min() == 0.0 and v.max() == 1.0


def test_unknown_name_is_one_line_naming_the_examples():
    with pytest.raises(WarpgaussError) as err:
        generate("nope", 16)
    msg = str(err.value)
    assert "\n" not in msg and "nope" in msg and all(n in msg for n in NAMES)
    with pytest.raises(WarpgaussError):
        raw_name("nope", 16)


@pytest.mark.parametrize("size", [3, 0, -8, (16, 16, 3), (16, 0, 16), (16, 16), (16, 16, 16, 16), 16.0, (16, 16, 2.5)])
def test_bad_sizes_are_refused(size):
    with pytest.raises(WarpgaussError):
        generate("vortex", size)


@pytest.mark.parametrize("seed", [-1, 1.5, None])
def test_bad_seeds_are_refused(seed):
    with pytest.raises(WarpgaussError):
        generate("vortex", 8, seed=seed)


def test_raw_name_follows_open_scivis():
    assert raw_name("vortex", 128) == "vortex_128x128x128_float32.raw"
    assert raw_name("bubbles", (256, 256, 640)) == "bubbles_256x256x640_float32.raw"


# --- character ------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", [0, 1])
def test_vortex_is_fully_occupied_and_smooth(seed):
    v = generate("vortex", 64, seed=seed)
    assert occupancy(v) >= 0.99
    assert structure(v, 1) / structure(v, 16) < 0.15


@pytest.mark.parametrize("size", [64, 96])
def test_bubbles_are_sparse(size):
    v = generate("bubbles", size, seed=size)
    assert 0.015 <= occupancy(v) <= 0.035
    assert (v == 0).mean() > 0.9  # exactly zero outside the bubbles' boxes
    assert structure(v, 1) / structure(v, 16) > 0.2  # sharp edges: structure saturates below 16 voxels


@pytest.mark.parametrize("seed", [0, 3])
def test_turbulence_is_fully_occupied_with_a_power_law_spectrum(seed):
    v = generate("turbulence", 64, seed=seed)
    assert occupancy(v) >= 0.97
    slope = spectrum_slope(v, 4, 16)  # k^-5/3 energy spectrum -> P(k) ~ k^-11/3
    assert -4.7 < slope < -2.7, slope


@pytest.mark.parametrize("seed", [0, 4])
def test_interface_is_half_occupied_with_concentrated_gradient(seed):
    v = generate("interface", 64, seed=seed)
    assert 0.4 <= occupancy(v) <= 0.6
    assert grad_top10(v) >= 0.5
    # heavy fluid below, light above
    assert v[:8].mean() > 0.7 and v[-8:].max() < OCCUPIED


# --- resolution independence ----------------------------------------------------------------


@pytest.mark.parametrize("name", ["vortex", "interface"])
def test_two_resolutions_show_the_same_field(name):
    coarse = generate(name, 32, seed=7)
    fine = block_mean(generate(name, 64, seed=7))
    assert np.corrcoef(coarse.ravel(), fine.ravel())[0, 1] > 0.97


def test_turbulence_large_scales_agree_across_resolutions():
    coarse = lowpass(generate("turbulence", 32, seed=7), 4)
    fine = lowpass(block_mean(generate("turbulence", 64, seed=7)), 4)
    assert np.corrcoef(coarse.ravel(), fine.ravel())[0, 1] > 0.9


def test_the_vortex_slabs_on_several_threads_equal_the_serial_field(monkeypatch):
    """The vortex field's slabs are computed on threads; the field is the one-thread field bit for
    bit (here 4 slabs, small ones, on up to 3 threads)."""
    import warpgauss.readers.synthetic as sy

    monkeypatch.setattr(sy, "SLAB_VOXELS", 40 * 40 * 10)
    monkeypatch.setattr(sy, "SLAB_THREADS", 1)
    serial = sy.generate("vortex", 40)
    monkeypatch.setattr(sy, "SLAB_THREADS", 3)
    np.testing.assert_array_equal(sy.generate("vortex", 40), serial)
    assert len(list(sy._slabs(serial.shape))) == 4
