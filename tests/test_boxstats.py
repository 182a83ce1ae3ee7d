"""A brick's box on the device (warpgauss.field.boxstats, the Warp CPU device here): region masks, and
counts and |grad V| sums of a masked box (a strided view of a larger array) against a float64
numpy reference; the counts exactly, the sum to float32 rounding."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.core.warp import warp
from warpgauss.field.analysis import OCCUPIED, count_seed_candidates, normalise
from warpgauss.field.boxstats import box_counts, box_view, region_mask
from warpgauss.readers.synthetic import generate

BOX = ((3, 27), (0, 22), (5, 30))
INNER = ((2, 15), (4, 19), (0, 20))


def reference_grad_sum(v: np.ndarray, select: np.ndarray) -> float:
    """float64 sum of |grad V| (numpy.gradient: central, one-sided at the faces) over occupied selected voxels."""
    g = np.zeros(v.shape)
    for axis in range(3):
        g += np.gradient(v.astype(np.float64), axis=axis) ** 2
    use = (v > np.float32(OCCUPIED)) & select
    return float(np.sqrt(g[use]).sum())


@pytest.fixture(scope="module")
def volume():
    wp = warp()
    v = normalise(generate("bubbles", 32)).values
    valid = np.random.default_rng(3).random(v.shape) > 0.15
    dv = wp.array(v, dtype=float, device="cpu")
    dm = wp.array(valid.view(np.uint8), dtype=wp.uint8, device="cpu")
    return v, valid, dv, dm


def test_region_masks_follow_the_regions_the_exclusion_and_validity(volume):
    v, valid, dv, dm = volume
    sub_valid = valid[tuple(slice(a, b) for a, b in BOX)]
    shape = sub_valid.shape
    inner = np.zeros(shape, bool)
    inner[tuple(slice(a, b) for a, b in INNER)] = True
    m = region_mask(shape, "cpu", [INNER], valid=box_view(dm, BOX))
    np.testing.assert_array_equal(m.numpy() != 0, inner & sub_valid)
    regions = [((0, 9), (0, shape[1]), (0, shape[2])), ((0, shape[0]), (15, 22), (0, shape[2]))]
    want = np.zeros(shape, bool)
    for r in regions:
        want[tuple(slice(a, b) for a, b in r)] = True
    halo = region_mask(shape, "cpu", regions, exclude=INNER)
    np.testing.assert_array_equal(halo.numpy() != 0, want & ~inner)
    assert not region_mask(shape, "cpu", []).numpy().any()


@pytest.mark.parametrize("masked", [False, True])
def test_box_counts_match_the_host_counts_and_a_float64_gradient_sum(volume, masked):
    v, valid, dv, dm = volume
    sub = np.ascontiguousarray(v[tuple(slice(a, b) for a, b in BOX)])
    sel = np.zeros(sub.shape, bool)
    sel[tuple(slice(a, b) for a, b in INNER)] = True
    if masked:
        sel &= valid[tuple(slice(a, b) for a, b in BOX)]
        m = region_mask(sub.shape, "cpu", [INNER], valid=box_view(dm, BOX))
        c = box_counts(box_view(dv, BOX), m)
        occ, elig = count_seed_candidates(sub, sel)
    else:
        c = box_counts(box_view(dv, BOX))
        sel[:] = True
        occ, elig = count_seed_candidates(sub, None)
    assert (c.n_valid, c.occupied, c.eligible) == (int(sel.sum()), occ, elig)
    assert 0 < c.occupied < sub.size and c.eligible > 0
    assert c.grad_sum == pytest.approx(reference_grad_sum(sub, sel), rel=1e-5)
