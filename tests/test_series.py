"""Time series groundwork (issue #21): the evolving example and the warm start (same seed, same
model; exact N; a warm start from another grid or budget refused in one line)."""

from __future__ import annotations

import numpy as np
import pytest

import warpgauss
from warpgauss.errors import WarpgaussError
from warpgauss.synthetic import generate, generate_series

FAST = dict(budget=200, iterations=40, samples=256, device="cpu", self_test=False, format="full")


def test_the_evolving_example_turns_about_z():
    a = list(generate_series("vortex", 20, 3))
    b = list(generate_series("vortex", 20, 3))
    assert len(a) == 3 and all(x.dtype == np.float32 and x.shape == (20, 20, 20) for x in a)
    np.testing.assert_array_equal(a[0], generate("vortex", 20))
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert all(float(x.min()) == 0.0 and float(x.max()) == 1.0 for x in a)
    d1, d2 = (float(np.abs(a[t] - a[0]).mean()) for t in (1, 2))
    assert 0 < d1 < d2  # further from the start as it turns
    with pytest.raises(WarpgaussError, match="steps must be a positive int"):
        next(generate_series("vortex", 20, 0))


def test_a_warm_start_refines_the_previous_model():
    v0, v1 = generate_series("vortex", 20, 2)
    m0 = warpgauss.encode(v0, **FAST)
    warm = warpgauss.encode(v1, warm_start=m0, **FAST)
    again = warpgauss.encode(v1, warm_start=m0, **FAST)
    np.testing.assert_array_equal(warm.params, again.params)  # same seed and device: same model
    assert warm.n == m0.n == 200
    assert warm.report["refinement"]["iterations"] == 40
    assert any(s["what"] == "S1b-S1e allocation" for s in warm.report["skipped"])
    start = warm.report["evaluation"]["analytic"]["psnr_db"]
    assert warm.report["psnr_db"] >= start  # refinement moved it towards the new timestep
    with pytest.raises(WarpgaussError, match="same budget"):
        warpgauss.encode(v1, **{**FAST, "budget": 150}, warm_start=m0)
    with pytest.raises(WarpgaussError, match="grid"):
        warpgauss.encode(generate("vortex", 16), **FAST, warm_start=m0)
    with pytest.raises(WarpgaussError, match=r"\(N, 12\)"):
        warpgauss.encode(v1, **FAST, warm_start=np.zeros((200, 3)))
