"""The bounded residual's interpolation passes with error feedback (issue #52 part 5).

One launch per pass of SZ3's level-wise interpolation (:func:`warpgauss.residual._interp_passes`),
one thread per target point: its prediction from the decoded points at +-h (and +-3h) along the
pass's axis, the error from that prediction quantised on the pass's step, and the point decoded
as prediction + step q. The operations are :func:`warpgauss.residual._interp_prediction`'s and
:func:`warpgauss.residual._quantise`'s in the same order, in float64 (or int64 on the integer
lattice) with floating-point contraction off (``fuse_fp``: no fused multiply-add), so every device
computes the numpy reference's bits: a reader on any machine replays the encoder's decode
exactly, which is what makes the bound hold (tested against the numpy passes bit for bit).
"""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False, "fuse_fp": False})


@wp.func
def line_value(dec: wp.array3d(dtype=Any), z: int, y: int, x: int, axis: int, c: int):
    """dec at (z, y, x) with the coordinate along ``axis`` replaced by c (float64 or int64)."""
    if axis == 0:
        return dec[c, y, x]
    if axis == 1:
        return dec[z, c, x]
    return dec[z, y, c]


@wp.func
def target(tid_z: int, tid_y: int, tid_x: int, start: wp.vec3i, stride: wp.vec3i) -> wp.vec3i:
    return wp.vec3i(start[0] + tid_z * stride[0], start[1] + tid_y * stride[1], start[2] + tid_x * stride[2])


@wp.func
def predict_f(dec: wp.array3d(dtype=wp.float64), p: wp.vec3i, axis: int, h: int, n: int, cubic: int) -> wp.float64:
    """(lo + hi) * 0.5 where +h exists, else lo; (-a + 9 lo + 9 hi - b) * 0.0625 where +-3h exist."""
    c = p[axis]
    lo1 = line_value(dec, p[0], p[1], p[2], axis, c - h)
    pred = lo1
    if c + h < n:
        hi1 = line_value(dec, p[0], p[1], p[2], axis, c + h)
        pred = (lo1 + hi1) * wp.float64(0.5)
        if cubic != 0 and c - 3 * h >= 0 and c + 3 * h < n:
            a = line_value(dec, p[0], p[1], p[2], axis, c - 3 * h)
            b = line_value(dec, p[0], p[1], p[2], axis, c + 3 * h)
            num = -a + wp.float64(9.0) * lo1 + wp.float64(9.0) * hi1 - b
            pred = num * wp.float64(0.0625)
    return pred


@wp.func
def predict_i(dec: wp.array3d(dtype=wp.int64), p: wp.vec3i, axis: int, h: int, n: int, cubic: int) -> wp.int64:
    """The integer lattice's rounding: (lo + hi) >> 1, (-a + 9 lo + 9 hi - b + 8) >> 4."""
    c = p[axis]
    lo1 = line_value(dec, p[0], p[1], p[2], axis, c - h)
    pred = lo1
    if c + h < n:
        hi1 = line_value(dec, p[0], p[1], p[2], axis, c + h)
        pred = (lo1 + hi1) >> wp.int64(1)
        if cubic != 0 and c - 3 * h >= 0 and c + 3 * h < n:
            a = line_value(dec, p[0], p[1], p[2], axis, c - 3 * h)
            b = line_value(dec, p[0], p[1], p[2], axis, c + 3 * h)
            num = -a + wp.int64(9) * lo1 + wp.int64(9) * hi1 - b
            pred = (num + wp.int64(8)) >> wp.int64(4)
    return pred


@wp.func
def floor_div(a: wp.int64, b: wp.int64) -> wp.int64:
    """numpy's floor_divide for b > 0 (C's division truncates toward zero)."""
    q = a / b
    if a % b != wp.int64(0) and a < wp.int64(0):
        q = q - wp.int64(1)
    return q


@wp.kernel
def feedback_pass_f(
    t: wp.array3d(dtype=wp.float64),  # the values to code
    skip: wp.array3d(dtype=wp.uint8),  # 1: coded as its prediction (q = 0)
    start: wp.vec3i,  # the pass's first target per axis (z, y, x)
    stride: wp.vec3i,  # and its stride
    axis: int,
    h: int,
    cubic: int,
    step: wp.float64,
    q: wp.array3d(dtype=wp.int64),  # out at the targets
    dec: wp.array3d(dtype=wp.float64),  # in: decoded so far; out at the targets
):
    """One pass on the float lattice: q = rint((t - pred) / step), dec = pred + q step."""
    i, j, k = wp.tid()
    p = target(i, j, k, start, stride)
    pred = predict_f(dec, p, axis, h, dec.shape[axis], cubic)
    qs = wp.int64(0)
    if skip[p[0], p[1], p[2]] == wp.uint8(0):
        qs = wp.int64(wp.rint((t[p[0], p[1], p[2]] - pred) / step))
    q[p[0], p[1], p[2]] = qs
    dec[p[0], p[1], p[2]] = pred + wp.float64(qs) * step


@wp.kernel
def feedback_pass_i(
    t: wp.array3d(dtype=wp.int64),
    skip: wp.array3d(dtype=wp.uint8),
    start: wp.vec3i,
    stride: wp.vec3i,
    axis: int,
    h: int,
    cubic: int,
    step: wp.int64,  # odd
    q: wp.array3d(dtype=wp.int64),
    dec: wp.array3d(dtype=wp.int64),
):
    """One pass on the integer lattice: q = floor((t - pred + step // 2) / step), dec = pred + q step."""
    i, j, k = wp.tid()
    p = target(i, j, k, start, stride)
    pred = predict_i(dec, p, axis, h, dec.shape[axis], cubic)
    qs = wp.int64(0)
    if skip[p[0], p[1], p[2]] == wp.uint8(0):
        qs = floor_div(t[p[0], p[1], p[2]] - pred + step / wp.int64(2), step)
    q[p[0], p[1], p[2]] = qs
    dec[p[0], p[1], p[2]] = pred + qs * step


@wp.kernel
def decode_pass_f(
    q: wp.array3d(dtype=wp.int64),  # the stored q's
    start: wp.vec3i,
    stride: wp.vec3i,
    axis: int,
    h: int,
    cubic: int,
    step: wp.float64,
    dec: wp.array3d(dtype=wp.float64),  # in: decoded so far; out at the targets
):
    """A reader's pass on the float lattice: dec = pred + q step (what :func:`feedback_pass_f` decoded)."""
    i, j, k = wp.tid()
    p = target(i, j, k, start, stride)
    pred = predict_f(dec, p, axis, h, dec.shape[axis], cubic)
    dec[p[0], p[1], p[2]] = pred + wp.float64(q[p[0], p[1], p[2]]) * step


@wp.kernel
def decode_pass_i(
    q: wp.array3d(dtype=wp.int64),
    start: wp.vec3i,
    stride: wp.vec3i,
    axis: int,
    h: int,
    cubic: int,
    step: wp.int64,
    dec: wp.array3d(dtype=wp.int64),
):
    """A reader's pass on the integer lattice: dec = pred + q step."""
    i, j, k = wp.tid()
    p = target(i, j, k, start, stride)
    pred = predict_i(dec, p, axis, h, dec.shape[axis], cubic)
    dec[p[0], p[1], p[2]] = pred + q[p[0], p[1], p[2]] * step
