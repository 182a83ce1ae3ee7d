"""Decode only where the model can be non-zero: bricks that some primitive's 5-sigma box touches.

V~ is exactly 0 at a point no primitive's truncated support reaches (numerator and density are
both 0), so a grid decode may skip those points without changing a single value. For sparse
fields (a few per cent occupied) most of the grid is such empty space.
"""

import warp as wp

from .field import RHO0, BinnedPrimitives, binned_sums

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


@wp.kernel
def eval_grid_blocked(
    z0: int,  # first output slice of this slab
    scale: wp.vec3,  # model voxels per output voxel along x, y, z
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
    p = wp.vec3(
        (float(i) + 0.5) * scale[0] - 0.5,
        (float(j) + 0.5) * scale[1] - 0.5,
        (float(k + z0) + 0.5) * scale[2] - 0.5,
    )
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
