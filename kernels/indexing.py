"""Voxel and brick indexing shared by the sampler's kernels (:mod:`warpgauss.kernels.sampling`,
:mod:`warpgauss.kernels.support`, :mod:`warpgauss.kernels.lists`): 4^3 bricks, ranks found through
prefix sums, and linear voxel indices. A volume in host memory may hold more than 2^31 voxels
(``field.analysis.MAX_HOST_VOXELS``): linear indices, ranks and prefix sums over voxels are int64
here; brick indices stay int (fewer than 2^31 bricks), and a voxel is returned as (k, j, i).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

BRICK = wp.constant(4)  # stratum index granularity: voxels per brick edge


@wp.func
def brick_voxel(bk: int, bj: int, bi: int, d: int) -> wp.vec3i:
    """(k, j, i) of the d-th voxel (z, then y, then x) of 4^3 brick (bk, bj, bi); may lie past the grid."""
    return wp.vec3i(bk * BRICK + d / (BRICK * BRICK), bj * BRICK + (d / BRICK) % BRICK, bi * BRICK + d % BRICK)


@wp.func
def block_voxels(pk: int, pj: int, pi: int, f: int, nz: int, ny: int, nx: int) -> int:
    """Voxels of block (pk, pj, pi) of f^3 bricks (edge 4 f) inside an nz x ny x nx grid."""
    e = BRICK * f
    return wp.min(e, nz - pk * e) * wp.min(e, ny - pj * e) * wp.min(e, nx - pi * e)


@wp.func
def brick_voxels(bk: int, bj: int, bi: int, nz: int, ny: int, nx: int) -> int:
    """Voxels of 4^3 brick (bk, bj, bi) inside an nz x ny x nx grid."""
    return block_voxels(bk, bj, bi, 1, nz, ny, nx)


@wp.func
def find_brick(cum: wp.array(dtype=Any), r: Any) -> wp.vec2i:
    """(brick, rank within it) of rank r, for inclusive prefix sums ``cum`` of per-brick counts
    (int, or int64 where a stratum holds more than 2^31 voxels: r of the same type, the rank
    within the brick below 2^31)."""
    lo = int(0)
    hi = cum.shape[0] - 1
    while lo < hi:  # first brick whose inclusive sum exceeds r
        mid_ = (lo + hi) / 2
        if cum[mid_] > r:
            hi = mid_
        else:
            lo = mid_ + 1
    rr = r
    if lo > 0:
        rr = r - cum[lo - 1]
    return wp.vec2i(lo, int(rr))


@wp.func
def brick_origin(b: int, ny: int, nx: int) -> wp.vec3i:
    """(i, j, k) of the first voxel of brick b (bricks in z, y, x order over a grid ny x nx wide)."""
    nbx = (nx + BRICK - 1) / BRICK
    nby = (ny + BRICK - 1) / BRICK
    return wp.vec3i((b % nbx) * BRICK, ((b / nbx) % nby) * BRICK, (b / (nbx * nby)) * BRICK)


@wp.func
def brick_rank_voxel(b: int, t: int, ny: int, nx: int) -> wp.vec3i:
    """(k, j, i) of the t-th voxel inside the grid (z, then y, then x) of brick b."""
    o = brick_origin(b, ny, nx)
    hx = wp.min(BRICK, nx - o[0])
    hy = wp.min(BRICK, ny - o[1])
    return wp.vec3i(o[2] + t / (hy * hx), o[1] + (t / hx) % hy, o[0] + t % hx)


@wp.func
def grid_voxel(r: wp.int64, ny: int, nx: int) -> wp.vec3i:
    """(k, j, i) of linear voxel index r (z, then y, then x), in int64: a grid may hold more
    than 2^31 voxels."""
    nx64 = wp.int64(nx)
    ny64 = wp.int64(ny)
    return wp.vec3i(int(r / (nx64 * ny64)), int((r / nx64) % ny64), int(r % nx64))


@wp.func
def grid_voxels(nz: int, ny: int, nx: int) -> wp.int64:
    """nz x ny x nx in int64."""
    return wp.int64(nz) * wp.int64(ny) * wp.int64(nx)


@wp.func
def rank_below(u: wp.uint32, n: wp.int64, rank32_max: wp.int64, stream: int, s: int) -> wp.int64:
    """A rank uniform in [0, n) from ``u``, a 32-bit draw (``wp.randu``) of sample s's stream.
    Where n <= ``rank32_max`` (at most 2^31 - 1) it is u mod n, bit for bit what
    ``wp.randi(state, 0, n)`` gives of the same state. Beyond, u is the low word of a 64-bit
    draw whose high word is drawn from a second stream of (``stream``, s): both words from one
    32-bit state would reach at most 2^32 of the n ranks, whatever n."""
    if n <= rank32_max:
        return wp.int64(u % wp.uint32(int(n)))
    hs = wp.rand_init(int(wp.rand_init(stream)), s)
    hi = wp.randu(hs)
    return wp.int64(((wp.uint64(hi) << wp.uint64(32)) | wp.uint64(u)) % wp.uint64(n))
