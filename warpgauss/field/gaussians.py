"""Truncation-aware evaluation of a Gaussian primitive set: points, grids, and the dense reference.

:class:`GaussianField` uploads a parameter array once, prepares every primitive (precision matrix,
5-sigma bounding box), bins primitives by truncation radius into cell grids, and answers queries
at arbitrary points (:meth:`GaussianField.evaluate`) or on a whole output grid
(:meth:`GaussianField.decode`). :meth:`GaussianField.evaluate_dense` runs the all-pairs reference
with the identical cut; it is for tests and the pre-run self-test only.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core.warp import resolve_device, warp
from ..errors import WarpgaussError

MIN_CELL = 1.0  # smallest cell edge in voxels: finer cells cost more cell visits than they save
MAX_LEVEL_CELLS = 1 << 24  # cells per level (64 MiB of int32 ranges at most); coarser beyond
# output voxels per decode launch (256 MiB of float32). Measured on an H200 (the bench's model at
# 1024^3, speed/decode_profile_1024_columns8_h200.json): 2^24 -> 2^26 took the brick listing
# (one thread a brick) 137.6 -> 58.9 ms at N 20,000 and 273.4 -> 109.3 ms at 1.4M, the decode
# 675 -> 585 and 1,014 -> 838 ms
DECODE_SLAB_VOXELS = 1 << 26
EVAL_CHUNK_POINTS = 1 << 22  # points per evaluation launch
MAX_BRICK_LIST = 1 << 27  # (brick, primitive) entries of one decode slab (512 MiB); more: halves (decode_slab)


@dataclass(frozen=True)
class BinPlan:
    """Cell levels for binning primitives by truncation radius.

    Attributes:
        sizes: Cell edge of each level in voxels, ascending; the last level is one global cell.
        dims: Cells per axis (x, y, z) of each level.
        offsets: First cell id of each level in the concatenated cell arrays.
        total_cells: Number of cells over all levels.
    """

    sizes: tuple[float, ...]
    dims: tuple[tuple[int, ...], ...]
    offsets: tuple[int, ...]
    total_cells: int


def plan_bins(radius: np.ndarray, shape_xyz: tuple[int, ...]) -> BinPlan:
    """Choose cell levels for primitives of the given truncation radii on a grid of ``shape_xyz``.

    One level per occupied power-of-two radius class (classes start at a power of two), its cells
    as large as the largest radius of the class (so a point needs only the 3^3 neighbouring
    cells), coarsened where a level would exceed :data:`MAX_LEVEL_CELLS`. A final global level catches any primitive larger than planned,
    so evaluation stays exact even with a stale plan. :func:`plan_bins_on_device` gives the same
    plan from radii on a device (without reading them back).

    Args:
        radius: Per-primitive truncation radius in voxels (max half-extent of the 5-sigma box).
        shape_xyz: Grid size in voxels; cells tile [-0.5, n - 0.5] on each axis.
    """
    r = np.asarray(radius, dtype=np.float64)
    r = r[np.isfinite(r)]
    if not r.size:
        return _plan_from_classes(1.0, [], shape_xyz)
    # a power of two: the plan then stays the same while radii drift within their octaves, so
    # a refiner re-planning every 100 iterations keeps its tables and its captured graph
    base = 2.0 ** math.floor(math.log2(max(float(r.min()), MIN_CELL)))
    classes = np.unique(np.ceil(np.log2(np.maximum(r, base) / base) - 1e-9).astype(np.int64))
    return _plan_from_classes(base, [int(c) for c in classes], shape_xyz)


def plan_bins_on_device(radius, shape_xyz: tuple[int, ...]) -> BinPlan:
    """:func:`plan_bins` of a Warp array of radii: the least radius and the occupied classes are
    found on its device (two launches, 260 bytes read back instead of 4 bytes a primitive; the
    numpy plan of 1.4M radii took 40-80 ms of host time every re-plan)."""
    wp = warp()
    from ..kernels import field as kf

    dev = radius.device
    n = int(radius.shape[0])
    rmin = wp.full(1, np.inf, dtype=float, device=dev)
    flags = wp.zeros(int(kf.RADIUS_CLASSES), dtype=int, device=dev)
    wp.launch(kf.radius_min, dim=n, inputs=[radius, rmin], device=dev)
    wp.launch(kf.radius_class_flags, dim=n, inputs=[radius, rmin, MIN_CELL], outputs=[flags], device=dev)
    lo = float(rmin.numpy()[0])
    if not math.isfinite(lo):
        return _plan_from_classes(1.0, [], shape_xyz)
    base = 2.0 ** math.floor(math.log2(max(lo, MIN_CELL)))
    return _plan_from_classes(base, [int(c) for c in np.flatnonzero(flags.numpy())], shape_xyz)


def _plan_from_classes(base: float, classes: list[int], shape_xyz: tuple[int, ...]) -> BinPlan:
    """The levels of occupied radius classes ``base`` x 2^c (ascending), then the global level."""
    shape = np.asarray(shape_xyz, dtype=np.float64)
    sizes: list[float] = []
    dims: list[tuple[int, ...]] = []
    for c in classes:
        size = base * 2.0 ** int(c)
        if sizes:
            size = max(size, sizes[-1])
        d = np.maximum(np.ceil(shape / size), 1).astype(np.int64)
        while int(np.prod(d)) > MAX_LEVEL_CELLS:
            size *= 2.0
            d = np.maximum(np.ceil(shape / size), 1).astype(np.int64)
        if sizes and size == sizes[-1]:
            continue
        sizes.append(float(size))
        dims.append((int(d[0]), int(d[1]), int(d[2])))
    return _with_global_level(sizes, dims)


def _with_global_level(sizes: list[float], dims: list[tuple[int, ...]]) -> BinPlan:
    """The plan of these levels followed by the global level (one cell), with the cell offsets."""
    sizes = [*sizes, float(np.finfo(np.float32).max)]
    dims = [*dims, (1, 1, 1)]
    counts = [a * b * c for a, b, c in dims]
    offsets = tuple(int(x) for x in np.concatenate([[0], np.cumsum(counts)[:-1]]))
    return BinPlan(tuple(sizes), tuple(dims), offsets, int(sum(counts)))


def plan_arrays(plan: BinPlan, device: str) -> tuple:
    """(cell edge, cells per axis, first cell id) of each level of ``plan`` as Warp arrays."""
    wp = warp()
    return (
        wp.array(np.asarray(plan.sizes, np.float32), dtype=float, device=device),
        wp.array(np.asarray(plan.dims, np.int32), dtype=wp.vec3i, device=device),
        wp.array(np.asarray(plan.offsets, np.int32), dtype=int, device=device),
    )


POINT_GRID_DIVS = (1, 2, 4, 8, 16)  # a point grid's cell: the level's cell over one of these
MAX_POINT_CELLS = 1 << 22  # cells of one level's point grid (16 MiB of int32 starts)
ROW_COST = 64.0  # cost of visiting one row of point cells, in candidate-point tests (one H200, the forward pass through cell lists on these grids: 64 with LIST_PAD_SHARE 0.1 took the three MRIs at CR 10 / 100 / 1000 in 44.9 s against 53.1 at 16 and 0.25, every row within -0.13..+0.04 dB, results/speed/profile_knobs2_h200.json; H100 before the lists: 16 beat 1 and 4 by 3-6 % and 64 by 24 %, results/kernels/row_cost_h100.json)


def plan_point_grids(plan: BinPlan, n_points: int, shape_xyz: tuple[int, ...], occupied_voxels: int) -> BinPlan:
    """Choose, per primitive level, the cell grid the backward pass bins points on (a
    :class:`BinPlan` of the same levels: the last is one global cell).

    A primitive of level ``l`` (half-extent e <= cell edge S) visits the rows of point cells its
    5-sigma box reaches. Cells of S / d cost (2e / F + 1)^2 rows and about rho (2e + F)^3
    candidate points (F = S / d, rho the points per voxel near primitives): fine cells waste
    fewer candidates, coarse cells fewer rows. This picks the d of
    :data:`POINT_GRID_DIVS` with the least ``ROW_COST`` x rows + candidates, taking e = 0.75 S
    (the middle of a level's radius class). The choice changes the speed, never the pairs.

    Args:
        plan: The primitives' levels.
        n_points: Points evaluated per iteration (samples and partners).
        shape_xyz: Grid size in voxels.
        occupied_voxels: Voxels above the occupancy threshold, where 75 % of the samples fall.
    """
    shape = np.asarray(shape_xyz, dtype=np.float64)
    volume = float(np.prod(shape))
    rho = 0.75 * n_points / max(float(occupied_voxels), 1.0) + 0.25 * n_points / volume
    sizes: list[float] = []
    dims: list[tuple[int, ...]] = []
    for s in plan.sizes[:-1]:  # the global level gets one cell below
        e = 0.75 * s
        best = None
        for d in POINT_GRID_DIVS:
            f = s / d
            if d > 1 and f < MIN_CELL:
                break
            n = np.maximum(np.ceil(shape / f), 1)
            if d > 1 and float(np.prod(n)) > MAX_POINT_CELLS:
                break
            reach = np.minimum(2 * e / f + 1, n)
            span = np.minimum(2 * e + f, shape)
            cost = ROW_COST * float(reach[1] * reach[2]) + rho * float(np.prod(span))
            if best is None or cost < best[0]:
                best = (cost, f, tuple(int(v) for v in n))
        assert best is not None  # the first division (1) always counts
        sizes.append(float(best[1]))
        dims.append(best[2])
    return _with_global_level(sizes, dims)


def set_plan(prims, plan: BinPlan, device: str, cell_start=None, cell_end=None) -> None:
    """Give a ``BinnedPrimitives`` the level arrays of ``plan`` and cell tables (zeroed, or given)."""
    wp = warp()
    prims.level_size, prims.level_dims, prims.level_offset = plan_arrays(plan, device)
    for name, table in (("cell_start", cell_start), ("cell_end", cell_end)):
        arr = wp.zeros(plan.total_cells, dtype=int, device=device) if table is None else wp.array(table, dtype=int, device=device)
        setattr(prims, name, arr)


def sort_into_cells(prims, prepared, keys, order, device: str) -> None:
    """Bin prepared primitives on ``prims``' levels, sort them by cell, record each cell's range
    and gather them into ``prims`` in cell order.

    Args:
        prims: ``BinnedPrimitives`` with its plan's arrays (:func:`set_plan`).
        prepared: (mu, rot, inv_s2, ext, radius, a, w, conic) of every primitive, any order.
        keys, order: Scratch of 2 N ints; ``order`` ends as the source index of each sorted slot.
    """
    from ..kernels import field as kf

    wp = warp()
    mu, rot, inv_s2, ext, radius, a, w, conic = prepared
    n = mu.shape[0]
    wp.launch(
        kf.bin_keys,
        dim=n,
        inputs=[mu, radius, prims.level_size, prims.level_dims, prims.level_offset],
        outputs=[keys, order],
        device=device,
    )
    wp.utils.radix_sort_pairs(keys, order, n)
    prims.cell_start.zero_()
    prims.cell_end.zero_()
    wp.launch(kf.cell_ranges, dim=n, inputs=[keys, n], outputs=[prims.cell_start, prims.cell_end], device=device)
    wp.launch(
        kf.gather_sorted,
        dim=n,
        inputs=[order, mu, rot, inv_s2, ext, a, w, conic],
        outputs=[prims.mu, prims.rot, prims.inv_s2, prims.ext, prims.a, prims.w, prims.conic],
        device=device,
    )


def cell_starts(sorted_keys, count: int, counts, start, device: str) -> None:
    """Dense start table of ``count`` cell-sorted entries: ``start[c]`` is the first entry at or
    past cell c (empty cells, at either end or between, hold the next cell's start; ``start[C]``
    is ``count``). ``counts`` and ``start`` hold C + 1 ints; both passes cost O(entries + cells)
    in parallel (a thread per entry filling the empty cells before it took 73 ms an iteration
    with 6,144 points on 20M point cells, interface 1024^3 on an H100)."""
    from ..kernels import field as kf

    wp = warp()
    counts.zero_()
    if count > 0:
        wp.launch(kf.count_keys, dim=count, inputs=[sorted_keys, count], outputs=[counts], device=device)
    wp.utils.array_scan(counts, start, inclusive=False)


class GaussianField:
    """A primitive set resident on one Warp device, ready for truncation-aware evaluation.

    Args:
        params: (N, 12) float32 parameters, or a Warp ``vec12`` array already on ``device``
            (kept by reference: call :meth:`update` after changing it).
        shape_xyz: The model grid (x, y, z) in voxels; positions are in its voxel units.
        device: Warp device; None picks CUDA when present, else CPU.
        raw: ``params`` are training parameters (weight logit in slot 11, quaternion unnormalised).
    """

    def __init__(self, params, shape_xyz: tuple[int, ...], device: str | None = None, *, raw: bool = False):
        wp = warp()
        from ..kernels import field as kf

        self._wp, self._k = wp, kf
        self.device = resolve_device(device)
        self.raw = raw
        if isinstance(params, wp.array):
            self.params = params
        else:
            params = np.ascontiguousarray(params, dtype=np.float32)
            if params.ndim != 2 or params.shape[1] != 12 or params.shape[0] < 1:
                raise WarpgaussError(f"primitive parameters must have shape (N, 12) with N >= 1, got {params.shape}")
            self.params = wp.array(params, dtype=kf.vec12, device=self.device)
        self.n = int(self.params.shape[0])
        self.shape_xyz = tuple(int(s) for s in shape_xyz)
        n, dev = self.n, self.device
        self.mu = wp.empty(n, dtype=wp.vec3, device=dev)
        self.rot = wp.empty(n, dtype=wp.mat33, device=dev)
        self.inv_s2 = wp.empty(n, dtype=wp.vec3, device=dev)
        self.ext = wp.empty(n, dtype=wp.vec3, device=dev)
        self.radius = wp.empty(n, dtype=float, device=dev)
        self.a = wp.empty(n, dtype=float, device=dev)
        self.w = wp.empty(n, dtype=float, device=dev)
        self.conic = wp.empty(n, dtype=kf.vec6, device=dev)
        self._keys = wp.empty(2 * n, dtype=int, device=dev)
        self.prims = kf.BinnedPrimitives()
        p = self.prims
        p.order = wp.empty(2 * n, dtype=int, device=dev)
        p.mu = wp.empty_like(self.mu)
        p.rot = wp.empty_like(self.rot)
        p.inv_s2 = wp.empty_like(self.inv_s2)
        p.ext = wp.empty_like(self.ext)
        p.a = wp.empty_like(self.a)
        p.w = wp.empty_like(self.w)
        p.conic = wp.empty_like(self.conic)
        self.plan: BinPlan | None = None
        self._active: tuple[Any, float] | None = None  # (brick grid or None: every brick, active share)
        self._decode_bufs: dict = {}  # int scratch of the brick-list decode, kept between slabs
        self._fit_height: dict = {}  # by (scale, offset, nx, ny): a slab height whose lists fit MAX_BRICK_LIST (decode_slab)
        self.decode_listings = 0  # brick listings decode_slab ran (a halved slab lists again)
        self._clamped: Any = None  # [1] int64: decoded voxels clamped into [0, 1] (decode_slab)
        self.update(replan=True)

    def update(self, replan: bool = False) -> None:
        """Re-prepare and re-bin after the parameters changed.

        Args:
            replan: Also re-plan the cell levels from the current radii (reads radii back to the
                host). Without it the old plan is reused, which stays exact thanks to the global
                level, only slower if primitives grew or shrank a lot.
        """
        wp, kf, dev, n = self._wp, self._k, self.device, self.n
        self._active = None  # the activity grid follows the primitives
        wp.launch(
            kf.prepare_primitives,
            dim=n,
            inputs=[self.params, int(self.raw)],
            outputs=[self.mu, self.rot, self.inv_s2, self.ext, self.radius, self.a, self.w, self.conic],
            device=dev,
        )
        prims = self.prims
        if replan or self.plan is None:
            plan = plan_bins_on_device(self.radius, self.shape_xyz)
            if plan != self.plan:
                self.plan = plan
                set_plan(prims, plan, dev)
        prepared = (self.mu, self.rot, self.inv_s2, self.ext, self.radius, self.a, self.w, self.conic)
        sort_into_cells(prims, prepared, self._keys, prims.order, dev)

    def _eval(self, points: np.ndarray, dense: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        wp, kf, dev = self._wp, self._k, self.device
        pts = np.ascontiguousarray(points, dtype=np.float32).reshape(-1, 3)
        m = pts.shape[0]
        value = np.empty(m, np.float32)
        density = np.empty(m, np.float32)
        pairs = np.empty(m, np.int32)
        for a in range(0, m, EVAL_CHUNK_POINTS):
            b = min(m, a + EVAL_CHUNK_POINTS)
            p = wp.array(pts[a:b], dtype=wp.vec3, device=dev)
            v = wp.empty(b - a, dtype=float, device=dev)
            d = wp.empty(b - a, dtype=float, device=dev)
            c = wp.empty(b - a, dtype=int, device=dev)
            if dense:
                inputs = [p, self.mu, self.conic, self.ext, self.a, self.w]
                wp.launch(kf.eval_points_dense, dim=b - a, inputs=inputs, outputs=[v, d, c], device=dev)
            else:
                inputs = [p, self.prims]
                wp.launch(kf.eval_points_binned, dim=b - a, inputs=inputs, outputs=[v, d, c], device=dev)
            value[a:b], density[a:b], pairs[a:b] = v.numpy(), d.numpy(), c.numpy()
        return value, density, pairs

    def evaluate(self, points: np.ndarray) -> np.ndarray:
        """V~ at ``points`` ((M, 3) voxel positions, x,y,z), normalised units, float32."""
        return self._eval(points, dense=False)[0]

    def evaluate_full(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(V~, density rho, contributing pairs) at ``points`` through the binned evaluator."""
        return self._eval(points, dense=False)

    def evaluate_dense(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(V~, rho, pairs) by the all-pairs reference; O(N M), for tests and the self-test only."""
        return self._eval(points, dense=True)

    def iter_slabs(self, shape_xyz: tuple[int, int, int] | None = None, *, box=None):
        """Evaluate V~ at every voxel centre of an output grid spanning the model's extent (or
        ``box``), by z-slabs.

        Output voxel (i, j, k) covers the same extent as the model grid, so its centre sits at
        ((i + 0.5) * scale - 0.5) model voxels with scale = model size / output size per axis.
        A ``box`` ((x0, x1), (y0, y1), (z0, z1)) of model voxel bounds (checked:
        :func:`warpgauss.field.region.check_box`) is sampled the same way over its own extent, starting
        ``offset = x0 / scale`` output voxels in (:func:`warpgauss.field.region.sampling`).

        Yields:
            (z0, slab): first output slice and a (h, ny, nx) float32 array in normalised units.
        """
        from .region import sampling

        wp, dev = self._wp, self.device
        out_shape = tuple(int(s) for s in (shape_xyz or self.shape_xyz))
        if len(out_shape) != 3 or min(out_shape) < 1:
            raise WarpgaussError(f"decode shape must be three positive sizes (x, y, z), got {shape_xyz}")
        nx, ny, nz = out_shape
        scale, offset = sampling(box, out_shape, self.shape_xyz)
        slab = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
        buf = wp.empty((slab, ny, nx), dtype=float, device=dev)
        for z0 in range(0, nz, slab):
            h = min(slab, nz - z0)
            view = buf if h == slab else wp.empty((h, ny, nx), dtype=float, device=dev)
            self.decode_slab(view, z0, wp.vec3(*scale), wp.vec3(*offset))
            yield z0, view.numpy()

    def decode_slab(self, out, z0: int, scale, offset=None) -> None:
        """Evaluate one (h, ny, nx) device slab starting at output slice ``z0`` (no host copy),
        clamped to [0, 1] (the source's value range; :attr:`clamped_voxels` counts the voxels moved).
        ``offset`` (a ``wp.vec3``, None: 0): output voxels before voxel 0 along x, y, z, a
        region's start (:func:`warpgauss.kernels.decode.voxel_coord`).

        Each 8^3 brick lists the primitives whose box meets it, then its voxels stream through
        the list (:mod:`warpgauss.kernels.decode`); one read-back of the list's length per slab.
        A slab whose lists would exceed :data:`MAX_BRICK_LIST` entries is decoded in two halves
        along z, and one a brick high by the cell walk instead (same values); later slabs of the
        same sampling start at the height that fitted, so that their whole listing is not wasted.
        """
        from ..kernels import decode as kd

        wp, dev = self._wp, self.device
        offset = wp.vec3(0.0, 0.0, 0.0) if offset is None else offset
        h, ny, nx = out.shape
        e = int(kd.BRICK_EDGE)
        key = (tuple(scale), tuple(offset), nx, ny)
        fit = self._fit_height.get(key)
        if fit is not None and h > fit:  # an earlier slab of this decode had to be halved: pieces that fit, listed once
            for a in range(0, h, fit):
                self.decode_slab(out[a : min(h, a + fit)], z0 + a, scale, offset)
            return
        self.decode_listings += 1
        bricks = wp.vec3i(-(-nx // e), -(-ny // e), -(-h // e))
        nb = int(bricks[0]) * int(bricks[1]) * int(bricks[2])
        size = wp.vec3i(nx, ny, h)
        counts, ends = self._decode_scratch("counts", nb), self._decode_scratch("ends", nb)
        items = self._decode_scratch("items", 1)
        common = [z0, scale, offset, size, bricks, self.prims]
        wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 0, ends, counts, items], device=dev)
        wp.utils.array_scan(counts[:nb], ends[:nb], inclusive=True)
        total = int(ends[nb - 1 : nb].numpy()[0])
        if total > MAX_BRICK_LIST and h > e:  # halves at a whole brick: shorter lists each
            half = max(e, (h // 2) // e * e)
            self._fit_height[key] = min(half, self._fit_height.get(key, half))
            self.decode_slab(out[:half], z0, scale, offset)
            self.decode_slab(out[half:], z0 + half, scale, offset)
            return
        if total > MAX_BRICK_LIST:
            self.decode_walk(out, z0, scale, offset)
        else:
            self._decode_lists(out, z0, scale, offset, common, ends, counts, nb, bricks, total)
        if self._clamped is None:
            self._clamped = wp.zeros(1, dtype=wp.int64, device=dev)
        wp.launch(kd.clamp_unit, dim=out.shape, inputs=[out], outputs=[self._clamped], device=dev)

    @property
    def clamped_voxels(self) -> int:
        """Decoded voxels clamped into [0, 1] by :meth:`decode_slab` so far (reads back from the device)."""
        return 0 if self._clamped is None else int(self._clamped.numpy()[0])

    def _decode_lists(self, out, z0: int, scale, offset, common, ends, counts, nb: int, bricks, total: int) -> None:
        from ..kernels import decode as kd

        wp, dev = self._wp, self.device
        items = self._decode_scratch("items", max(total, 1))
        wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 1, ends, counts, items], device=dev)
        wp.launch(
            kd.eval_brick_lists,
            dim=nb * int(kd.LIST_THREADS),
            inputs=[z0, scale, offset, bricks, self.prims, ends, counts, items],
            outputs=[out],
            device=dev,
        )

    def predict(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The model in float64 at every voxel centre of its grid, the predictor of a bounded
        residual (:mod:`warpgauss.kernels.predict`: within a few 1e-16 on any device).

        Args:
            params: The (N, 12) parameters this field was built from (their float32 values are
                read exactly into float64).

        Returns:
            ``(values, fragile)``: (nz, ny, nx) float64 V~ clamped to [0, 1], and a bool array
            marking the voxels where devices could disagree (a pair on the 5-sigma cut).
        """
        from ..kernels import decode as kd
        from ..kernels import predict as kp

        wp, dev, n = self._wp, self.device, self.n
        p64 = wp.array(np.asarray(params, np.float32).astype(np.float64), dtype=wp.float64, device=dev)
        mu = wp.empty(n, dtype=wp.vec3d, device=dev)
        rot = wp.empty(n, dtype=wp.mat33d, device=dev)
        inv_s2 = wp.empty(n, dtype=wp.vec3d, device=dev)
        wa = wp.empty(n, dtype=wp.float64, device=dev)
        w = wp.empty(n, dtype=wp.float64, device=dev)
        wp.launch(kp.prepare64, dim=n, inputs=[p64, self.prims.order], outputs=[mu, rot, inv_s2, wa, w], device=dev)
        nx, ny, nz = self.shape_xyz
        values = np.empty((nz, ny, nx), np.float64)
        fragile = np.empty((nz, ny, nx), bool)
        e = int(kd.BRICK_EDGE)
        slab = max(e, min(-(-nz // e) * e, (DECODE_SLAB_VOXELS // (nx * ny * 2)) // e * e))  # whole bricks along z
        scale = wp.vec3(1.0, 1.0, 1.0)
        for z0 in range(0, nz, slab):
            h = min(slab, nz - z0)
            bricks = wp.vec3i(-(-nx // e), -(-ny // e), -(-h // e))
            nb = int(bricks[0]) * int(bricks[1]) * int(bricks[2])
            counts, ends = self._decode_scratch("counts", nb), self._decode_scratch("ends", nb)
            common = [z0, scale, wp.vec3(0.0, 0.0, 0.0), wp.vec3i(nx, ny, h), bricks, self.prims]
            wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 0, ends, counts, self._decode_scratch("items", 1)], device=dev)
            wp.utils.array_scan(counts[:nb], ends[:nb], inclusive=True)
            items = self._decode_scratch("items", max(int(ends[nb - 1 : nb].numpy()[0]), 1))
            wp.launch(kd.list_bricks, dim=nb, inputs=[*common, 1, ends, counts, items], device=dev)
            out = wp.empty((h, ny, nx), dtype=wp.float64, device=dev)
            near = wp.empty((h, ny, nx), dtype=wp.uint8, device=dev)
            wp.launch(
                kp.predict_lists,
                dim=(h, ny, nx),
                inputs=[z0, bricks, ends, counts, items, mu, rot, inv_s2, wa, w],
                outputs=[out, near],
                device=dev,
            )
            values[z0 : z0 + h] = out.numpy()
            fragile[z0 : z0 + h] = near.numpy().astype(bool)
        return values, fragile

    def _decode_scratch(self, name: str, n: int):
        """A device int buffer of at least n entries kept between slabs (grown by half again)."""
        bufs = self._decode_bufs
        buf = bufs.get(name)
        if buf is None or buf.shape[0] < n:
            buf = self._wp.empty(max(n, 3 * (buf.shape[0] if buf is not None else 0) // 2), dtype=int, device=self.device)
            bufs[name] = buf
        return buf

    def decode_walk(self, out, z0: int, scale, offset=None) -> None:
        """Evaluate a slab by the binned cell walk, skipping bricks no primitive reaches."""
        from ..kernels import decode as kd

        offset = self._wp.vec3(0.0, 0.0, 0.0) if offset is None else offset
        active = self.active_bricks()
        use = active is not None
        if not use:
            active = self._wp.ones((1, 1, 1), dtype=self._wp.uint8, device=self.device)
        h, ny, nx = out.shape
        self._wp.launch(
            kd.eval_grid_blocked,
            dim=kd.blocked_threads(h, ny, nx),
            inputs=[z0, scale, offset, self.prims, active, int(use)],
            outputs=[out],
            device=self.device,
        )

    def active_bricks(self):
        """8^3-voxel bricks of the model grid that some primitive's 5-sigma box reaches (a Warp
        uint8 array), or None when a primitive is too large to mark (then every brick counts).

        Decoding writes 0 without evaluation elsewhere: exactly the model's value there.
        """
        if self._active is not None:
            return self._active[0]
        from ..kernels import decode as kd

        wp, dev = self._wp, self.device
        b = int(kd.BRICK_EDGE)
        nx, ny, nz = self.shape_xyz
        active = wp.zeros((-(-nz // b), -(-ny // b), -(-nx // b)), dtype=wp.uint8, device=dev)
        everything = wp.zeros(1, dtype=int, device=dev)
        wp.launch(kd.mark_bricks, dim=self.n, inputs=[self.mu, self.ext], outputs=[active, everything], device=dev)
        if int(everything.numpy()[0]):
            self._active = (None, 1.0)
        else:
            self._active = (active, float(active.numpy().mean()))
        return self._active[0]

    @property
    def active_fraction(self) -> float:
        """Share of the model grid's bricks a decode evaluates (1.0 when every brick does)."""
        self.active_bricks()
        assert self._active is not None  # active_bricks() set it
        return self._active[1]

    def decode(
        self,
        shape_xyz: tuple[int, int, int] | None = None,
        *,
        box=None,
        progress: Callable[[int, int], None] | None = None,
    ) -> np.ndarray:
        """The whole output grid of :meth:`iter_slabs` as one (nz, ny, nx) float32 array (normalised).

        Args:
            shape_xyz: Output grid (x, y, z); None for the model grid itself (a box: required).
            box: Evaluate only this region ((x0, x1), (y0, y1), (z0, z1)) of model voxel bounds
                (see :meth:`iter_slabs`); None: the whole extent.
            progress: Called with (slices done, slices total) after each slab.
        """
        if box is not None and shape_xyz is None:
            raise WarpgaussError("a box decode needs its output shape (warpgauss.field.region.box_shape gives the encoded resolution's)")
        nx, ny, nz = tuple(int(s) for s in (shape_xyz or self.shape_xyz))
        result = np.empty((nz, ny, nx), np.float32)
        for z0, slab in self.iter_slabs(shape_xyz, box=box):
            result[z0 : z0 + slab.shape[0]] = slab
            if progress is not None:
                progress(z0 + slab.shape[0], nz)
        return result


def grid_points(shape_xyz: tuple[int, int, int]) -> np.ndarray:
    """All voxel centres of a grid as (nz*ny*nx, 3) float32 positions in C order (x fastest)."""
    nx, ny, nz = shape_xyz
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)
