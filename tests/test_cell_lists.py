"""The forward pass through cell lists (issue #52): each primitive listed in every point cell its
widened box reaches, exact between re-bins because steps that would leave the listed cells wait."""

from __future__ import annotations

import numpy as np
import pytest

from warpgauss.encoding.refine import LossWeights, RefineConfig, Refiner
from warpgauss.field.analysis import DeviceVolume, normalise


def _refiner(device, n=300, samples=1024, seed=0, field="vortex", size=24, **cfg):
    from warpgauss.core.profiling import StageRecorder
    from warpgauss.encoding.allocate import AllocationConfig, allocate
    from warpgauss.readers.synthetic import generate

    f = normalise(generate(field, size, seed=1))
    dv = DeviceVolume(f, device)
    ac = AllocationConfig()
    params, _ = allocate(dv, n, seed, ac, StageRecorder())
    cfg.setdefault("weights", LossWeights(smooth=0.01))  # the partner points in the passes too
    return Refiner(dv, params, RefineConfig(iterations=60, samples=samples, **cfg), seed, ac.scale_min, ac.resolved_cap(f.shape_xyz))


def _dense(r):
    """V~, rho and pair counts of the all-pairs reference at the refiner's current points."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import field as kf

    wp, p, m2 = warp(), r.prims, r.n_points
    out = [wp.empty(m2, dtype=t, device=r.device) for t in (float, float, int)]
    wp.launch(kf.eval_points_dense, dim=m2, inputs=[r.points, p.mu, p.conic, p.ext, p.a, p.w], outputs=out, device=r.device)
    return [a.numpy() for a in out]


def _forward(r, listed: bool):
    r.passes.listed = listed
    r.forward()
    return r.value.numpy().copy(), r.density.numpy().copy(), r.pairs.numpy().copy()


@pytest.mark.parametrize("field", ["vortex", "interface"])
def test_listed_forward_is_the_bin_walk_bit_for_bit_and_the_dense_pairs(device, field):
    """Mid-interval (primitives moved since their re-bin): the lists give the bin walk's values
    bit for bit (a cell lists its primitives in slot order, the walk's summation order) and the
    all-pairs reference's pairs."""
    r = _refiner(device, field=field)
    for _ in range(15):  # a re-bin at 10, then five steps
        r.step()
    assert r.passes.listed and r.passes.list_entries > r.n
    assert r.forward_pass.startswith("point-major, cell lists") or r.passes.use_partials()
    r.sample()
    walk = _forward(r, False)
    lists = _forward(r, True)
    for a, b in zip(walk, lists):
        np.testing.assert_array_equal(a, b)
    from warpgauss.encoding.refine import passes

    kept = passes.FORWARD_UNROLL, passes.FORWARD_MORTON, passes.MORTON_MIN_ENTRIES
    try:  # one or two entries loaded at a time, points in Morton or cell order: the same sums bit for bit
        for unroll in (1, 2):
            for morton, least in ((0, 0.0), (1, 0.0), (1, 1e9)):
                passes.FORWARD_UNROLL, passes.FORWARD_MORTON, passes.MORTON_MIN_ENTRIES = unroll, morton, least
                assert r.passes.morton() == (morton == 1 and least == 0.0)
                for a, b in zip(lists, _forward(r, True)):
                    np.testing.assert_array_equal(a, b)
    finally:
        passes.FORWARD_UNROLL, passes.FORWARD_MORTON, passes.MORTON_MIN_ENTRIES = kept
    dense = _dense(r)
    np.testing.assert_array_equal(lists[2], dense[2])
    np.testing.assert_allclose(lists[0], dense[0], rtol=2e-5, atol=2e-6)


def test_steps_that_would_leave_the_listed_cells_wait_for_the_rebin(device, monkeypatch):
    """No widening at all: many steps would leave the listed cells; those wait (more deferred
    steps than with the bin cells alone), and the pairs stay exactly the reference's."""
    from warpgauss.encoding.refine import passes

    monkeypatch.setattr(passes, "LIST_PAD_SHARE", 0.0)
    monkeypatch.setattr(passes, "LIST_PAD_VOXELS", 0.0)
    deferred = {}
    for lists in (False, True):
        r = _refiner(device, field="interface", cell_lists=lists)
        for it in range(19):
            r.step()
            if lists and it % 6 == 5:
                r.sample()
                _forward(r, True)
                np.testing.assert_array_equal(r.pairs.numpy(), _dense(r)[2])
        deferred[lists] = r.deferred_steps()
    assert deferred[True] > deferred[False]
    lo, hi = r.state.bounds.box_lo.numpy(), r.state.bounds.box_hi.numpy()
    mu, ext = r.prims.mu.numpy(), r.prims.ext.numpy()
    assert np.all(mu - ext >= lo) and np.all(mu + ext <= hi)  # every box inside its listed cells


def test_lists_follow_new_point_grids_without_a_rebin(device):
    """More samples mid-interval re-plan the point grids: the lists are indexed anew (the union of
    each listing box and the current box), and stay exact."""
    r = _refiner(device, samples=256)
    for _ in range(14):
        r.step()
    before = r.passes.buffers()["grid_plan"]
    r.set_samples(8192)
    r.sample()
    lists = _forward(r, True)
    assert r.passes.buffers()["grid_plan"] != before
    np.testing.assert_array_equal(lists[2], _dense(r)[2])
    r.step()  # and the iteration runs on them


def test_too_many_entries_fall_back_to_the_bin_walk(device, monkeypatch):
    """Lists that would pass LIST_MAX_ENTRIES are not built: the bin walk, slots free to go where
    their bin cells allow, and the very model of a run without lists (same seed, same device)."""
    from warpgauss.encoding.refine import passes

    monkeypatch.setattr(passes, "LIST_MAX_ENTRIES", 10)
    a = _refiner(device)
    b = _refiner(device, cell_lists=False)
    for r in (a, b):
        r.run()
    assert not a.passes.listed and a.forward_pass.startswith("point-major") and "cell lists" not in a.forward_pass
    assert np.all(a.state.bounds.box_lo.numpy() <= -1e29) and np.all(a.state.bounds.box_hi.numpy() >= 1e29)
    np.testing.assert_array_equal(a.model_params(), b.model_params())


def test_listed_runs_repeat_bit_for_bit(device):
    """Same seed, same device: the same model with lists (the sort is stable, the sums ordered)."""
    runs = []
    for _ in range(2):
        r = _refiner(device, field="interface")
        r.run()
        runs.append(r.model_params())
    np.testing.assert_array_equal(*runs)


def test_lists_filled_one_thread_an_entry_are_the_slot_walks_lists(device):
    """kernels.lists.list_fill_entries (one thread per entry, its slot by a binary search; the one
    the re-bin runs) writes the entries of list_fill (one thread per slot) in the same places:
    the same keys and slots before the sort, with primitives of very different list lengths."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import lists as kl

    wp = warp()
    r = _refiner(device, n=120)
    for _ in range(12):  # a re-bin at 10
        r.step()
    ps, st = r.passes, r.state
    total = ps.list_entries
    counts = ps._list_counts.numpy()
    assert total > 3 * r.n and counts.max() > 4 * max(counts.min(), 1)  # some slots list many more cells
    args = [st.slot_cell, st.prims, ps.buffers()["grid"], ps.list_centre, ps.list_half, ps._list_cum]
    got = []
    for kernel, dim in ((kl.list_fill, r.n), (kl.list_fill_entries, total)):
        out = [wp.full(total, -1, dtype=int, device=r.device) for _ in range(2)]
        wp.launch(kernel, dim=dim, inputs=args, outputs=out, device=r.device)
        got.append([a.numpy() for a in out])
    for a, b in zip(*got):
        assert (a >= 0).all()
        np.testing.assert_array_equal(a, b)


def test_morton_order_is_numpys_interleave_stably_sorted(device):
    """The forward's point order: the Morton code of each point's voxel (x in the lowest bit,
    clamped to 0..1023 an axis) from bit interleaving in numpy, sorted stably (ties by point)."""
    from warpgauss.core.warp import warp
    from warpgauss.kernels import lists as kl

    wp = warp()
    rng = np.random.default_rng(3)
    pts = np.concatenate([rng.uniform(-0.5, 40.5, (500, 3)), [[-3.0, 2.0, 2.0], [2000.0, 1.0, 5.0]], rng.uniform(0, 3, (60, 3))])
    pts = pts.astype(np.float32)
    n = len(pts)
    keys = wp.empty(2 * n, dtype=int, device=device)
    order = wp.empty(2 * n, dtype=int, device=device)
    wp.launch(kl.morton_keys, dim=n, inputs=[wp.array(pts, dtype=wp.vec3, device=device), 0.5], outputs=[keys, order], device=device)
    q = np.clip(np.floor((pts.astype(np.float64) + 0.5) * 0.5), 0, 1023).astype(np.int64)
    ref = np.zeros(n, np.int64)
    for bit in range(10):
        for axis in range(3):
            ref |= ((q[:, axis] >> bit) & 1) << (3 * bit + axis)
    np.testing.assert_array_equal(keys.numpy()[:n], ref)
    wp.utils.radix_sort_pairs(keys, order, n, 0, 30)
    np.testing.assert_array_equal(order.numpy()[:n], np.argsort(ref, kind="stable"))
