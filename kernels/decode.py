"""Grid decode, brick by brick: each 8^3 brick of output voxels lists once the primitives whose
5-sigma box reaches it, and its voxels stream through that list.

A voxel of the binned evaluator (:func:`warpgauss.kernels.field.binned_sums`) walks 27 cells on
every level, and the threads of one warp walk different cells; about six candidates are tested per
contributing pair. A brick list holds only the primitives whose box meets the brick (for boxes
a few bricks wide, 1.5-3 candidates per pair), every thread of a brick walks the same list (no
divergence, each primitive read once per warp and broadcast), and each thread evaluates a column
of 4 voxels per primitive read. The list keeps the binned order (level, cell in raster order,
slot in the cell), and a voxel's contributing primitives are a subsequence of it in exactly the
order :func:`binned_sums` visits them, so the decoded values are the evaluator's, bit for bit.

V~ is exactly 0 at a point no primitive's truncated support reaches (numerator and density are
both 0): a brick with an empty list is written 0 without evaluation. :func:`mark_bricks` and
:func:`eval_grid_blocked` remain for the share of bricks a decode evaluates and as the path for
a slab whose lists would not fit (:data:`warpgauss.field.gaussians.MAX_BRICK_LIST`).
"""

import warp as wp

from .field import RHO0, BinnedPrimitives, binned_sums, conic_kernel

wp.set_module_options({"enable_backward": False})

BRICK_EDGE = wp.constant(8)  # voxels per brick edge of the activity grid
MAX_MARKED = wp.constant(4096)  # bricks one primitive may mark; a larger one marks the whole grid


@wp.kernel
def mark_bricks(
    mu: wp.array(dtype=wp.vec3),  # [N] prepared centres (any order)
    ext: wp.array(dtype=wp.vec3),  # [N] 5-sigma half-extents
    active: wp.array3d(dtype=wp.uint8),  # [bz, by, bx] out (zeroed before): 1 where a box reaches
    everything: wp.array(dtype=int),  # [1] out: set when a primitive is too large to mark brick by brick
):
    """Mark the bricks each primitive's bounding box overlaps (one thread per primitive)."""
    i = wp.tid()
    c = mu[i]
    e = ext[i]
    nbz = active.shape[0]
    nby = active.shape[1]
    nbx = active.shape[2]
    b = float(BRICK_EDGE)
    # voxel v spans [v - 0.5, v + 0.5]; brick k holds voxels [k B, (k + 1) B)
    x0 = wp.clamp(int(wp.floor((c[0] - e[0] + 0.5) / b)), 0, nbx - 1)
    x1 = wp.clamp(int(wp.floor((c[0] + e[0] + 0.5) / b)), 0, nbx - 1)
    y0 = wp.clamp(int(wp.floor((c[1] - e[1] + 0.5) / b)), 0, nby - 1)
    y1 = wp.clamp(int(wp.floor((c[1] + e[1] + 0.5) / b)), 0, nby - 1)
    z0 = wp.clamp(int(wp.floor((c[2] - e[2] + 0.5) / b)), 0, nbz - 1)
    z1 = wp.clamp(int(wp.floor((c[2] + e[2] + 0.5) / b)), 0, nbz - 1)
    if not (wp.isfinite(c[0] + c[1] + c[2]) and wp.isfinite(e[0] + e[1] + e[2])):
        everything[0] = 1
        return
    count = (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
    if count > MAX_MARKED:
        everything[0] = 1
        return
    for z in range(z0, z1 + 1):
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                active[z, y, x] = wp.uint8(1)


@wp.func
def voxel_coord(i: int, offset: float, scale: float) -> float:
    """Model-grid coordinate of output voxel i's centre: ((i + offset) + 0.5) scale - 0.5, the
    formula every grid evaluator uses (offset 0: the whole extent, as
    :func:`warpgauss.kernels.field.eval_grid_binned`; an integer offset adds exactly, so a region
    that starts on a voxel of a whole grid samples that grid's very coordinates)."""
    return (float(i) + offset + 0.5) * scale - 0.5


@wp.kernel
def eval_grid_blocked(
    z0: int,  # first output slice of this slab
    scale: wp.vec3,  # model voxels per output voxel along x, y, z
    offset: wp.vec3,  # output voxels before voxel 0 (a region's start; 0 for the whole extent)
    prims: BinnedPrimitives,
    active: wp.array3d(dtype=wp.uint8),  # [bz, by, bx] bricks some primitive reaches (see use_active)
    use_active: int,  # 0: evaluate everywhere (a primitive too large to mark bricks)
    out: wp.array3d(dtype=float),  # [nz_slab, ny, nx] out
):
    """:func:`warpgauss.kernels.field.eval_grid_binned` that writes 0 without evaluating where no
    primitive reaches (exactly the value the evaluation would give there), with threads grouped in
    8^3 blocks, each warp a 4x4x2 voxel block.

    A warp of a row-major launch spans 32 voxels along x, often two or three cells of a level, and
    its threads walk different cell ranges; a compact 4x4x2 block mostly shares them. The values
    are the same, bit for bit (each voxel is evaluated by the same function).
    """
    t = wp.tid()
    local = t % 512
    blk = t / 512
    nx = out.shape[2]
    ny = out.shape[1]
    nbx = (nx + 7) / 8
    nby = (ny + 7) / 8
    i = (blk % nbx) * 8 + (local & 3) + 4 * ((local >> 5) & 1)
    j = ((blk / nbx) % nby) * 8 + ((local >> 2) & 3) + 4 * ((local >> 6) & 1)
    k = (blk / (nbx * nby)) * 8 + ((local >> 4) & 1) + 2 * ((local >> 7) & 3)
    if i >= nx or j >= ny or k >= out.shape[0]:
        return
    p = wp.vec3(voxel_coord(i, offset[0], scale[0]), voxel_coord(j, offset[1], scale[1]), voxel_coord(k + z0, offset[2], scale[2]))
    if use_active != 0:
        b = float(BRICK_EDGE)
        bx = wp.clamp(int(wp.floor((p[0] + 0.5) / b)), 0, active.shape[2] - 1)
        by = wp.clamp(int(wp.floor((p[1] + 0.5) / b)), 0, active.shape[1] - 1)
        bz = wp.clamp(int(wp.floor((p[2] + 0.5) / b)), 0, active.shape[0] - 1)
        if active[bz, by, bx] == wp.uint8(0):
            out[k, j, i] = 0.0
            return
    s = binned_sums(p, prims)
    out[k, j, i] = s[0] / wp.max(s[1], RHO0)


def blocked_threads(h: int, ny: int, nx: int) -> int:
    """Launch size of :func:`eval_grid_blocked` for a (h, ny, nx) slab."""
    return -(-h // 8) * -(-ny // 8) * -(-nx // 8) * 512


# threads per brick in eval_brick_lists: 8 x 8, each a column of 8 voxels along z. Measured on an
# H200 (speed/decode_profile_1024*_h200.json, the bench's model at 1024^3): 128 threads of 4 voxels
# took eval_brick_lists 668 / 945 ms at N 20,000 / 1.4M (330 / 489 list entries a brick)
LIST_THREADS = wp.constant(64)
vec8 = wp.types.vector(length=8, dtype=wp.float32)


@wp.func
def cell_span(lo: float, hi: float, size: float, dim: int) -> wp.vec2i:
    """Inclusive range of a level's cells (clamped like ``level_cell``) whose primitives can reach
    [lo, hi]: a primitive of the level has radius <= size, so its (clamped) cell is that of a
    centre within [lo - size, hi + size]; the margin covers rounding."""
    if dim == 1:
        return wp.vec2i(0, 0)
    inv = 1.0 / size
    m = 1.001 * size + 0.01
    a = wp.clamp((lo - m + 0.5) * inv, -1.0, float(dim))
    b = wp.clamp((hi + m + 0.5) * inv, -1.0, float(dim))
    return wp.vec2i(wp.clamp(int(wp.floor(a)), 0, dim - 1), wp.clamp(int(wp.floor(b)), 0, dim - 1))


@wp.func
def box_meets(mu: wp.vec3, ext: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> bool:
    """Whether the box mu +- ext may reach a point of [lo, hi] (widened for rounding; a box with a
    non-finite bound is kept, the per-voxel test decides)."""
    for a in range(3):
        tol = 1.0e-5 * (wp.abs(mu[a]) + ext[a] + wp.abs(lo[a]) + wp.abs(hi[a])) + 1.0e-6
        if mu[a] - ext[a] > hi[a] + tol or mu[a] + ext[a] < lo[a] - tol:
            return False
    return True


@wp.func
def brick_of(b: int, bricks: wp.vec3i) -> wp.vec3i:
    """(bx, by, bz) of brick id b in a slab of ``bricks`` bricks per axis (x fastest)."""
    return wp.vec3i(b % bricks[0], (b / bricks[0]) % bricks[1], b / (bricks[0] * bricks[1]))


@wp.kernel
def list_bricks(
    z0: int,  # first output slice of this slab
    scale: wp.vec3,  # model voxels per output voxel along x, y, z
    offset: wp.vec3,  # output voxels before voxel 0 (a region's start; 0 for the whole extent)
    size: wp.vec3i,  # output voxels of the slab (nx, ny, h)
    bricks: wp.vec3i,  # bricks per axis of the slab
    prims: BinnedPrimitives,
    fill: int,  # 0: count each brick's primitives; 1: write them at their offsets
    ends: wp.array(dtype=int),  # [B] inclusive prefix sum of counts (read when fill)
    counts: wp.array(dtype=int),  # [B] out when counting, read when filling
    items: wp.array(dtype=int),  # [total] out when filling: sorted slots, brick by brick
):
    """Count (fill=0), then list (fill=1), the primitives whose box meets each brick's voxel
    centres, in binned order (one thread per brick; both passes walk identically)."""
    b = wp.tid()
    c = brick_of(b, bricks)
    x0 = c[0] * BRICK_EDGE
    y0 = c[1] * BRICK_EDGE
    zb = c[2] * BRICK_EDGE
    lo = wp.vec3(voxel_coord(x0, offset[0], scale[0]), voxel_coord(y0, offset[1], scale[1]), voxel_coord(zb + z0, offset[2], scale[2]))
    hi = wp.vec3(
        voxel_coord(wp.min(x0 + BRICK_EDGE, size[0]) - 1, offset[0], scale[0]),
        voxel_coord(wp.min(y0 + BRICK_EDGE, size[1]) - 1, offset[1], scale[1]),
        voxel_coord(wp.min(zb + BRICK_EDGE, size[2]) - 1 + z0, offset[2], scale[2]),
    )
    w = int(0)
    if fill != 0:
        w = ends[b] - counts[b]
    n = int(0)
    for l in range(prims.level_size.shape[0]):
        s = prims.level_size[l]
        d = prims.level_dims[l]
        sx = cell_span(lo[0], hi[0], s, d[0])
        sy = cell_span(lo[1], hi[1], s, d[1])
        sz = cell_span(lo[2], hi[2], s, d[2])
        for cz in range(sz[0], sz[1] + 1):
            for cy in range(sy[0], sy[1] + 1):
                row = prims.level_offset[l] + (cz * d[1] + cy) * d[0]
                for cx in range(sx[0], sx[1] + 1):
                    for j in range(prims.cell_start[row + cx], prims.cell_end[row + cx]):
                        if box_meets(prims.mu[j], prims.ext[j], lo, hi):
                            if fill != 0:
                                items[w + n] = j
                            n += 1
    if fill == 0:
        counts[b] = n


@wp.kernel
def eval_brick_lists(
    z0: int,  # first output slice of this slab
    scale: wp.vec3,  # model voxels per output voxel along x, y, z
    offset: wp.vec3,  # output voxels before voxel 0 (a region's start; 0 for the whole extent)
    bricks: wp.vec3i,  # bricks per axis of the slab
    prims: BinnedPrimitives,
    ends: wp.array(dtype=int),  # [B] inclusive prefix sum of counts
    counts: wp.array(dtype=int),  # [B] primitives listed per brick
    items: wp.array(dtype=int),  # sorted slots, brick by brick (list_bricks)
    out: wp.array3d(dtype=float),  # [h, ny, nx] out
):
    """V~ of each voxel of a slab from its brick's list: LIST_THREADS threads a brick, each a column
    of BRICK_EDGE voxels along z (a warp an 8 x 4 footprint): one primitive read a column, its x and
    y offsets tested against the box once for the column, then eight voxels (the same arithmetic as
    :func:`conic_kernel` voxel by voxel, in list order: the evaluator's sums bit for bit)."""
    t = wp.tid()
    b = t / LIST_THREADS
    c = brick_of(b, bricks)
    local = t % LIST_THREADS
    i = c[0] * BRICK_EDGE + (local & 7)
    j = c[1] * BRICK_EDGE + ((local >> 3) & 7)
    k0 = c[2] * BRICK_EDGE
    if i >= out.shape[2] or j >= out.shape[1] or k0 >= out.shape[0]:
        return
    px = voxel_coord(i, offset[0], scale[0])
    py = voxel_coord(j, offset[1], scale[1])
    num = vec8(0.0)
    den = vec8(0.0)
    for u in range(ends[b] - counts[b], ends[b]):
        s = items[u]
        mu = prims.mu[s]
        ext = prims.ext[s]
        if wp.abs(px - mu[0]) > ext[0] or wp.abs(py - mu[1]) > ext[1]:
            continue  # outside the box for the whole column: conic_kernel's 0 at each voxel
        cq = prims.conic[s]
        w = prims.w[s]
        wa = w * prims.a[s]
        for q in range(BRICK_EDGE):
            g = conic_kernel(wp.vec3(px, py, voxel_coord(k0 + q + z0, offset[2], scale[2])) - mu, ext, cq)
            if g > 0.0:
                num[q] = num[q] + wa * g
                den[q] = den[q] + w * g
    for q in range(BRICK_EDGE):
        if k0 + q < out.shape[0]:
            out[k0 + q, j, i] = num[q] / wp.max(den[q], RHO0)


@wp.kernel
def clamp_unit(
    out: wp.array3d(dtype=float),  # [h, ny, nx] decoded values (normalised), clamped in place
    clamped: wp.array(dtype=wp.int64),  # [1] out: += voxels moved into [0, 1]
):
    """Clamp decoded values to [0, 1], the source's [min, max] (one thread per voxel): a sum of
    Gaussians can overshoot a sharp edge or undershoot into empty space, where no source value
    lies. Integer atomics: the count does not depend on the threads' order."""
    k, j, i = wp.tid()
    v = out[k, j, i]
    if v < 0.0:
        out[k, j, i] = 0.0
        wp.atomic_add(clamped, 0, wp.int64(1))
    elif v > 1.0:
        out[k, j, i] = 1.0
        wp.atomic_add(clamped, 0, wp.int64(1))
