"""The model's support for the uniform training samples (see :mod:`warpgauss.kernels.sampling`):
the 4^3 bricks some primitive's 5-sigma box, widened by :data:`SUPPORT_MARGIN` voxels, reaches,
counted by corner marks and three prefix sums, and what the draw cannot reach outside them."""

import warp as wp

from .analysis import usable
from .indexing import BRICK, brick_voxel, brick_voxels
from .sampling import stratum_of

wp.set_module_options({"enable_backward": False})

SUPPORT_MARGIN = wp.constant(2.0)  # voxels added to each 5-sigma half-extent (see mark_support)


@wp.kernel
def mark_support(
    mu: wp.array(dtype=wp.vec3),  # [N] prepared centres (any order)
    ext: wp.array(dtype=wp.vec3),  # [N] 5-sigma half-extents
    marks: wp.array3d(dtype=int),  # [bz, by, bx] out (zeroed before): corner counts, see below
    everything: wp.array(dtype=int),  # [1] out (zeroed before): set when the whole grid is support
):
    """Mark the 4^3 bricks holding a voxel whose jittered samples (+-0.5) can fall in a primitive's
    5-sigma box widened by SUPPORT_MARGIN voxels: where it contributes now and, up to that much
    growth or motion, until the next re-bin re-marks them.

    Each primitive adds +-1 at the 8 corners of its range of bricks (inclusion-exclusion; integer
    atomics, so the result does not depend on their order); prefix sums along x, y and z
    (:func:`prefix_sum_axis`) then give each brick the number of boxes that reach it. A
    primitive costs 8 writes whatever its size (marking brick by brick cost 130 ms a re-bin for
    1.4M primitives of about 16^3 bricks each on an H100).
    """
    i = wp.tid()
    c = mu[i]
    e = ext[i]
    if not wp.isfinite(c[0] + c[1] + c[2] + e[0] + e[1] + e[2]):
        everything[0] = 1
        return
    b = float(BRICK)
    lo = wp.vec3i(0, 0, 0)
    hi = wp.vec3i(0, 0, 0)
    nb = wp.vec3i(marks.shape[2], marks.shape[1], marks.shape[0])
    for a in range(3):
        h = e[a] + SUPPORT_MARGIN
        v0 = wp.clamp(wp.ceil(c[a] - h - 0.5), -b, float(nb[a]) * b)  # voxels whose [v - 0.5, v + 0.5] meets [c - h, c + h]
        v1 = wp.clamp(wp.floor(c[a] + h + 0.5), -b, float(nb[a]) * b)
        lo[a] = wp.clamp(int(wp.floor(v0 / b)), 0, nb[a] - 1)
        hi[a] = wp.clamp(int(wp.floor(v1 / b)), 0, nb[a] - 1)
    for corner in range(8):
        x = lo[0]
        y = lo[1]
        z = lo[2]
        sign = int(1)
        if corner & 1:
            x = hi[0] + 1
            sign = -sign
        if corner & 2:
            y = hi[1] + 1
            sign = -sign
        if corner & 4:
            z = hi[2] + 1
            sign = -sign
        if x < nb[0] and y < nb[1] and z < nb[2]:  # a corner past the grid's end changes no brick
            wp.atomic_add(marks, z, y, x, sign)


@wp.kernel
def prefix_sum_axis(marks: wp.array3d(dtype=int), axis: int):
    """Running sum along ``axis`` (0: z, 1: y, 2: x) of every line of ``marks``, in place: one
    thread per line, launched over the two other axes in (z, y, x) order."""
    u, v = wp.tid()
    s = int(0)
    for t in range(marks.shape[axis]):
        k = u
        j = v
        i = t
        if axis == 0:
            k = t
            j = u
            i = v
        elif axis == 1:
            k = u
            j = t
            i = v
        s += marks[k, j, i]
        marks[k, j, i] = s


@wp.kernel
def support_counts(
    marks: wp.array3d(dtype=int),  # [bz, by, bx] from mark_support
    everything: wp.array(dtype=int),  # [1]
    nz: int,
    ny: int,
    nx: int,
    counts: wp.array3d(
        dtype=wp.int64
    ),  # [bz, by, bx] out: voxels of each supported brick inside the grid (int64: their prefix sums may pass 2^31)
):
    bk, bj, bi = wp.tid()
    n = int(0)
    if marks[bk, bj, bi] != 0 or everything[0] != 0:
        n = brick_voxels(bk, bj, bi, nz, ny, nx)
    counts[bk, bj, bi] = wp.int64(n)


@wp.kernel
def unreached_squares(
    vol: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
    support_counts_: wp.array3d(dtype=wp.int64),  # [bz, by, bx] support_counts' output
    out: wp.array3d(dtype=float),  # [bz, by, bx] out: sum of V^2 over the brick's unreached voxels
):
    """Per 4^3 brick, the sum of V^2 over the usable voxels the draw cannot reach when its
    uniform stratum is drawn over the support: empty (in neither stratum) and in an unsupported
    brick. No primitive reaches them, so the decode writes 0 there and V^2 is their squared error."""
    bk, bj, bi = wp.tid()
    s = float(0.0)
    if support_counts_[bk, bj, bi] == wp.int64(0):
        for d in range(BRICK * BRICK * BRICK):
            v = brick_voxel(bk, bj, bi, d)
            if stratum_of(vol, mask, has_mask, v[0], v[1], v[2]) < 0 and usable(vol, mask, has_mask, v[0], v[1], v[2]):
                x = vol[v[0], v[1], v[2]]
                s += x * x
    out[bk, bj, bi] = s


@wp.kernel
def sum_runs(values: wp.array(dtype=float), run: int, partials: wp.array(dtype=wp.float64)):
    """partials[t] = the float64 sum of values[t run .. (t + 1) run), in order (one thread a run):
    a large per-brick array summed on the device, so that only its partials are read back."""
    t = wp.tid()
    s = wp.float64(0.0)
    for i in range(t * run, wp.min((t + 1) * run, values.shape[0])):
        s += wp.float64(values[i])
    partials[t] = s
