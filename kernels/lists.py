"""Cell lists: each primitive listed in every point cell its (padded) 5-sigma box reaches (issue #52).

The forward pass of refinement used to visit, for every point, the 3^3 neighbour cells of every
primitive level (cells at least a radius wide): 27 L cell lookups and some 10-40 candidate
primitives for each pair that contributes. Here every primitive is listed once per cell of its
level's point grid (:class:`warpgauss.kernels.chunked.PointGrid`, the grid the backward pass
bins points on) that its box, widened by a margin, reaches. A point then reads one list a level:
the candidates are the primitives whose boxes reach its cell, the transpose of what the backward
pass visits (2-4 candidates a pair).

Lists are built at every re-bin (:func:`list_count`, a scan, :func:`list_fill_entries` (one thread
an entry; :func:`list_fill`, one a slot, writes the same), a stable sort by cell, so a cell lists
its primitives in slot order and sums run in a fixed order) and stay exact
between re-bins because a step that would carry a primitive's box out of its listed cells is
deferred (:func:`warpgauss.kernels.optim.fits_list`), as steps out of reach of a bin cell are.
"""

import warp as wp

from .chunked import PointGrid, box_rows, slot_level
from .field import BinnedPrimitives, add_pair, conic_g, in_box, level_cell, store_sums, vec6
from .indexing import find_brick
from .optim import BIG, cell_faces

wp.set_module_options({"enable_backward": False})


@wp.struct
class CellLists:
    """Primitives by point cell: ``prim[start[c]:start[c + 1]]`` are the slots listed in cell c of
    the point grids (levels' cells numbered as in :class:`PointGrid`), in slot order."""

    start: wp.array(dtype=int)  # [C + 1] first entry of each cell; start[C] = entries
    prim: wp.array(dtype=int)  # [>= entries] slot of each entry, cell order


@wp.kernel
def list_inputs(
    prims: BinnedPrimitives,
    reach: wp.array(dtype=float),  # [N] reach a deferred step asked for (slot order), 0 if none
    pad_share: float,
    pad_voxels: float,
    centre: wp.array(dtype=wp.vec3),  # [N] out: centre of the box each slot is listed with
    half: wp.array(dtype=wp.vec3),  # [N] out: its half-extents
):
    """The box a slot is listed with at a re-bin: its 5-sigma box widened by a share and a margin,
    or by the reach a deferred step asked for, whichever is larger (one thread per slot)."""
    j = wp.tid()
    e = prims.ext[j]
    r = reach[j]
    centre[j] = prims.mu[j]
    half[j] = wp.vec3(
        wp.max(e[0] * (1.0 + pad_share) + pad_voxels, r),
        wp.max(e[1] * (1.0 + pad_share) + pad_voxels, r),
        wp.max(e[2] * (1.0 + pad_share) + pad_voxels, r),
    )


@wp.func
def listed_cells(
    j: int,
    slot_cell: wp.array(dtype=int),
    prims: BinnedPrimitives,
    grid: PointGrid,
    centre: wp.array(dtype=wp.vec3),
    half: wp.array(dtype=wp.vec3),
):
    """(level, first cell, last cell) of slot j's list: the point cells of its level that the union
    of its listing box and its current 5-sigma box reaches (the union changes nothing between
    re-bins, where the current box stays inside the listed cells; it keeps the lists exact when
    the point grids change without a re-bin)."""
    l = slot_level(slot_cell[j], prims.level_offset)
    c = centre[j]
    h = half[j]
    mu = prims.mu[j]
    e = prims.ext[j]
    lo = wp.vec3(wp.min(c[0] - h[0], mu[0] - e[0]), wp.min(c[1] - h[1], mu[1] - e[1]), wp.min(c[2] - h[2], mu[2] - e[2]))
    hi = wp.vec3(wp.max(c[0] + h[0], mu[0] + e[0]), wp.max(c[1] + h[1], mu[1] + e[1]), wp.max(c[2] + h[2], mu[2] + e[2]))
    a, b = box_rows(0.5 * (lo + hi), 0.5 * (hi - lo), l, grid)
    return l, a, b


@wp.kernel
def list_count(
    slot_cell: wp.array(dtype=int),  # [N] primitive cell of each slot
    prims: BinnedPrimitives,
    grid: PointGrid,
    centre: wp.array(dtype=wp.vec3),  # [N] from list_inputs
    half: wp.array(dtype=wp.vec3),  # [N]
    counts: wp.array(dtype=int),  # [N] out: cells each slot is listed in
):
    """Count each slot's listed cells (one thread per slot)."""
    j = wp.tid()
    l, lo, hi = listed_cells(j, slot_cell, prims, grid, centre, half)
    counts[j] = (hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1) * (hi[2] - lo[2] + 1)


@wp.kernel
def list_region(
    slot_cell: wp.array(dtype=int),  # [N]
    prims: BinnedPrimitives,
    grid: PointGrid,
    centre: wp.array(dtype=wp.vec3),  # [N]
    half: wp.array(dtype=wp.vec3),  # [N]
    box_lo: wp.array(dtype=wp.vec3),  # [N] out: lower faces of the listed cells (-BIG at the grid's first)
    box_hi: wp.array(dtype=wp.vec3),  # [N] out: upper faces (+BIG at the last)
):
    """The region each slot's listed cells cover, which its box must not leave before the next
    re-bin (:func:`warpgauss.kernels.optim.fits_list`; one thread per slot)."""
    j = wp.tid()
    l, lo, hi = listed_cells(j, slot_cell, prims, grid, centre, half)
    a, b = cell_faces(lo, hi, grid.size[l], grid.dims[l])
    box_lo[j] = a
    box_hi[j] = b


@wp.kernel
def unlisted_region(box_lo: wp.array(dtype=wp.vec3), box_hi: wp.array(dtype=wp.vec3)):
    """No lists: every slot may go anywhere its bin cell allows."""
    j = wp.tid()
    box_lo[j] = wp.vec3(-BIG, -BIG, -BIG)
    box_hi[j] = wp.vec3(BIG, BIG, BIG)


@wp.kernel
def list_fill(
    slot_cell: wp.array(dtype=int),  # [N]
    prims: BinnedPrimitives,
    grid: PointGrid,
    centre: wp.array(dtype=wp.vec3),  # [N]
    half: wp.array(dtype=wp.vec3),  # [N]
    counts_cum: wp.array(dtype=int),  # [N] inclusive scan of list_count's counts
    keys: wp.array(dtype=int),  # [>= 2 entries] out: point cell of each entry (first entries)
    values: wp.array(dtype=int),  # [>= 2 entries] out: slot of each entry
):
    """Write each slot's (cell, slot) entries, slots in order (one thread per slot): a stable
    sort by cell then lists every cell's primitives in slot order."""
    j = wp.tid()
    l, lo, hi = listed_cells(j, slot_cell, prims, grid, centre, half)
    dims = grid.dims[l]
    k = counts_cum[j] - (hi[2] - lo[2] + 1) * (hi[1] - lo[1] + 1) * (hi[0] - lo[0] + 1)
    for z in range(lo[2], hi[2] + 1):
        for y in range(lo[1], hi[1] + 1):
            first = grid.offset[l] + (z * dims[1] + y) * dims[0]
            for x in range(lo[0], hi[0] + 1):
                keys[k] = first + x
                values[k] = j
                k += 1


@wp.kernel
def list_fill_entries(
    slot_cell: wp.array(dtype=int),  # [N]
    prims: BinnedPrimitives,
    grid: PointGrid,
    centre: wp.array(dtype=wp.vec3),  # [N]
    half: wp.array(dtype=wp.vec3),  # [N]
    counts_cum: wp.array(dtype=int),  # [N] inclusive scan of list_count's counts
    keys: wp.array(dtype=int),  # [>= 2 entries] out: point cell of each entry (first entries)
    values: wp.array(dtype=int),  # [>= 2 entries] out: slot of each entry
):
    """:func:`list_fill` with one thread per entry: its slot by a binary search of the counts'
    prefix sums, its cell from its rank in the slot's box (x fastest), so the same entries in the
    same places. A primitive listed in thousands of cells (a large one at a high ratio) no longer
    holds one thread for all of them."""
    e = wp.tid()
    jr = find_brick(counts_cum, e)  # (the slot whose inclusive count first exceeds e, e's rank in it)
    j = jr[0]
    r = jr[1]
    l, lo, hi = listed_cells(j, slot_cell, prims, grid, centre, half)
    wx = hi[0] - lo[0] + 1
    wy = hi[1] - lo[1] + 1
    x = lo[0] + r % wx
    y = lo[1] + (r / wx) % wy
    z = lo[2] + r / (wx * wy)
    dims = grid.dims[l]
    keys[e] = grid.offset[l] + (z * dims[1] + y) * dims[0] + x
    values[e] = j


@wp.func
def point_cell(p: wp.vec3, l: int, grid: PointGrid) -> int:
    """Id of the level-l point cell holding p (clamped at the grid's faces, as the backward bins it)."""
    dims = grid.dims[l]
    c = level_cell(p, grid.size[l], dims)
    return grid.offset[l] + (c[2] * dims[1] + c[1]) * dims[0] + c[0]


@wp.func
def listed_sums(p: wp.vec3, prims: BinnedPrimitives, grid: PointGrid, lists: CellLists) -> wp.vec3:
    """(numerator, density, contributing pairs) at p over the primitives listed in its cells."""
    s = wp.vec3(0.0, 0.0, 0.0)
    for l in range(grid.size.shape[0]):
        cid = point_cell(p, l, grid)
        for e in range(lists.start[cid], lists.start[cid + 1]):
            s = add_pair(p, prims, lists.prim[e], s)
    return s


@wp.kernel
def eval_points_listed(
    points: wp.array(dtype=wp.vec3),  # [P] query positions
    order: wp.array(dtype=int),  # [>= P] point index of each thread, sorted by level-0 point cell
    prims: BinnedPrimitives,
    grid: PointGrid,
    lists: CellLists,
    value: wp.array(dtype=float),  # [P] out: V~
    density: wp.array(dtype=float),  # [P] out: rho
    pairs: wp.array(dtype=int),  # [P] out: contributing pairs
):
    """V~ and rho at the points through the cell lists (one thread per point; threads of a warp
    mostly share a cell, so they read the same list)."""
    i = order[wp.tid()]
    store_sums(i, listed_sums(points[i], prims, grid, lists), value, density, pairs)


@wp.func
def add_loaded(d: wp.vec3, e: wp.vec3, c: vec6, a: float, w: float, s: wp.vec3) -> wp.vec3:
    """:func:`warpgauss.kernels.field.add_pair` on values already loaded (the same operations in
    the same order, so the same sums bit for bit)."""
    if not in_box(d, e):
        return s
    g = conic_g(d, c)
    if g > 0.0:
        return wp.vec3(s[0] + w * a * g, s[1] + w * g, s[2] + 1.0)
    return s


@wp.func
def listed_sums_2(p: wp.vec3, prims: BinnedPrimitives, grid: PointGrid, lists: CellLists) -> wp.vec3:
    """:func:`listed_sums` two entries at a time: both entries' primitives are loaded before
    either is evaluated (their loads overlap instead of waiting on each other), the sums taken in
    the same order, so the result is the same bit for bit."""
    s = wp.vec3(0.0, 0.0, 0.0)
    for l in range(grid.size.shape[0]):
        cid = point_cell(p, l, grid)
        e = lists.start[cid]
        end = lists.start[cid + 1]
        while e + 1 < end:
            j0 = lists.prim[e]
            j1 = lists.prim[e + 1]
            d0 = p - prims.mu[j0]
            d1 = p - prims.mu[j1]
            x0 = prims.ext[j0]
            x1 = prims.ext[j1]
            c0 = prims.conic[j0]
            c1 = prims.conic[j1]
            a0 = prims.a[j0]
            a1 = prims.a[j1]
            w0 = prims.w[j0]
            w1 = prims.w[j1]
            s = add_loaded(d0, x0, c0, a0, w0, s)
            s = add_loaded(d1, x1, c1, a1, w1, s)
            e += 2
        if e < end:
            s = add_pair(p, prims, lists.prim[e], s)
    return s


@wp.kernel
def eval_points_listed_2(
    points: wp.array(dtype=wp.vec3),  # [P] query positions
    order: wp.array(dtype=int),  # [>= P] point index of each thread, sorted by level-0 point cell
    prims: BinnedPrimitives,
    grid: PointGrid,
    lists: CellLists,
    value: wp.array(dtype=float),  # [P] out: V~
    density: wp.array(dtype=float),  # [P] out: rho
    pairs: wp.array(dtype=int),  # [P] out: contributing pairs
):
    """:func:`eval_points_listed` reading two list entries at a time (:func:`listed_sums_2`)."""
    i = order[wp.tid()]
    store_sums(i, listed_sums_2(points[i], prims, grid, lists), value, density, pairs)


@wp.func
def spread_bits(v: int) -> int:
    """The low 10 bits of v moved to every third bit (one axis of a Morton code)."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


@wp.kernel
def morton_keys(
    points: wp.array(dtype=wp.vec3),  # [>= P]
    inv_cell: float,  # 1 / the edge of the cells the code counts in (voxels; 1,024 cells an axis at most)
    keys: wp.array(dtype=int),  # [>= 2 P] out: Morton code (x lowest) of each point's cell, clamped to 0..1023 an axis
    values: wp.array(dtype=int),  # [>= 2 P] out: point index
):
    """Morton keys of the points (one thread per point): sorted by them, the threads of a warp
    hold points of a compact block, so they share their cells, and lists, on every level (sorted
    by one level's cell ids, row-major, a warp's points spread along x over tens of cells)."""
    i = wp.tid()
    p = points[i]
    qx = wp.clamp(int(wp.floor((p[0] + 0.5) * inv_cell)), 0, 1023)
    qy = wp.clamp(int(wp.floor((p[1] + 0.5) * inv_cell)), 0, 1023)
    qz = wp.clamp(int(wp.floor((p[2] + 0.5) * inv_cell)), 0, 1023)
    keys[i] = spread_bits(qx) | (spread_bits(qy) << 1) | (spread_bits(qz) << 2)
    values[i] = i


@wp.kernel
def gather_reach(perm: wp.array(dtype=int), reach: wp.array(dtype=float), out: wp.array(dtype=float)):
    """out[i] = reach[perm[i]]: a per-slot float from the old slot order into the new at a re-bin
    (a deferred step's reach; the held anchor targets, refine.update.refresh_anchors)."""
    i = wp.tid()
    out[i] = reach[perm[i]]
