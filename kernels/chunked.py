"""The balanced chunk backward pass (paper stage S2's pair gradients, see :mod:`.backward`).

The iteration's points are binned on one :class:`PointGrid` per primitive level, sorted by cell
(:func:`gather_point_state` copies what the pass reads of them into that order). Each primitive's
candidate points are the entries of the grid rows its 5-sigma box reaches: :func:`pair_work`
counts them, :func:`pair_chunks` and :func:`chunk_owner` (or :func:`chunk_owner_search`) split them into chunks, in groups that
share the box's rows; :func:`pair_grad_chunks` sums one chunk per thread in the grid's frame
(K = sum k d and the six entries of D = sum k d d^T, with k = dL/dG G: 11 sums a thread, no
rotation a pair); :func:`reduce_lanes` adds blocks of a group's chunks and :func:`reduce_chunks` a
primitive's blocks in order, and turns K and D into the gradients (:func:`frame_grads`): no
float atomics, bit-identical reruns. :func:`warpgauss.kernels.backward.accumulate_pairs` (one
thread per point scattering through atomics) is its reference.
"""

import warp as wp

from .backward import point_state
from .field import BinnedPrimitives, conic_g, in_box, level_cell, vec6

wp.set_module_options({"enable_backward": False})


@wp.kernel
def gather_point_state(
    order: wp.array(dtype=int),  # [>=K] point index of each sorted (level, point) entry
    points: wp.array(dtype=wp.vec3),  # [P]
    value: wp.array(dtype=float),  # [P] forward V~
    density: wp.array(dtype=float),  # [P] forward rho
    g_value: wp.array(dtype=float),  # [P]
    g_density: wp.array(dtype=float),  # [P]
    pos: wp.array(dtype=wp.vec3),  # [K] out: position of each sorted entry
    state: wp.array(dtype=wp.vec4),  # [K] out: point_state() of each sorted entry
):
    """Copy what the pair pass reads of each point into cell order (one thread per entry)."""
    k = wp.tid()
    i = order[k]
    pos[k] = points[i]
    state[k] = point_state(i, value, density, g_value, g_density)


@wp.struct
class PointGrid:
    """The iteration's points binned on one cell grid per primitive level (see
    :func:`warpgauss.field.gaussians.plan_point_grids`), every (level, point) entry sorted by cell.

    Cells are numbered x fastest within a level and the levels one after the other, so the
    entries of a row of cells (fixed y and z, consecutive x) are one contiguous range of the
    sorted entries: ``[start[first cell], start[last cell + 1])``.
    """

    size: wp.array(dtype=float)  # [L] cell edge of each level's point grid (voxels)
    dims: wp.array(dtype=wp.vec3i)  # [L] cells per axis
    offset: wp.array(dtype=int)  # [L] first cell id of each level
    start: wp.array(dtype=int)  # [C + 1] first sorted entry of each cell; start[C] = entries


@wp.func
def slot_level(cid: int, level_offset: wp.array(dtype=int)) -> int:
    """Level of the primitive cell ``cid`` (levels' cell ids are consecutive)."""
    l = int(0)
    for q in range(1, level_offset.shape[0]):
        if level_offset[q] <= cid:
            l = q
    return l


@wp.func
def box_rows(mu: wp.vec3, e: wp.vec3, l: int, grid: PointGrid):
    """The cells of level ``l``'s point grid that a primitive's 5-sigma box reaches: (first cell,
    last cell) per axis. Every point the primitive contributes to lies in the box, so in one of
    these cells (lookups clamp at the grid's faces, on both sides alike). The box is widened by a
    relative 1e-6 so that float rounding of mu +- e never drops a point on its face.
    """
    size = grid.size[l]
    dims = grid.dims[l]
    lo = wp.vec3i(0, 0, 0)
    hi = wp.vec3i(dims[0] - 1, dims[1] - 1, dims[2] - 1)
    if wp.isfinite(mu[0] + mu[1] + mu[2] + e[0] + e[1] + e[2]):
        pad = wp.vec3(
            1.0e-6 * (wp.abs(mu[0]) + e[0]) + 1.0e-6,
            1.0e-6 * (wp.abs(mu[1]) + e[1]) + 1.0e-6,
            1.0e-6 * (wp.abs(mu[2]) + e[2]) + 1.0e-6,
        )
        lo = level_cell(mu - e - pad, size, dims)
        hi = level_cell(mu + e + pad, size, dims)
    return lo, hi


@wp.func
def row_range(grid: PointGrid, l: int, lo: wp.vec3i, hi: wp.vec3i, y: int, z: int) -> wp.vec2i:
    """[start, end) of the sorted entries in cells lo.x..hi.x of row (y, z) on level l."""
    dims = grid.dims[l]
    first = grid.offset[l] + (z * dims[1] + y) * dims[0]
    return wp.vec2i(grid.start[first + lo[0]], grid.start[first + hi[0] + 1])


@wp.kernel
def pair_work(
    slot_cell: wp.array(dtype=int),  # [N] cell id each sorted slot is binned in
    prims: BinnedPrimitives,
    grid: PointGrid,
    split: int,  # threads a primitive: each counts every split-th row of its box
    work: wp.array(dtype=wp.int64),  # [N] out: candidate points of each slot (entries in its box rows); zeroed before where split > 1
    rows: wp.array(dtype=int),  # [N] out: rows of its box
):
    """Count the candidate points and the rows of each primitive's box (``split`` threads each,
    rows y fastest then z dealt out in turn; integer sums, so the same counts in any order: with
    few primitives a thread each left most of the GPU idle while each walked hundreds of rows)."""
    t = wp.tid()
    j = t / split
    s = t - j * split
    l = slot_level(slot_cell[j], prims.level_offset)
    lo, hi = box_rows(prims.mu[j], prims.ext[j], l, grid)
    ny = hi[1] - lo[1] + 1
    nr = ny * (hi[2] - lo[2] + 1)
    w = wp.int64(0)
    for q in range(s, nr, split):
        z = lo[2] + q / ny
        r = row_range(grid, l, lo, hi, lo[1] + q - (q / ny) * ny, z)
        w += wp.int64(r[1] - r[0])
    if split == 1:
        work[j] = w
    elif w != wp.int64(0):
        wp.atomic_add(work, j, w)
    if s == 0:
        rows[j] = nr


@wp.kernel
def pair_chunks(
    work: wp.array(dtype=wp.int64),  # [N] from pair_work
    work_cum: wp.array(dtype=wp.int64),  # [N] inclusive scan of work
    rows: wp.array(dtype=int),  # [N] from pair_work
    capacity: int,  # chunks the partial buffers hold beyond one per primitive
    min_chunk: int,  # candidates per chunk at least
    max_chunks: int,  # chunks of one primitive at most
    lanes: int,  # chunks a group at least, where a primitive has several groups
    chunks: wp.array(dtype=int),  # [N] out: chunks of each primitive
    groups: wp.array(dtype=int),  # [N] out: groups its chunks form (1 at least; divides chunks)
    chunk_size: wp.array(dtype=int),  # [1] out: candidates per chunk this iteration
):
    """Split each primitive's candidates into chunks of K = max(min_chunk, total / capacity), so
    that sum(chunks) <= N + capacity whatever the load, and at most ``max_chunks`` per primitive
    (larger chunks then; one thread per primitive). The chunks form groups of ``lanes`` or more,
    no more groups than the box has rows (:func:`pair_grad_chunks` gives each group its own
    rows); the count is rounded down to a multiple of the groups."""
    j = wp.tid()
    total = work_cum[work_cum.shape[0] - 1]
    cap = wp.int64(capacity)
    k = wp.max(wp.int64(min_chunk), (total + cap - wp.int64(1)) / cap)
    c = int(wp.min((work[j] + k - wp.int64(1)) / k, wp.int64(max_chunks)))
    g = wp.max(1, wp.min(c / lanes, rows[j]))
    chunks[j] = (c / g) * g
    groups[j] = g
    if j == 0:
        chunk_size[0] = int(k)


@wp.kernel
def chunk_owner(
    chunks: wp.array(dtype=int),  # [N]
    chunk_cum: wp.array(dtype=int),  # [N] inclusive scan of chunks
    owner: wp.array(dtype=int),  # [>= sum chunks] out: slot of each chunk
):
    """Record which slot each chunk belongs to (one thread per slot; chunks are consecutive)."""
    j = wp.tid()
    c = chunks[j]
    base = chunk_cum[j] - c
    for t in range(c):
        owner[base + t] = j


@wp.kernel
def chunk_owner_search(
    chunk_cum: wp.array(dtype=int),  # [N] inclusive scan of chunks
    owner: wp.array(dtype=int),  # [>= sum chunks] out: slot of each chunk
):
    """:func:`chunk_owner` one thread per chunk: the first slot whose inclusive chunk count
    exceeds the chunk's number (a binary search; the same owners). Threads past the chunk count
    return at once."""
    t = wp.tid()
    n = chunk_cum.shape[0]
    if t >= chunk_cum[n - 1]:
        return
    lo = int(0)
    hi = n - 1
    while lo < hi:
        mid = (lo + hi) / 2
        if chunk_cum[mid] > t:
            hi = mid
        else:
            lo = mid + 1
    owner[t] = lo


@wp.func
def frame_grads(s_kd: wp.vec3, s_dd: vec6, R: wp.mat33, inv: wp.vec3):
    """(dL/dmu, dL/dlog-sigma, dL/dR) of one primitive from its pairs' sums K = sum k d and
    D = sum k d d^T (k = dL/dG G; see the module docstring): with y = R^T d,
    sum k R (y / s^2) = Sigma^-1 K, sum k y_k^2 / s_k^2 = (R^T D R)_kk / s_k^2 and
    -sum k d (y / s^2)^T = -D R diag(1 / s^2)."""
    D = wp.mat33(s_dd[0], s_dd[3], s_dd[4], s_dd[3], s_dd[1], s_dd[5], s_dd[4], s_dd[5], s_dd[2])
    Dr = D @ R
    L = wp.diag(inv)
    d_mu = R @ (L @ (wp.transpose(R) @ s_kd))
    RtDR = wp.transpose(R) @ Dr
    d_ls = wp.vec3(RtDR[0, 0] * inv[0], RtDR[1, 1] * inv[1], RtDR[2, 2] * inv[2])
    return d_mu, d_ls, -(Dr @ L)


@wp.func
def chunk_place(
    t: int,
    owner: wp.array(dtype=int),
    chunks: wp.array(dtype=int),
    chunk_cum: wp.array(dtype=int),
    groups: wp.array(dtype=int),
) -> wp.vec4i:
    """(slot, its chunk number, chunks a group, groups) of chunk ``t``; slot -1 past the chunk
    count (pair_chunks laid them out)."""
    if t >= chunk_cum[chunk_cum.shape[0] - 1]:
        return wp.vec4i(-1, 0, 1, 1)
    j = owner[t]
    nc = chunks[j]
    ng = groups[j]
    return wp.vec4i(j, t - (chunk_cum[j] - nc), nc / ng, ng)


def _pair_grad_chunks(
    owner: wp.array(dtype=int),  # [>=T] slot of each chunk
    chunks: wp.array(dtype=int),  # [N] chunks of each slot
    chunk_cum: wp.array(dtype=int),  # [N] inclusive scan of chunks (T = chunk_cum[N - 1])
    groups: wp.array(dtype=int),  # [N] groups of each slot's chunks (pair_chunks)
    slot_cell: wp.array(dtype=int),  # [N]
    prims: BinnedPrimitives,
    grid: PointGrid,
    pos: wp.array(dtype=wp.vec3),  # [K] sorted point positions (gather_point_state)
    state: wp.array(dtype=wp.vec4),  # [K] sorted point states
    order: wp.array(dtype=int),  # [>=K] point index of each sorted entry (for the pair count)
    count_pairs: int,  # 1: add each contributing pair to pairs[point] (tests, self-test)
    pairs: wp.array(dtype=int),  # [P] out (zeroed before when counting)
    part_kd: wp.array(dtype=wp.vec3),  # [>=T] out: partial sum of k d of each chunk
    part_dd: wp.array(dtype=vec6),  # [>=T] out: partial sum of k d d^T (xx, yy, zz, xy, xz, yz)
    part_aw: wp.array(dtype=wp.vec2),  # [>=T] out: (dL/da, dL/dw)
):
    """Partial gradients of one chunk of one primitive's candidate points (one thread per chunk).

    A primitive's C chunks form G groups of L = C / G (:func:`pair_chunks`): group g takes the
    box rows whose number (y fastest, then z) is g modulo G, and its i-th candidate (counting
    along its rows) goes to the group's chunk i mod L. A thread thus reads the cell
    starts of 1/G of the rows, neighbouring threads of a group read neighbouring points, and the
    chunks of a group have the same load within one point. Each partial is stored;
    :func:`reduce_lanes` and :func:`reduce_chunks` add them in chunk order: no atomics,
    bit-identical reruns. Threads past the chunk count return at once.
    """
    t = wp.tid()
    at = chunk_place(t, owner, chunks, chunk_cum, groups)
    j = at[0]
    if j < 0:
        return
    c = at[1]
    nl = at[2]
    ng = at[3]
    grp = c / nl
    lane = c - grp * nl
    l = slot_level(slot_cell[j], prims.level_offset)
    mu = prims.mu[j]
    cq = prims.conic[j]
    e = prims.ext[j]
    a = prims.a[j]
    w = prims.w[j]
    lo, hi = box_rows(mu, e, l, grid)
    s_kd = wp.vec3(0.0, 0.0, 0.0)
    s_dd = vec6(0.0)
    s_a = float(0.0)
    s_w = float(0.0)
    acc = int(0)  # candidates in the group's rows before this one, modulo nl
    ny = hi[1] - lo[1] + 1
    z = lo[2] + grp / ny  # row grp, then every ng-th
    y = lo[1] + grp - (grp / ny) * ny
    for _q in range(grp, ny * (hi[2] - lo[2] + 1), ng):
        r = row_range(grid, l, lo, hi, y, z)
        first = lane - acc
        if first < 0:
            first += nl
        for k in range(r[0] + first, r[1], nl):
            d = pos[k] - mu
            if in_box(d, e):
                g = conic_g(d, cq)
                if g > 0.0:
                    if count_pairs != 0:
                        wp.atomic_add(pairs, order[k], 1)
                    st = state[k]
                    if st[0] != 0.0 or st[1] != 0.0:
                        gl = st[0] * (a - st[3]) / st[2] + st[1]  # dL/dG / w
                        kk = w * gl * g
                        kd = kk * d
                        s_kd += kd
                        s_dd += vec6(kd[0] * d[0], kd[1] * d[1], kd[2] * d[2], kd[0] * d[1], kd[0] * d[2], kd[1] * d[2])
                        s_a += st[0] * w * g / st[2]
                        s_w += g * gl
        acc = (acc + r[1] - r[0]) % nl
        y += ng
        if y > hi[1]:
            dz = (y - lo[1]) / ny
            z += dz
            y -= dz * ny
    part_kd[t] = s_kd
    part_dd[t] = s_dd
    part_aw[t] = wp.vec2(s_a, s_w)


pair_grad_chunks = wp.kernel(_pair_grad_chunks, name="pair_grad_chunks")
# capped at 64 registers a thread on CUDA (passes.BACKWARD_REGISTERS; the pass before the groups
# compiled to 95: 2 blocks of 256 an SM, 25 % occupancy)
pair_grad_chunks_r64 = wp.kernel(_pair_grad_chunks, name="pair_grad_chunks_r64", cuda_max_registers=64)


REDUCE_BLOCK = wp.constant(32)  # chunks reduce_lanes adds in one thread at most


@wp.kernel
def reduce_lanes(
    owner: wp.array(dtype=int),  # [>=T] slot of each chunk
    chunks: wp.array(dtype=int),  # [N]
    chunk_cum: wp.array(dtype=int),  # [N]
    groups: wp.array(dtype=int),  # [N] (pair_chunks)
    part_kd: wp.array(dtype=wp.vec3),  # [>=T] in: chunk partials; out: block partials at each block's first chunk
    part_dd: wp.array(dtype=vec6),
    part_aw: wp.array(dtype=wp.vec2),
):
    """Add each block of REDUCE_BLOCK consecutive chunks of a group (the last block of a group
    may be shorter) in chunk order into the block's first chunk (one thread per chunk; the first
    of each block works)."""
    t = wp.tid()
    at = chunk_place(t, owner, chunks, chunk_cum, groups)
    if at[0] < 0:
        return
    nl = at[2]
    p = at[1] % nl  # place in the group
    if p % REDUCE_BLOCK != 0 or nl - p == 1:
        return
    s_kd = part_kd[t]
    s_dd = part_dd[t]
    s_aw = part_aw[t]
    for u in range(t + 1, t + wp.min(REDUCE_BLOCK, nl - p)):
        s_kd += part_kd[u]
        s_dd += part_dd[u]
        s_aw += part_aw[u]
    part_kd[t] = s_kd
    part_dd[t] = s_dd
    part_aw[t] = s_aw


@wp.kernel
def reduce_chunks(
    chunks: wp.array(dtype=int),  # [N]
    chunk_cum: wp.array(dtype=int),  # [N]
    groups: wp.array(dtype=int),  # [N] (pair_chunks)
    prims: BinnedPrimitives,
    part_kd: wp.array(dtype=wp.vec3),  # [>=T] block partials (reduce_lanes)
    part_dd: wp.array(dtype=vec6),
    part_aw: wp.array(dtype=wp.vec2),
    d_mu: wp.array(dtype=wp.vec3),  # [N] out (cell order, overwritten): dL/dmu
    d_ls: wp.array(dtype=wp.vec3),  # [N] out: dL/dlog-sigma
    d_rot: wp.array(dtype=wp.mat33),  # [N] out: dL/dR
    d_a: wp.array(dtype=float),  # [N] out: dL/da
    d_w: wp.array(dtype=float),  # [N] out: dL/dw (activated weight)
):
    """Sum each primitive's block partials, group by group, in chunk order (one thread per
    primitive; a primitive with no candidate point gets zeros)."""
    j = wp.tid()
    nc = chunks[j]
    base = chunk_cum[j] - nc
    nl = wp.max(nc / groups[j], 1)
    s_kd = wp.vec3(0.0, 0.0, 0.0)
    s_dd = vec6(0.0)
    s_aw = wp.vec2(0.0, 0.0)
    for g0 in range(base, base + nc, nl):
        for t in range(g0, g0 + nl, REDUCE_BLOCK):
            s_kd += part_kd[t]
            s_dd += part_dd[t]
            s_aw += part_aw[t]
    g_mu, g_ls, g_rot = frame_grads(s_kd, s_dd, prims.rot[j], prims.inv_s2[j])
    d_mu[j] = g_mu
    d_ls[j] = g_ls
    d_rot[j] = g_rot
    d_a[j] = s_aw[0]
    d_w[j] = s_aw[1]
