"""Stages "forward" and "backward": the pair passes between the iteration's points and the primitives.

Forward: the points are binned on one point grid per primitive level (the backward pass's grids,
sorted once an iteration for both passes) and each reads, per level, the list of primitives whose
boxes reach its cell (:mod:`warpgauss.kernels.lists`, built at every re-bin); V~, rho and the
contributing pairs, then the loss's per-point gradients. Where the lists would pass
:data:`LIST_MAX_ENTRIES`, and for the split pass, the points visit the 3^3 neighbour bin cells
of every level instead. Backward: the points are binned on one grid per primitive level; every primitive visits the rows
of point cells its 5-sigma box reaches, split into chunks of at least :data:`MIN_CHUNK`
candidates, one thread per chunk, and the chunks' partials are summed per primitive in a fixed
order. No float atomics: reruns are bit-identical.
"""

from __future__ import annotations

import math

import numpy as np

from ...core.warp import warp
from .draw import Sampler
from .state import Primitives

# The chunked backward pass (kernels/chunked.py). One H200, one state after each default encode of
# mni_icbm152 / mean_reg2mean / inia19, pair_grad_chunks at CR 1000 / 100 / 10 against one group a
# primitive, at most 128 chunks of 128 or more (0cbaf1a, the same run): 431 / 542 / 1057 ->
# 156 / 381 / 1036 us, 435 / 851 / 1274 -> 292 / 855 / 1288, 441 / 517 / 1213 -> 217 / 551 / 1179
# (results/speed/iteration_floor_groups_*_h200.json). MIN_CHUNK 32 or 128, MAX_CHUNKS 256 or 1024,
# LANES 16 or 64 and registers as compiled (BACKWARD_REGISTERS 0) were within a few % of these on
# every state, better on some and worse on others (iteration_floor_groups_trial2_*_h200.json)
MIN_CHUNK = 64  # candidate points per chunk at least
MAX_CHUNKS = 512  # chunks of one primitive at most
# chunks that share box rows: a primitive with more chunks splits its rows between groups of at
# least this many (at most one group a row)
LANES = 32
BACKWARD_BLOCK = 256  # threads a block on CUDA (64 and 128 were no faster)
CHUNKS_PER_POINT = 2  # chunks the backward pass may use beyond one per primitive, per point of the iteration
PARTIAL_MAX_ENTRIES = 1 << 24  # (point, neighbour cell) partial sums of the split forward pass (192 MiB)
# points an iteration at most for which the refiner picks the split forward pass by itself
# (RefineConfig.split_cells None, CUDA). One H200, five volumes, N 20,000 and 200,000
# (benchmarks/refine/forward_split.py, results/refine/forward_split_h200.json): the split pass
# steps 1.26-2.15x faster at 16,384 points (8,192 samples and partners), is 0.9-1.4x at 32,768 (1.3-1.4x
# faster at N 200,000, 0.1-0.3 ms slower at N 20,000) and 0.58-0.96x of the point-major pass at
# 65,536, where one thread per point already fills the GPU. Since the smoothness term is off by
# default (no partner points), inia19 evaluates 32,768 points an iteration: there the split pass
# took 3.48 s for a CR 100 encode against 2.40 point-major (N 22,000; 2.46 / 1.82 s at CR 1000;
# results/speed/profile_nosmooth_split_h200.json), so the split pass stops at 16,384
SPLIT_MAX_POINTS = 1 << 14
# between SPLIT_MAX_POINTS and this many points (exclusive) the split pass is kept for at least
# SPLIT_DENSE_PRIMITIVES primitives, whose points each visit more of them: vortex 512^3 on one H200
# at 20,000 samples (40,000 points), N 400,000: split 4.9 ms a step against 6.7; a 2x2x2 brick of
# it (72,218 primitives, 20,089 samples): 3.0 against 3.1 ms, the bricked encode 54.3 s against
# 61.0 (results/bricked/profile_wave_512_split{on,off}_h200.json, one_gpu_512_split*_h200.json)
SPLIT_DENSE_POINTS = 1 << 16
SPLIT_DENSE_PRIMITIVES = 50_000


# cell lists (kernels/lists.py): a primitive is listed with its box widened by this share and these
# voxels, so that the steps of the iterations up to the next re-bin rarely leave its listed cells
# (a step that would is deferred to the re-bin, as one that leaves its bin cell's reach is)
LIST_PAD_SHARE = 0.1  # one H200, three MRIs at CR 10 / 100 / 1000: 0.1 took 49.1 s against 53.1 at 0.25 (with ROW_COST 64: 44.9), profile_knobs2_h200.json
# LIST_PAD_VOXELS 0: the same dB (-0.02..+0.07) and encodes 0.92-1.03x, within the runs' spread
# (one H200, three MRIs at CR 10 / 100 / 1000, results/accuracy/sweep_rc_pad_mri_h200.json)
LIST_PAD_VOXELS = 1.0
LIST_MAX_ENTRIES = 1 << 26  # (cell, primitive) entries at most (4 int32 arrays: 1 GiB); beyond, no lists
LIST_HEADROOM = 1.25  # list arrays are allocated this much larger than needed (fewer re-captures)
# list entries the forward pass loads at a time (1 or 2: the same sums bit for bit, see
# kernels.lists.listed_sums_2). One H200, default encodes of the three MRIs at CR 100 and 10
# (results/speed/profile_unroll_h200.json, profile_unroll4_h200.json): the listed forward took
# 0.51 -> 0.45 s, 1.92 -> 1.77, 0.91 -> 0.65, 2.90 -> 1.85 s (mni_icbm152, inia19 at CR 100, 10);
# four at a time gained at CR 100 (0.41, 0.55 s) and lost at CR 10 (mean_reg2mean 2.40 -> 2.51 s),
# and the backward pass two candidates at a time lost 6-18 % (more registers than its 95): dropped
FORWARD_UNROLL = 2
# the listed forward visits the points in the Morton order of their voxels (1) or by their level-0
# point cell (0, the backward pass's sort) where the lists hold at least MORTON_MIN_ENTRIES entries
# a point: the same sums bit for bit (a point's sums do not depend on the order). By cell, ncu at
# mni_icbm152 CR 10 found 16.6 of 32 lanes active an instruction (a warp's points spread over tens
# of cells a level; results/speed/ncu_eval_points_listed_mni10_h200.txt). One H200, one state after
# each default encode of the three MRIs (results/speed/iteration_floor_morton2_h200.json), kernels
# of an iteration by cell -> Morton, us, at list entries a point: CR 10 mni 2,638 -> 2,146 (39),
# mean_reg2mean 3,594 -> 2,845 (95), inia19 2,895 -> 2,512 (101), the forward 1,296 -> 758,
# 1,844 -> 1,045, 1,395 -> 966; CR 100 950 -> 976 (13), 1,842 -> 1,783 (16), 1,199 -> 1,199 (28);
# CR 1000 +46..+59 (4-14): the sort costs some 45 us, the short lists gain nothing
FORWARD_MORTON = 1
MORTON_MIN_ENTRIES = 32.0
# Tried and dropped (one H200, three MRIs at CR 10 / 100 / 1000, results/accuracy/sweep_xdiv_*_h200.json,
# results/speed/iteration_floor_spans_h200.json, commit 213440b): each backward row narrowed to the
# ellipsoid's x-range over the row (per-row Schur-complement bounds) and point cells 4x finer along x
# cut the candidates by a third (backward) and 8-25 % (forward) on saved models
# (results/speed/pair_counts_xdiv_cpu.json), but refinement took 1.15-1.64x as long: pair_grad_chunks
# 156 -> 375 us at mni CR 1000, pair_work 36 -> 141 us (the per-row arithmetic), and the listed
# forward 1360 -> 1478 us at mni CR 10 (a warp's points spread over more cells)
# Tried and dropped: one block of 32 lanes a primitive where N >= half the points (tile reductions
# of the 11 sums, no partials; c18b74f). One H200, default encodes at CR 10, same run against the
# chunks (results/accuracy/sweep_tiles_mri_h200.json): refinement 6.74 / 3.97 / 6.38 s against
# 5.62 / 3.88 / 5.58 (mean_reg2mean, mni_icbm152, inia19), PSNR within 0.04 dB
# registers a thread of the chunked backward may use on CUDA (0: as compiled, 95). One H200, `bench
# kernels` rows (results/speed/bench_backward_registers_h200.json): 64 took 1.13 / 10.18 / 3.89 /
# 29.18 ms at 20K x 65,536 / 20K x 1M / 1.4M x 65,536 / 1.4M x 1M against 1.13 / 11.52 / 4.31 /
# 32.26 as compiled; 48 spilled (1.21 / 10.86 / 4.16 / 31.15)
BACKWARD_REGISTERS = 64
# below WORK_SPLIT_BELOW primitives the backward pass's candidate count (kernels.chunked.pair_work)
# takes WORK_SPLIT threads a primitive, each every WORK_SPLIT-th row of its box (1: one thread a
# primitive), and where the chunk capacity is OWNER_SEARCH_SLOTS or more chunks a primitive the
# chunks find their primitive by a binary search (chunked.chunk_owner_search), one thread a chunk,
# rather than each primitive writing its chunks' owners in turn: the same counts and owners.
# With few large primitives (high ratios) one thread a primitive left most of the GPU idle: at mni_icbm152
# CR 1000 (N 919, 120,416 chunks) pair_work took 36 us and chunk_owner 48 of a 552 us iteration
# (one H200, results/speed/iteration_floor_groups_mni_icbm152_h200.json)
WORK_SPLIT = 8
WORK_SPLIT_BELOW = 1 << 16
OWNER_SEARCH_SLOTS = 4


def picks_split(cuda: bool, n_points: int, n_primitives: int = 0, dense_rule: bool = True) -> bool:
    """The forward pass ``RefineConfig.split_cells`` None picks: split on CUDA up to
    :data:`SPLIT_MAX_POINTS` points an iteration, and (``dense_rule``; a refiner stepping beside
    others drops it, ``Refiner(split_dense=False)``) below :data:`SPLIT_DENSE_POINTS` for :data:`SPLIT_DENSE_PRIMITIVES` primitives or more;
    point-major otherwise."""
    n_points = int(n_points)
    dense = dense_rule and n_points < SPLIT_DENSE_POINTS and int(n_primitives) >= SPLIT_DENSE_PRIMITIVES
    return bool(cuda) and (n_points <= SPLIT_MAX_POINTS or dense)


def chunk_capacity(n_points: int) -> int:
    """Chunks the backward pass may use beyond one per primitive: :data:`CHUNKS_PER_POINT` a point,
    enough for chunks of :data:`MIN_CHUNK` at :data:`MIN_CHUNK` x :data:`CHUNKS_PER_POINT`
    candidates per point, at most 2^21 (then chunks grow)."""
    return max(1024, min(1 << 21, int(CHUNKS_PER_POINT * int(n_points))))


class PairPasses:
    """Forward and backward pair passes over a sampler's points and a primitive state.

    Args:
        state: The primitives (slot order, binned).
        sampler: Where the points, targets and sample weights come from.
        shape_xyz: The model grid.
        split: Forward with one thread per (point, neighbour cell), partials summed in a fixed order.
        partners: Evaluate the partner points too (the smoothness term needs them).
    """

    def __init__(self, state: Primitives, sampler: Sampler, shape_xyz: tuple[int, int, int], split: bool, partners: bool):
        self._wp = warp()
        self.state, self.sampler, self.shape_xyz = state, sampler, shape_xyz
        self.device = state.device
        self.split, self.partners = bool(split), bool(partners)
        self._buf: dict | None = None
        self.lists = True  # forward through cell lists where they fit (False: the 3^3 bin-cell walk)
        n = state.n
        self.list_centre = self._wp.zeros(n, dtype=self._wp.vec3, device=self.device)  # listing boxes (slot order)
        self.list_half = self._wp.zeros(n, dtype=self._wp.vec3, device=self.device)
        self._list_counts = self._wp.zeros(n, dtype=int, device=self.device)
        self._list_cum = self._wp.zeros(n, dtype=int, device=self.device)
        self._list_keys = None  # [2 capacity] sort keys (point cell), then values (slot): CellLists.prim
        self._list_values = None
        self._inputs_ready = False  # list_centre / list_half hold a listing (set by relist or restore)
        self.listed = False  # the forward pass reads the lists (set when they are indexed)
        self.list_entries = 0
        self._sorted: int | None = None  # points sorted on the point grids this iteration (forward -> backward)

    @property
    def m(self) -> int:
        return self.sampler.m

    @property
    def n_points(self) -> int:
        """Points evaluated per iteration: the samples and, for the smoothness term, their partners."""
        return 2 * self.m if self.partners else self.m

    def resize(self) -> None:
        """(Re)allocate the per-point buffers for the sampler's sample count."""
        wp, dev, m = self._wp, self.device, self.m
        self.value, self.density, self.g_value, self.g_density = (wp.zeros(2 * m, dtype=float, device=dev) for _ in range(4))
        self.pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.back_pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.point_loss = wp.zeros(m, dtype=wp.vec3, device=dev)
        self._buf = None

    def invalidate(self) -> None:
        """Drop the buffers sized by the plan, the point count or the pass kind (re-made on use)."""
        self._buf = None
        self._sorted = None

    def points_changed(self) -> None:
        """New points were drawn: the backward pass sorts them unless a forward pass does first."""
        self._sorted = None

    def use_partials(self) -> bool:
        return self.split and self.n_points * 27 * len(self.state.binned.sizes) <= PARTIAL_MAX_ENTRIES

    def buffers(self) -> dict:
        """Buffers that bin the points of an iteration on every level's point grid and split the
        pair pass into chunks (allocated outside any graph capture; the sort's scratch is
        reserved for the largest sort this pass runs)."""
        if self._buf is None:
            from ...field.gaussians import plan_arrays, plan_point_grids
            from ...kernels import chunked as kc
            from ...kernels import field as kf

            wp, dev, n, plan = self._wp, self.device, self.state.n, self.state.binned
            levels, p2 = len(plan.sizes), self.n_points
            k = levels * p2
            gp = plan_point_grids(plan, p2, self.shape_xyz, self.sampler.n_high + self.sampler.n_mid)
            grid = kc.PointGrid()
            grid.size, grid.dims, grid.offset = plan_arrays(gp, dev)
            grid.start = wp.zeros(gp.total_cells + 1, dtype=int, device=dev)
            cap = chunk_capacity(p2)
            slots = n + cap  # chunks at most (kernels.chunked.pair_chunks)
            b = {
                "grid_plan": gp,
                "grid": grid,
                "cell_counts": wp.zeros(gp.total_cells + 1, dtype=int, device=dev),
                "keys": wp.empty(2 * k, dtype=int, device=dev),
                "order": wp.empty(2 * k, dtype=int, device=dev),
                "fkeys": wp.empty(2 * p2, dtype=int, device=dev),
                "forder": wp.empty(2 * p2, dtype=int, device=dev),
                "pos": wp.empty(k, dtype=wp.vec3, device=dev),
                "state": wp.empty(k, dtype=wp.vec4, device=dev),
                "part": wp.empty((p2, 27 * levels), dtype=wp.vec3, device=dev) if self.use_partials() else None,
                "capacity": cap,
                "work": wp.empty(n, dtype=wp.int64, device=dev),
                "work_cum": wp.empty(n, dtype=wp.int64, device=dev),
                "rows": wp.empty(n, dtype=int, device=dev),
                "chunks": wp.empty(n, dtype=int, device=dev),
                "groups": wp.empty(n, dtype=int, device=dev),
                "chunk_cum": wp.empty(n, dtype=int, device=dev),
                "chunk_size": wp.zeros(1, dtype=int, device=dev),
                "owner": wp.empty(slots, dtype=int, device=dev),
                "slots": slots,
                "parts": (
                    wp.empty(slots, dtype=wp.vec3, device=dev),
                    wp.empty(slots, dtype=kf.vec6, device=dev),
                    wp.empty(slots, dtype=wp.vec2, device=dev),
                ),
            }
            # CUB keeps one scratch buffer per context and re-allocates it for a larger sort: sort
            # the largest count now, so that a captured graph never refers to a freed buffer
            big = max(k, n)
            scratch = [wp.zeros(2 * big, dtype=int, device=dev) for _ in range(2)]
            wp.utils.radix_sort_pairs(scratch[0], scratch[1], big)
            self._buf = b
            if self._inputs_ready:
                self.index_lists()
        return self._buf

    def list_inputs_from_state(self) -> None:
        """Set every slot's listing box from the primitives as they stand (at a re-bin: the
        state's ``reach_listed`` holds the reach deferred steps asked for, in the new slot order)."""
        from ...kernels import lists as kl

        st = self.state
        self._wp.launch(
            kl.list_inputs,
            dim=st.n,
            inputs=[st.prims, st.reach_listed, LIST_PAD_SHARE, LIST_PAD_VOXELS],
            outputs=[self.list_centre, self.list_half],
            device=self.device,
        )
        self._inputs_ready = True

    def lists_restored(self) -> None:
        """The listing boxes were restored (a checkpoint): index them with the next buffers."""
        self._inputs_ready = True
        self.invalidate()

    def relist(self) -> bool:
        """List the primitives anew after a re-bin; returns whether arrays a captured iteration
        refers to changed (new list arrays, or lists switched on or off)."""
        self.list_inputs_from_state()
        if self._buf is None:
            return True  # indexed when the buffers are made, before any capture
        return self.index_lists()

    def index_lists(self) -> bool:
        """Index the listing boxes on the current point grids: counts, a scan, the (cell, slot)
        entries, a stable sort by cell and the cell start table, and the region each slot must stay
        in (syncs once, for the entry count). Returns whether arrays a captured iteration refers
        to changed."""
        from ...field.gaussians import cell_starts
        from ...kernels import lists as kl

        wp, dev, st, b = self._wp, self.device, self.state, self._buf
        assert b is not None
        was = (self.listed, self._list_keys, self.morton())
        grid = b["grid"]
        args = [st.slot_cell, st.prims, grid, self.list_centre, self.list_half]
        n = st.n
        total = 0
        if self.lists:
            wp.launch(kl.list_count, dim=n, inputs=args, outputs=[self._list_counts], device=dev)
            wp.utils.array_scan(self._list_counts, self._list_cum, inclusive=True)
            total = int(self._list_cum[n - 1 :].numpy()[0]) if n else 0
        self.list_entries = total
        if not self.lists or total > LIST_MAX_ENTRIES:
            wp.launch(kl.unlisted_region, dim=n, inputs=[st.bounds.box_lo, st.bounds.box_hi], device=dev)
            self.listed = False
            return was[0] != self.listed or was[2] != self.morton()
        if self._list_keys is None or self._list_keys.shape[0] < 2 * max(total, 1):
            cap = max(1024, int(LIST_HEADROOM * total))
            self._list_keys = wp.empty(2 * cap, dtype=int, device=dev)
            self._list_values = wp.empty(2 * cap, dtype=int, device=dev)
            wp.utils.radix_sort_pairs(self._list_keys, self._list_values, cap)  # CUB's scratch for the largest sort, before any capture
            b["list_start"] = None
        if b.get("list_start") is None:
            b["list_start"] = wp.zeros(b["grid_plan"].total_cells + 1, dtype=int, device=dev)
        # one thread an entry (list_fill, one a slot, writes the same: at CR 1000 one slot's thread
        # wrote thousands, 0.5 ms of a 0.7 ms re-bin on one H200, inia19;
        # results/speed/iteration_floor_rowshare_h200.json)
        wp.launch(kl.list_fill_entries, dim=total, inputs=[*args, self._list_cum], outputs=[self._list_keys, self._list_values], device=dev)
        cells = b["grid_plan"].total_cells
        wp.utils.radix_sort_pairs(self._list_keys, self._list_values, total, 0, max(1, (cells - 1).bit_length()))
        cell_starts(self._list_keys, total, b["cell_counts"], b["list_start"], dev)
        wp.launch(kl.list_region, dim=n, inputs=args, outputs=[st.bounds.box_lo, st.bounds.box_hi], device=dev)
        cl = kl.CellLists()
        cl.start, cl.prim = b["list_start"], self._list_values
        b["lists"] = cl
        self.listed = True
        return was[0] != self.listed or was[1] is not self._list_keys or was[2] != self.morton()

    def sort_points(self, count: int) -> None:
        """Bin the first ``count`` points on every level's point grid and sort them by cell
        (stable: the order within a cell is the point index, so the pair pass sums in a fixed
        order), with the dense cell start table."""
        from ...field.gaussians import cell_starts
        from ...kernels import field as kf

        wp, dev, b = self._wp, self.device, self.buffers()
        grid, cells = b["grid"], b["grid_plan"].total_cells
        k = len(self.state.binned.sizes) * count
        wp.launch(
            kf.point_keys,
            dim=k,
            inputs=[self.sampler.points, count, grid.size, grid.dims, grid.offset],
            outputs=[b["keys"], b["order"]],
            device=dev,
        )
        wp.utils.radix_sort_pairs(b["keys"], b["order"], k, 0, max(1, (cells - 1).bit_length()))
        cell_starts(b["keys"], k, b["cell_counts"], grid.start, dev)

    def order_points(self, count: int) -> None:
        """Sort the first ``count`` points by their cell on the primitives' first level (stable),
        the order the forward pass visits them in: neighbouring threads then share a cell, and
        so the same candidate ranges on every level (the levels' cells nest)."""
        from ...kernels import field as kf

        wp, dev, p, b = self._wp, self.device, self.state.prims, self.buffers()
        wp.launch(
            kf.point_keys,
            dim=count,
            inputs=[self.sampler.points, count, p.level_size, p.level_dims, p.level_offset],
            outputs=[b["fkeys"], b["forder"]],
            device=dev,
        )
        wp.utils.radix_sort_pairs(b["fkeys"], b["forder"], count, 0, max(1, (self.state.binned.total_cells - 1).bit_length()))

    def morton(self) -> bool:
        """Whether the listed forward visits the points in Morton order (long lists only)."""
        return bool(FORWARD_MORTON) and self.list_entries >= MORTON_MIN_ENTRIES * self.n_points

    def morton_order(self, count: int) -> None:
        """Sort the first ``count`` points by the Morton code of their voxel (cells of a voxel,
        coarser past 1,024 voxels an axis; stable, so ties keep the point order) into the
        buffers' ``forder``."""
        from ...kernels import lists as kl

        wp, dev, b = self._wp, self.device, self.buffers()
        cell = max(1.0, max(self.shape_xyz) / 1024.0)
        # bits an axis for the cells in the grid (a point past the grid may set a higher bit, which
        # the sort ignores: it lands out of place, which costs only speed)
        bits = max(1, math.ceil(math.log2(math.ceil(max(self.shape_xyz) / cell))))
        wp.launch(kl.morton_keys, dim=count, inputs=[self.sampler.points, 1.0 / cell], outputs=[b["fkeys"], b["forder"]], device=dev)
        wp.utils.radix_sort_pairs(b["fkeys"], b["forder"], count, 0, 3 * bits)

    def forward(self, value_empty: float, density_weight: float, now) -> None:
        """Order the points by cell, evaluate V~ and rho at them, and the per-point loss gradients
        (``now``: the device's per-iteration scalars, see :class:`.schedule.Schedule`)."""
        from ...kernels import backward as kb
        from ...kernels import field as kf

        wp, dev, m2, s = self._wp, self.device, self.n_points, self.sampler
        b = self.buffers()
        prims = self.state.prims
        if self.listed and not self.use_partials():
            from ...kernels import lists as kl

            self.sort_points(m2)  # the backward pass reads the same sort
            self._sorted = m2
            order = b["order"]  # by level-0 point cell
            if self.morton():
                self.morton_order(m2)
                order = b["forder"]
            wp.launch(
                kl.eval_points_listed_2 if FORWARD_UNROLL == 2 else kl.eval_points_listed,
                dim=m2,
                inputs=[s.points, order, prims, b["grid"], b["lists"]],
                outputs=[self.value, self.density, self.pairs],
                device=dev,
            )
        elif self.use_partials():
            self.order_points(m2)
            order = b["forder"]
            wp.launch(kf.eval_points_partial, dim=b["part"].shape, inputs=[s.points, order, prims], outputs=[b["part"]], device=dev)
            wp.launch(kf.finish_partials, dim=m2, inputs=[order, b["part"]], outputs=[self.value, self.density, self.pairs], device=dev)
        else:
            self.order_points(m2)
            wp.launch(
                kf.eval_points_ordered,
                dim=m2,
                inputs=[s.points, b["forder"], prims],
                outputs=[self.value, self.density, self.pairs],
                device=dev,
            )
        wp.launch(
            kb.point_grads,
            dim=self.m,
            inputs=[self.value, self.density, s.target, s.weight, s.occupied, self.m, value_empty, density_weight, now],
            outputs=[self.g_value, self.g_density, self.point_loss],
            device=dev,
        )

    def backward(self, count: int | None = None, count_pairs: bool = False) -> None:
        """Primitive-major pair pass over the first ``count`` points (all by default), balanced
        by chunks: overwrites the pair-gradient buffers, no float atomics (bit-identical reruns).

        Each primitive's candidate points are the point-grid rows its 5-sigma box reaches; they
        are split into chunks of at least :data:`MIN_CHUNK` candidates (more when the load
        exceeds the chunk capacity), one thread per chunk, and the chunks' partial gradients are
        summed per primitive in chunk order. The cost follows the candidates, not the largest
        primitive's point count.
        """
        from ...kernels import chunked as kc

        wp, dev, b, st = self._wp, self.device, self.buffers(), self.state
        n = st.n
        count = self.n_points if count is None else int(count)
        if self._sorted != count:  # the forward pass sorted these points already
            self.sort_points(count)
        self._sorted = None
        k = len(st.binned.sizes) * count
        wp.launch(
            kc.gather_point_state,
            dim=k,
            inputs=[b["order"], self.sampler.points, self.value, self.density, self.g_value, self.g_density],
            outputs=[b["pos"], b["state"]],
            device=dev,
        )
        if count_pairs:
            self.back_pairs.zero_()
        grid, cap = b["grid"], b["capacity"]
        split = WORK_SPLIT if n < WORK_SPLIT_BELOW else 1
        if split > 1:
            b["work"].zero_()
        wp.launch(kc.pair_work, dim=n * split, inputs=[st.slot_cell, st.prims, grid, split], outputs=[b["work"], b["rows"]], device=dev)
        wp.utils.array_scan(b["work"], b["work_cum"], inclusive=True)
        wp.launch(
            kc.pair_chunks,
            dim=n,
            inputs=[b["work"], b["work_cum"], b["rows"], cap, MIN_CHUNK, MAX_CHUNKS, LANES],
            outputs=[b["chunks"], b["groups"], b["chunk_size"]],
            device=dev,
        )
        wp.utils.array_scan(b["chunks"], b["chunk_cum"], inclusive=True)
        if b["slots"] >= OWNER_SEARCH_SLOTS * n:
            wp.launch(kc.chunk_owner_search, dim=b["slots"], inputs=[b["chunk_cum"]], outputs=[b["owner"]], device=dev)
        else:
            wp.launch(kc.chunk_owner, dim=n, inputs=[b["chunks"], b["chunk_cum"]], outputs=[b["owner"]], device=dev)
        wp.launch(
            kc.pair_grad_chunks_r64 if BACKWARD_REGISTERS == 64 else kc.pair_grad_chunks,
            dim=b["slots"],
            inputs=[
                b["owner"],
                b["chunks"],
                b["chunk_cum"],
                b["groups"],
                st.slot_cell,
                st.prims,
                grid,
                b["pos"],
                b["state"],
                b["order"],
                int(count_pairs),
            ],
            outputs=[self.back_pairs, *b["parts"]],
            device=dev,
            block_dim=BACKWARD_BLOCK,
        )
        wp.launch(kc.reduce_lanes, dim=b["slots"], inputs=[b["owner"], b["chunks"], b["chunk_cum"], b["groups"], *b["parts"]], device=dev)
        wp.launch(
            kc.reduce_chunks,
            dim=n,
            inputs=[b["chunks"], b["chunk_cum"], b["groups"], st.prims, *b["parts"]],
            outputs=list(st.pair_grads),
            device=dev,
        )
        st.clean = False

    def values_at(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(V~, rho) of the current state at any ``points`` (volume coordinates, (M, 3)), through
        the binned primitives, one thread a point; nothing of the iteration's buffers changes
        (the re-plan's cut reads the model at the primitives' centres this way, without a second
        copy of the model on the device)."""
        from ...kernels import field as kf

        wp, dev = self._wp, self.device
        pts = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
        m = pts.shape[0]
        value = wp.empty(m, dtype=float, device=dev)
        density = wp.empty(m, dtype=float, device=dev)
        pairs = wp.empty(m, dtype=int, device=dev)
        if m:
            at = wp.array(pts, dtype=wp.vec3, device=dev)
            wp.launch(kf.eval_points_binned, dim=m, inputs=[at, self.state.prims], outputs=[value, density, pairs], device=dev)
        return value.numpy(), density.numpy()

    def atomic_pairs(self, kernel, count: int) -> None:
        """A point-major pair kernel (float atomics; the references of tests and the self-test)."""
        st = self.state
        self._wp.launch(
            kernel,
            dim=count,
            inputs=[self.sampler.points, self.value, self.density, self.g_value, self.g_density, st.prims],
            outputs=[*st.pair_grads, self.back_pairs],
            device=self.device,
        )
        st.clean = False

    def stats(self) -> dict:
        """The last backward pass's load (syncs): candidate points, chunks and chunk size, and
        the point grids' cell edges."""
        b, n = self.buffers(), self.state.n
        return {
            "candidates": int(b["work_cum"][n - 1 :].numpy()[0]),
            "chunks": int(b["chunk_cum"][n - 1 :].numpy()[0]),
            "chunk_size": int(b["chunk_size"].numpy()[0]),
            "chunk_capacity": b["slots"],
            "point_cells": list(b["grid_plan"].sizes[:-1]),
            "list_entries": self.list_entries,
        }
