"""The Gaussian model in float64 at the voxel centres of its grid: the predictor of a bounded
residual (:mod:`warpgauss.format.residual`).

A residual makes every decoded voxel lie within a bound E of the source, so it must be applied to
the very prediction the encoder coded it against, wherever the file is read. The float32 decode
(:mod:`warpgauss.kernels.decode`) differs between the CPU and CUDA by a few units in the last
place of float32 (``exp`` and fused multiply-adds differ), and at a pair on the 5-sigma cut by a
whole term; a bound of 1e-6 of the range could not absorb that. In float64 each term carries a
relative error of a few 1e-16 on either device, far below the margin the residual keeps
(:data:`warpgauss.format.residual.MARGIN_REL`), and a voxel with a pair within ``CUT_REL`` of the cut
(where the devices could disagree on whether the term counts) is flagged ``fragile``: the
residual stores its value outright.

The predictor is its own function of the stored parameters (float32 values, read exactly into
float64): the 5-sigma cut tested in float64, no separate box test, the same density floor. It is
not bit-for-bit the float32 decode, only within a few 1e-7 of it; it need not be.

Each voxel walks the list of its 8^3 brick (:func:`warpgauss.kernels.decode.list_bricks`, built
from the float32 boxes widened for rounding, so a list holds every primitive whose float64
ellipsoid reaches the brick).
"""

import warp as wp

from .decode import BRICK_EDGE
from .field import LOG_SCALE_MAX, LOG_SCALE_MIN, RHO0, VALUE_BOUND

wp.set_module_options({"enable_backward": False})

CUT_REL = wp.constant(wp.float64(1.0e-9))  # a pair with |m - 25| below 25 x this marks its voxel fragile
TRUNC_M2_64 = wp.constant(wp.float64(25.0))


@wp.kernel
def prepare64(
    params: wp.array2d(dtype=wp.float64),  # [N, 12] model parameters (float32 values, exactly)
    order: wp.array(dtype=int),  # [>=N] primitive index at each sorted slot (the lists' numbering)
    mu: wp.array(dtype=wp.vec3d),  # [N] out, slot order: centres
    rot: wp.array(dtype=wp.mat33d),  # [N] out: R (columns = local axes)
    inv_s2: wp.array(dtype=wp.vec3d),  # [N] out: 1 / sigma^2 per local axis
    wa: wp.array(dtype=wp.float64),  # [N] out: w a
    w: wp.array(dtype=wp.float64),  # [N] out: w
):
    """Prepare one primitive in float64 (one thread per sorted slot); the float64 counterpart of
    :func:`warpgauss.kernels.field.prepare_one` for model (not training) parameters."""
    s = wp.tid()
    i = order[s]
    qx = params[i, 6]
    qy = params[i, 7]
    qz = params[i, 8]
    qw = params[i, 9]
    n2 = qx * qx + qy * qy + qz * qz + qw * qw
    if n2 < wp.float64(1.0e-20):
        qx = wp.float64(0.0)
        qy = wp.float64(0.0)
        qz = wp.float64(0.0)
        qw = wp.float64(1.0)
    else:
        inv = wp.float64(1.0) / wp.sqrt(n2)
        qx = qx * inv
        qy = qy * inv
        qz = qz * inv
        qw = qw * inv
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    rot[s] = wp.mat33d(
        one - two * (qy * qy + qz * qz),
        two * (qx * qy - qz * qw),
        two * (qx * qz + qy * qw),
        two * (qx * qy + qz * qw),
        one - two * (qx * qx + qz * qz),
        two * (qy * qz - qx * qw),
        two * (qx * qz - qy * qw),
        two * (qy * qz + qx * qw),
        one - two * (qx * qx + qy * qy),
    )
    lo = wp.float64(LOG_SCALE_MIN)
    hi = wp.float64(LOG_SCALE_MAX)
    sx = wp.exp(wp.clamp(params[i, 3], lo, hi))
    sy = wp.exp(wp.clamp(params[i, 4], lo, hi))
    sz = wp.exp(wp.clamp(params[i, 5], lo, hi))
    inv_s2[s] = wp.vec3d(one / (sx * sx), one / (sy * sy), one / (sz * sz))
    mu[s] = wp.vec3d(params[i, 0], params[i, 1], params[i, 2])
    bound = wp.float64(VALUE_BOUND)
    wt = wp.clamp(params[i, 11], -bound, bound)
    w[s] = wt
    wa[s] = wt * wp.clamp(params[i, 10], -bound, bound)


@wp.kernel
def predict_lists(
    z0: int,  # first slice of this slab on the model grid
    bricks: wp.vec3i,  # bricks per axis of the slab
    ends: wp.array(dtype=int),  # [B] inclusive prefix sum of counts
    counts: wp.array(dtype=int),  # [B] primitives listed per brick
    items: wp.array(dtype=int),  # sorted slots, brick by brick (list_bricks)
    mu: wp.array(dtype=wp.vec3d),
    rot: wp.array(dtype=wp.mat33d),
    inv_s2: wp.array(dtype=wp.vec3d),
    wa: wp.array(dtype=wp.float64),
    w: wp.array(dtype=wp.float64),
    out: wp.array3d(dtype=wp.float64),  # [h, ny, nx] out: V~ clamped to [0, 1]
    fragile: wp.array3d(dtype=wp.uint8),  # [h, ny, nx] out: 1 where a pair lies within CUT_REL of the cut
):
    """V~ in float64 at each voxel centre of a slab (one thread per voxel)."""
    k, j, i = wp.tid()
    b = ((k / BRICK_EDGE) * bricks[1] + j / BRICK_EDGE) * bricks[0] + i / BRICK_EDGE
    p = wp.vec3d(wp.float64(i), wp.float64(j), wp.float64(k + z0))
    num = wp.float64(0.0)
    den = wp.float64(0.0)
    near = wp.uint8(0)
    half = wp.float64(-0.5)
    for u in range(ends[b] - counts[b], ends[b]):
        s = items[u]
        y = wp.transpose(rot[s]) @ (p - mu[s])
        c = inv_s2[s]
        m = y[0] * y[0] * c[0] + y[1] * y[1] * c[1] + y[2] * y[2] * c[2]
        if wp.abs(m - TRUNC_M2_64) <= TRUNC_M2_64 * CUT_REL:
            near = wp.uint8(1)
        if m < TRUNC_M2_64:
            g = wp.exp(half * m)
            num = num + wa[s] * g
            den = den + w[s] * g
    v = num / wp.max(den, wp.float64(RHO0))
    out[k, j, i] = wp.clamp(v, wp.float64(0.0), wp.float64(1.0))
    fragile[k, j, i] = near
