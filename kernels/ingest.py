"""Stage P on the device: a volume that already lives on the GPU (a simulation's array, handed over
by DLPack or ``__cuda_array_interface__``) is scanned, masked, normalised and counted there, with
no host copy (SPEC section 2; the host path is :func:`warpgauss.field.analysis.normalise`).

Reductions run one thread per (z, y) row: each writes its row's result, and the host sums the rows
(a few hundred kilobytes at 512^3), so that the result does not depend on the order of atomics.
The source may be any real dtype and strided (a view without ghost cells); it is read as float64
for the checks, and normalised exactly as the host does (float32 arithmetic where its plan allows).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def source_valid(s: wp.float64, check_finite: int, use_fill: int, fill: wp.float64) -> bool:
    """Not NaN/Inf (floating sources) and not the fill value (compared as the host compares)."""
    if check_finite != 0 and not wp.isfinite(s):
        return False
    if use_fill != 0 and s == fill:
        return False
    return True


@wp.kernel
def row_range(
    src: wp.array3d(dtype=Any),
    check_finite: int,
    use_fill: int,
    fill: wp.float64,
    row_lo: wp.array2d(dtype=wp.float64),
    row_hi: wp.array2d(dtype=wp.float64),
    row_invalid: wp.array2d(dtype=int),
):
    """Per (z, y) row: the finite min and max of its valid voxels (+inf / -inf if none) and how many are invalid."""
    k, j = wp.tid()
    lo = wp.float64(wp.inf)
    hi = wp.float64(-wp.inf)
    bad = int(0)
    for i in range(src.shape[2]):
        s = wp.float64(src[k, j, i])
        if source_valid(s, check_finite, use_fill, fill):
            lo = wp.min(lo, s)
            hi = wp.max(hi, s)
        else:
            bad += 1
    row_lo[k, j] = lo
    row_hi[k, j] = hi
    row_invalid[k, j] = bad


@wp.kernel
def normalise_values(
    src: wp.array3d(dtype=Any),
    check_finite: int,
    use_fill: int,
    fill: wp.float64,
    f32: int,
    lo32: wp.float32,
    scale32: wp.float32,
    lo: wp.float64,
    span: wp.float64,
    scale: wp.float64,
    halve: int,
    divide: int,
    clip: int,
    bound: wp.float64,
    out: wp.array3d(dtype=float),
    mask: wp.array3d(dtype=wp.uint8),
    has_mask: int,
):
    """out = (s - lo) / (hi - lo), as ``analysis._NormPlan.apply`` computes it; invalid voxels 0
    (and 0 in ``mask`` where there is one)."""
    k, j, i = wp.tid()
    x = src[k, j, i]
    s = wp.float64(x)
    ok = source_valid(s, check_finite, use_fill, fill)
    v = float(0.0)
    if ok:
        if f32 != 0:
            v = (wp.float32(x) - lo32) * scale32
        else:
            d = s
            if halve != 0:
                d = d * wp.float64(0.5)
            d = d - lo
            if divide != 0:
                d = d / span
            else:
                d = d * scale
            if clip != 0:
                d = wp.clamp(d, wp.float64(0.0), wp.float64(1.0))
            elif bound > wp.float64(0.0):
                d = wp.clamp(d, -bound, bound)
            v = wp.float32(d)
        if clip != 0:
            v = wp.clamp(v, 0.0, 1.0)
    out[k, j, i] = v
    if has_mask != 0:
        mask[k, j, i] = wp.where(ok, wp.uint8(1), wp.uint8(0))


@wp.kernel
def gather_values(vol: wp.array3d(dtype=float), idx: wp.array(dtype=wp.int64), out: wp.array(dtype=float)):
    """out[t] = vol at linear voxel index idx[t] (x fastest)."""
    t = wp.tid()
    n = idx[t]
    ny = wp.int64(vol.shape[1])
    nx = wp.int64(vol.shape[2])
    out[t] = vol[int(n // (nx * ny)), int((n // nx) % ny), int(n % nx)]


@wp.kernel
def gather_mask(mask: wp.array3d(dtype=wp.uint8), idx: wp.array(dtype=wp.int64), out: wp.array(dtype=wp.uint8)):
    t = wp.tid()
    n = idx[t]
    ny = wp.int64(mask.shape[1])
    nx = wp.int64(mask.shape[2])
    out[t] = mask[int(n // (nx * ny)), int((n // nx) % ny), int(n % nx)]
