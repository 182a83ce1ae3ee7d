"""The bounded residual's interpolation passes as Warp kernels (kernels/interp.py) against the
numpy passes of warpgauss.format.residual: the same q's and decoded values bit for bit, float and
integer lattices, cubic and linear, every axis order, level-wise steps, skipped points and ties."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.format import interpolation as I
from warpgauss.format import residual as R


def _case(rng, shape, integer: bool, step: float):
    if integer:
        t = rng.integers(-300, 300, shape).astype(np.int64)
    else:
        # half a step apart: many errors fall exactly between two levels (rint's ties)
        t = np.where(rng.random(shape) < 0.5, rng.integers(-40, 40, shape) * (0.5 * step), rng.normal(0.0, 7.0, shape))
    skip = rng.random(shape) < 0.1
    if not integer:
        t[skip & (rng.random(shape) < 0.5)] = np.nan  # a skipped value may be NaN
    return t, skip


@pytest.mark.parametrize("shape", [(9, 13, 6), (17, 5, 33), (1, 8, 3), (32, 32, 32)])
@pytest.mark.parametrize("integer", [False, True])
def test_kernel_passes_equal_the_numpy_passes_bit_for_bit(device, shape, integer):
    rng = np.random.default_rng(sum(shape) + integer)
    step = 5.0 if integer else 0.3
    t, skip = _case(rng, shape, integer, step)
    for interp in ("cubic", "linear"):
        for axes, levels in (("012", I.FLAT), ("201", (1.5, 4.0)), ("120", (1.25, 2.0))):
            ref_q, ref_dec = I.feedback(t, skip, step, integer, interp, axes, levels)
            q, dec = I.feedback(t, skip, step, integer, interp, axes, levels, device=device)
            assert q.dtype == ref_q.dtype and dec.dtype == ref_dec.dtype
            np.testing.assert_array_equal(q, ref_q)
            assert np.array_equal(dec.view(np.int64), ref_dec.view(np.int64))  # the bits, signed zeros included
            assert np.any(q != 0)
            # and a reader decodes the same values from the q's
            back = I.decoded(q, step, integer, interp, axes, levels)
            assert np.array_equal(back.view(np.int64), dec.view(np.int64))
            # on the kernels too (kernels.interp.decode_pass_*)
            again = I.decoded(q, step, integer, interp, axes, levels, device=device)
            assert again.dtype == back.dtype and np.array_equal(again.view(np.int64), back.view(np.int64))


def test_a_coded_residual_is_the_same_file_on_the_kernels(device):
    """code_residual with the passes on a device writes the bytes the numpy passes write."""
    rng = np.random.default_rng(4)
    z, y, x = np.mgrid[0:20, 0:24, 0:18]
    src = (100 * np.sin(0.3 * x) * np.cos(0.2 * y) + 3 * z + rng.normal(0, 2, x.shape)).astype(np.float32)
    pred = src.astype(np.float64) + rng.normal(0, 1.5, src.shape)
    lo, hi = float(src.min()), float(src.max())
    for rel in (1e-2, 1e-3):
        a, fa = R.code_residual(src, None, pred, np.zeros(src.shape, bool), rel * (hi - lo), (lo, hi))
        b, fb = R.code_residual(src, None, pred, np.zeros(src.shape, bool), rel * (hi - lo), (lo, hi), device=device)
        assert a.payload() == b.payload() and a.info == b.info and fa["sizes"] == fb["sizes"]
        # a reader applying it with the passes on the device decodes the numpy reader's values
        out = R.apply_residual(b, pred, device)
        assert np.array_equal(out.view(np.int32), R.apply_residual(a, pred).view(np.int32))
        assert R.verify(b, pred, src, None, (lo, hi), device)["max_abs_error"] <= rel * (hi - lo)
