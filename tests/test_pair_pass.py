"""The balanced pair pass of refinement: point grids, dense cell starts, chunked partial gradients."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import assert_matches_atomic_scatter

from warpgauss.encoding.refine import LossWeights, RefineConfig, Refiner
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.field.gaussians import BinPlan, plan_bins, plan_point_grids


def _refiner(device, n=300, samples=1024, seed=0):
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 24, seed=1))
    dv = DeviceVolume(f, device)
    cfg = AllocationConfig()
    params, _ = allocate(dv, n, seed, cfg, StageRecorder())
    rc = RefineConfig(iterations=1, samples=samples, weights=LossWeights(smooth=0.01))  # partner points too
    return Refiner(dv, params, rc, seed, cfg.scale_min, cfg.resolved_cap(f.shape_xyz))


def test_cell_starts_equal_numpy_searchsorted(device):
    """Every cell, empty ones at either end and between included, gets the first entry at or past
    it, and the table ends with the entry count; only the first ``count`` keys count."""
    from warpgauss.core.warp import warp
    from warpgauss.field.gaussians import cell_starts

    wp = warp()
    rng = np.random.default_rng(5)
    for cells, count in ((40, 0), (40, 1), (50, 300), (7, 64), (100000, 5)):
        keys = np.sort(rng.integers(3, max(cells - 4, 4), count)).astype(np.int32)
        padded = np.concatenate([keys, [cells - 1] * 3]).astype(np.int32)  # entries past count: ignored
        start = wp.full(cells + 1, -7, dtype=int, device=device)  # poisoned: every cell must be written
        counts = wp.full(cells + 1, 9, dtype=int, device=device)  # stale counts: zeroed first
        cell_starts(wp.array(padded, dtype=int, device=device), count, counts, start, device)
        ref = np.searchsorted(keys, np.arange(cells + 1), side="left")
        np.testing.assert_array_equal(start.numpy(), ref)


def _pair_pass(r):
    r.sample()
    r.forward_backward()
    return [a.numpy().copy() for a in r.pair_grads], r.back_pairs.numpy().copy(), r.pair_pass_stats()


@pytest.mark.parametrize(
    "min_chunk,capacity,max_chunks,lanes",
    [(1, 1 << 20, 1 << 30, 32), (5, 1 << 20, 1 << 30, 3), (1, 7, 1 << 30, 32), (1, 1 << 20, 4, 2), (2, 1 << 20, 64, 1)],
    ids=["one-per-chunk", "five-in-groups-of-three", "capacity-bound", "two-groups-of-two", "groups-of-one"],
)
def test_chunked_pass_equals_the_atomic_scatter_however_it_splits(device, monkeypatch, min_chunk, capacity, max_chunks, lanes):
    """Chunks of 1, 2 or 5 candidates, as many as a tiny capacity forces, or at most 4 per
    primitive; groups of at least 32, 3, 2 or 1 chunks sharing a primitive's rows: the same pairs, and the
    gradients of the point-major atomic scatter (another summation order: rounding only)."""
    from warpgauss.encoding.refine import passes

    monkeypatch.setattr(passes, "MIN_CHUNK", min_chunk)
    monkeypatch.setattr(passes, "MAX_CHUNKS", max_chunks)
    monkeypatch.setattr(passes, "LANES", lanes)
    monkeypatch.setattr(passes, "chunk_capacity", lambda n_points: capacity)
    r = _refiner(device)
    mine, pairs, stats = _pair_pass(r)
    np.testing.assert_array_equal(pairs, r.pairs.numpy())
    assert pairs.sum() > 10 * r.m
    assert stats["chunks"] <= min(r.n + capacity, r.n * max_chunks)
    b = r.passes.buffers()
    chunks, groups, rows = (b[k].numpy()[: r.n] for k in ("chunks", "groups", "rows"))
    assert np.all(chunks % groups == 0) and np.all(groups >= 1)  # whole groups
    assert np.all(groups <= np.maximum(rows, 1))  # at most one a row
    assert np.all(chunks[groups > 1] // groups[groups > 1] >= lanes)  # of LANES chunks or more
    if max_chunks < 100:
        assert np.mean(chunks == max_chunks) > 0.5  # most primitives use them all: two groups of two, 64 of one
    elif capacity > 1000:
        assert stats["chunk_size"] == min_chunk
        assert 2 * stats["chunks"] >= stats["candidates"] // min_chunk > 5 * r.n  # really split
        assert np.sum(groups > 1) > 0.1 * r.n  # several groups
        assert np.any(chunks // groups > 32)  # groups reduced in several blocks
    else:
        assert stats["chunk_size"] >= stats["candidates"] / capacity
    assert stats["candidates"] >= pairs.sum()
    assert_matches_atomic_scatter(r, mine, pairs)


def test_chunked_pass_reruns_bit_identically(device, monkeypatch):
    from warpgauss.encoding.refine import passes

    monkeypatch.setattr(passes, "MIN_CHUNK", 3)
    monkeypatch.setattr(passes, "LANES", 4)
    runs = []
    for _ in range(2):
        r = _refiner(device)
        runs.append(_pair_pass(r)[0])
    for x, y in zip(*runs):
        np.testing.assert_array_equal(x, y)


def test_register_capped_backward_is_the_same_kernel(device, monkeypatch):
    """The chunked backward with its registers capped (a CUDA compile option) gives the same
    pairs and gradients bit for bit."""
    from warpgauss.encoding.refine import passes

    runs = []
    for regs in (0, 64):
        monkeypatch.setattr(passes, "BACKWARD_REGISTERS", regs)
        grads, pairs, _ = _pair_pass(_refiner(device))
        runs.append((grads, pairs))
    for grads, pairs in runs[1:]:
        np.testing.assert_array_equal(pairs, runs[0][1])
        for x, y in zip(grads, runs[0][0]):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("split,owner_search", [(1, 4), (3, 1 << 30), (8, 1), (5, 4)])
def test_split_counts_and_searched_owners_change_nothing(device, monkeypatch, split, owner_search):
    """The candidate counts taken by several threads a primitive (any split, rows dealt out in
    turn) and the chunks' owners found by a binary search give the counts, the owners and the
    gradients of one thread a primitive, bit for bit; the owners are numpy's repeat of the slots."""
    from warpgauss.encoding.refine import passes

    monkeypatch.setattr(passes, "MIN_CHUNK", 2)
    runs = []
    for ws, below, search in ((1, 0, 1 << 30), (split, 1 << 30, owner_search)):
        monkeypatch.setattr(passes, "WORK_SPLIT", ws)
        monkeypatch.setattr(passes, "WORK_SPLIT_BELOW", below)
        monkeypatch.setattr(passes, "OWNER_SEARCH_SLOTS", search)
        r = _refiner(device)
        grads, pairs, _ = _pair_pass(r)
        b = r.passes.buffers()
        chunks = b["chunks"].numpy()[: r.n]
        owner = b["owner"].numpy()[: int(chunks.sum())]
        np.testing.assert_array_equal(owner, np.repeat(np.arange(r.n), chunks))
        assert (chunks > 1).sum() > r.n // 4  # several chunks a primitive: the search has work
        runs.append((grads, pairs, b["work"].numpy()[: r.n].copy(), b["rows"].numpy()[: r.n].copy()))
    (g0, p0, w0, r0), (g1, p1, w1, r1) = runs
    np.testing.assert_array_equal(w1, w0)
    np.testing.assert_array_equal(r1, r0)
    np.testing.assert_array_equal(p1, p0)
    for x, y in zip(g1, g0):
        np.testing.assert_array_equal(x, y)


def test_chunked_pass_keeps_every_pair_of_needle_and_disc_shapes(device):
    """Rotated primitives up to 40:1 (needles and discs), centres past the grid, partner points:
    the chunked pass, the forward pass, the dense all-pairs reference and the atomic scatter count
    the same pairs, and the gradients agree."""
    from conftest import random_params
    from test_cell_lists import _dense

    from warpgauss.readers.synthetic import generate

    f = normalise(generate("vortex", 32, seed=1))
    params = random_params(np.random.default_rng(7), 400, f.shape_xyz, log_scale=(-2.0, -0.5), aniso=40.0)
    rc = RefineConfig(iterations=1, samples=8192, weights=LossWeights(smooth=0.01))
    r = Refiner(DeviceVolume(f, device), params, rc, 0, 0.05, 8.0)
    mine, pairs, stats = _pair_pass(r)
    np.testing.assert_array_equal(pairs, r.pairs.numpy())
    np.testing.assert_array_equal(pairs, _dense(r)[2])
    assert r.n_points < pairs.sum() <= stats["candidates"]
    assert_matches_atomic_scatter(r, mine, pairs)


def test_point_grids_refine_with_more_points_and_stay_bounded():
    """More points per voxel: finer (never coarser) point cells; the global level stays one cell."""
    rng = np.random.default_rng(0)
    shape = (256, 256, 256)
    plan = plan_bins(rng.uniform(6.0, 60.0, 5000), shape)
    sparse = plan_point_grids(plan, 6_000, shape, 256**3)
    dense = plan_point_grids(plan, 2_000_000, shape, 256**3)
    for a, b, s in zip(sparse.sizes[:-1], dense.sizes[:-1], plan.sizes[:-1]):
        assert b <= a <= s and s % a == 0 and s % b == 0
    assert any(b < a for a, b in zip(sparse.sizes[:-1], dense.sizes[:-1]))
    for g in (sparse, dense):
        assert g.dims[-1] == (1, 1, 1) and g.total_cells == sum(x * y * z for x, y, z in g.dims)
        assert g.offsets[0] == 0 and all(np.diff(g.offsets) > 0)
    # sparse samples (the paper's 3,072 for many primitives): the level's own cells
    tiny = plan_point_grids(BinPlan((8.0, 3.4e38), ((32, 32, 32), (1, 1, 1)), (0, 32768), 32769), 6_000, shape, 256**3)
    assert tiny.sizes[0] == 8.0
