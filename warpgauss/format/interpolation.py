"""The bounded residual's predictor (:mod:`.residual`): the quantiser on step 2E (an integer
source on its odd integer step), and SZ3's interpolation, level by level along an axis order chosen
on a central block, over decoded values in float64 numpy, so that every machine computes the same
bits."""

from __future__ import annotations

import math

import numpy as np

DEVICE_BYTES_PER_VOXEL = 25  # the passes on a device: the values (8), skips (1), q's (8), decoded (8)


def quantiser(bound: float, margin: float, dtype: np.dtype) -> tuple[float, bool, np.dtype]:
    """(step, integer?, decoded dtype) for a bound in source units.

    An integer source keeps its dtype with the odd integer step 2 floor(E) + 1 (|error| <= floor(E)
    exactly) unless the float step 2E is coarser (E < 1, or its fraction >= 1/2: at E = 0.646 the
    integer step is lossless, 1 against 1.29): then it decodes to float32 (float64 past 16-bit
    integers). The float step keeps the readers' margin: 2 (E - margin)."""
    if dtype.kind in "iu" and (bound < 0.5 or (bound >= 1.0 and bound - math.floor(bound) < 0.5)):
        return float(2 * math.floor(bound) + 1), True, dtype  # below 1/2: step 1, the source's own integers
    out = dtype if dtype.kind == "f" else np.dtype(np.float32 if dtype.itemsize <= 2 else np.float64)
    return 2.0 * (bound - margin) * (1.0 - 2.0**-30), False, out


def quantise(t: np.ndarray, step: float, integer: bool) -> np.ndarray:
    if integer:
        return np.floor_divide(t + int(step) // 2, int(step))  # t integer: |t - step q| <= step // 2
    return np.rint(t / step).astype(np.int64)


def cast(x: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """float64 or int64 values in the decoded dtype (integers clipped to its range: the source lies
    within it, so clipping never moves a value away from the source)."""
    if dtype.kind in "iu":
        info = np.iinfo(dtype)
        return np.clip(x, max(info.min, -(2**62)), min(info.max, 2**62)).astype(dtype)
    with np.errstate(over="ignore", invalid="ignore"):
        return x.astype(dtype)


AXES = "012"  # the axis order of files without one: z, then y, then x at every level; and the raster layout
ORDERS = ("012", "021", "102", "120", "201", "210")
CHOOSE_BLOCK = 64  # edge of the central block the interpolation's axis order is chosen on (0.1 s at 64^3)
# level-wise bounds (alpha, beta), as QoZ tunes SZ3's interpolation: level l (1: the finest) is
# quantised with the step / min(alpha^(l-1), beta), since an error on a coarse level spreads to
# every finer point predicted from it. Chosen per interpolation kind on the central block. On the
# head MRIs at 1e-2 of the range: mean_reg2mean 32.08 -> 33.77 (cubic, 1.25, 2), inia19 and
# mni_icbm152 keep (1, 1) or gain under 1 % (linear)
LEVELWISE = ((1.0, 1.0), (1.25, 2.0), (1.5, 2.0), (1.5, 4.0), (2.0, 4.0))
FLAT = (1.0, 1.0)


def level_step(step: float, integer: bool, levels: tuple[float, float], lv: int) -> float:
    """The quantisation step of interpolation level ``lv`` (1: the finest): ``step`` over
    min(alpha^(lv-1), beta), by repeated products of exactly representable numbers (the same on
    every machine); on the integer lattice the odd step whose half-width is the bound's over that."""
    alpha, beta = levels
    f = 1.0
    for _ in range(lv - 1):
        f = min(f * alpha, beta)
    if f == 1.0:
        return step
    if integer:
        return float(2 * math.floor(((int(step) - 1) // 2) / f) + 1)
    return step / f


def interp_passes(shape: tuple[int, ...], axes: str = AXES):
    """SZ3's interpolation order: from the coarsest lattice (stride 2^L, stored as it is) down to
    stride 1, each level along the axes in ``axes``' order (e.g. "201": x, then z, then y): the
    points at odd multiples of h along that axis, from their neighbours at +-h (and +-3h) on that
    axis, already known."""
    order = [int(c) for c in axes]
    for lv in range(top_level(shape), 0, -1):
        h = 1 << (lv - 1)
        for k, a in enumerate(order):
            if h >= shape[a]:
                continue
            done = order[:k]  # the axes this level has interpolated: known at stride h along them
            sel = tuple(slice(0, None, h) if b in done else slice(h, None, 2 * h) if b == a else slice(0, None, 2 * h) for b in range(3))
            yield a, h, sel


def interp_prediction(x: np.ndarray, a: int, h: int, sel, cubic_ok: bool = True) -> np.ndarray:
    """The integer prediction of the points ``x[sel]`` from their neighbours along axis ``a``:
    cubic (-1, 9, 9, -1) / 16 where +-h and +-3h exist, linear where only +-h do, else the -h one."""
    n = x.shape[a]
    cols = tuple(s if b != a else slice(None) for b, s in enumerate(sel))
    line = x[cols]  # every point of the lines through the targets (the axis at full resolution)
    idx = np.arange(h, n, 2 * h)

    def take(i):
        return np.take(line, np.clip(i, 0, n - 1), axis=a)

    lo1, hi1 = take(idx - h), take(idx + h)
    has_hi = np.expand_dims(idx + h < n, tuple(b for b in range(3) if b != a))
    whole = x.dtype.kind in "iu"  # integers: exact integer rounding; float64: the same operations on every machine
    pred = np.where(has_hi, (lo1 + hi1) >> 1 if whole else (lo1 + hi1) * 0.5, lo1)
    cubic = np.expand_dims((idx - 3 * h >= 0) & (idx + 3 * h < n), tuple(b for b in range(3) if b != a))
    if cubic_ok and cubic.any():
        num = -take(idx - 3 * h) + 9 * lo1 + 9 * hi1 - take(idx + 3 * h)
        pred = np.where(cubic, (num + 8) >> 4 if whole else num * 0.0625, pred)
    return pred


def feedback(
    t: np.ndarray,
    skip: np.ndarray,
    step: float,
    integer: bool,
    interp: str,
    axes: str = AXES,
    levels: tuple[float, float] = FLAT,
    device: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """SZ's quantisation with error feedback: each point is predicted from already decoded points
    (``interp`` "cubic" or "linear": the interpolation passes; "": 0), its error from that prediction quantised to q,
    and decoded as prediction + step q (|t - decoded| <= step / 2). ``skip``: points coded as their
    prediction (q = 0: masked, or stored outright); ``axes``: the passes' axis order; ``levels``: the
    level-wise bounds (:data:`LEVELWISE`); ``device``: run the passes as Warp kernels there (the
    same bits; None: numpy). Returns (q, decoded)."""
    if interp and device is not None:
        return feedback_on(device, t, skip, step, integer, interp, axes, levels)
    q = np.zeros(t.shape, np.int64)
    dec = np.zeros(t.shape, np.int64 if integer else np.float64)
    if not interp:  # "": no interpolation
        q[~skip] = quantise(t[~skip], step, integer)
        dec[...] = q * np.int64(step) if integer else q * step
        return q, dec
    first, s0, passes = stepped_passes(t.shape, step, integer, axes, levels)
    q[first], dec[first] = first_coded(t, skip, first, s0, integer)
    for a, h, sel, s in passes:
        pred = interp_prediction(dec, a, h, sel, interp == "cubic")
        qs = np.where(skip[sel], 0, quantise(np.where(skip[sel], pred, t[sel]) - pred, s, integer))
        q[sel] = qs
        dec[sel] = pred + (qs * np.int64(s) if integer else qs * s)
    return q, dec


def first_coded(t: np.ndarray, skip: np.ndarray, first, s0: float, integer: bool) -> tuple[np.ndarray, np.ndarray]:
    """The first voxel's (q, decoded value): the coarsest lattice, predicted as 0, on step ``s0``
    (q = 0 where it is skipped; a skipped value may be NaN)."""
    q0 = np.where(skip[first], 0, quantise(np.where(skip[first], 0, t[first]), s0, integer))
    return q0, q0 * (np.int64(s0) if integer else s0)


def feedback_on(
    device: str, t: np.ndarray, skip: np.ndarray, step: float, integer: bool, interp: str, axes: str, levels: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`feedback`'s interpolation passes as Warp kernels on ``device`` (one launch a pass,
    :mod:`warpgauss.kernels.interp`): the same q's and decoded values bit for bit."""
    from ..core.warp import warp
    from ..kernels import interp as ki

    wp = warp()
    kind, wkind = (np.int64, wp.int64) if integer else (np.float64, wp.float64)
    first, s0, passes = stepped_passes(t.shape, step, integer, axes, levels)
    q0, dec0 = first_coded(t, skip, first, s0, integer)
    q = wp.zeros(t.shape, dtype=wp.int64, device=device)
    dec = wp.zeros(t.shape, dtype=wkind, device=device)
    dec[first].assign(np.asarray(dec0, kind))
    tt = wp.array(np.ascontiguousarray(t, kind), dtype=wkind, device=device)
    sk = wp.array(np.ascontiguousarray(skip).view(np.uint8), dtype=wp.uint8, device=device)
    kernel = ki.feedback_pass_i if integer else ki.feedback_pass_f
    for dims, args in _launches(passes, t.shape, integer, interp == "cubic"):
        wp.launch(kernel, dim=dims, inputs=[tt, sk, *args], outputs=[q, dec], device=device)
    qn = q.numpy()
    qn[first] = q0
    return qn, dec.numpy()


def decoded_on(device: str, q: np.ndarray, step: float, integer: bool, interp: str, axes: str, levels: tuple[float, float]) -> np.ndarray:
    """:func:`decoded`'s interpolation passes as Warp kernels on ``device``: the same values bit for bit."""
    from ..core.warp import warp
    from ..kernels import interp as ki

    wp = warp()
    kind, wkind = (np.int64, wp.int64) if integer else (np.float64, wp.float64)
    first, s0, passes = stepped_passes(q.shape, step, integer, axes, levels)
    dec = wp.zeros(q.shape, dtype=wkind, device=device)
    dec[first].assign(np.asarray(q[first] * (np.int64(s0) if integer else s0), kind))
    qq = wp.array(np.ascontiguousarray(q, np.int64), dtype=wp.int64, device=device)
    kernel = ki.decode_pass_i if integer else ki.decode_pass_f
    for dims, args in _launches(passes, q.shape, integer, interp == "cubic"):
        wp.launch(kernel, dim=dims, inputs=[qq, *args], outputs=[dec], device=device)
    return dec.numpy()


def _launches(passes, shape: tuple[int, ...], integer: bool, cubic: bool):
    """Each pass's launch: (dims, [start, stride, axis, h, cubic, step]); passes with no target left out."""
    from ..core.warp import warp

    wp = warp()
    for a, h, sel, s in passes:
        dims = tuple(len(range(x.start, n, x.step)) for x, n in zip(sel, shape))
        if min(dims) == 0:
            continue
        start = wp.vec3i(*(x.start for x in sel))
        stride = wp.vec3i(*(x.step for x in sel))
        yield dims, [start, stride, a, h, int(cubic), wp.int64(int(s)) if integer else wp.float64(s)]


def residual_device(device: str | None, n_voxels: int) -> str | None:
    """Where the bounded residual's interpolation passes run: the encode's device (the Warp CPU
    device too) where it holds their :data:`DEVICE_BYTES_PER_VOXEL`, else None (numpy); the
    bytes are the same either way."""
    from ..core.warp import resolve_device, warp

    wp = warp()
    dev = wp.get_device(resolve_device(device))
    if dev.is_cuda:
        free = getattr(dev, "free_memory", None)
        if free is not None and n_voxels * DEVICE_BYTES_PER_VOXEL > 0.8 * free:
            return None
    return str(dev)


def top_level(shape: tuple[int, ...]) -> int:
    return max(1, int(math.ceil(math.log2(max(max(shape), 2)))))


def stepped_passes(shape: tuple[int, ...], step: float, integer: bool, axes: str, levels: tuple[float, float]):
    """What the coder and every reader walk alike: the first voxel (the coarsest lattice, predicted
    as 0) and its step, then (axis, h, selection, step) of each interpolation pass."""
    first = (slice(0, 1),) * 3
    s0 = level_step(step, integer, levels, top_level(shape) + 1)
    passes = ((a, h, sel, level_step(step, integer, levels, h.bit_length())) for a, h, sel in interp_passes(shape, axes))
    return first, s0, passes


def decoded(
    q: np.ndarray, step: float, integer: bool, interp: str, axes: str = AXES, levels: tuple[float, float] = FLAT, device: str | None = None
) -> np.ndarray:
    """The decoded residual from its q's: what :func:`feedback` decoded, on any machine (the passes
    as Warp kernels on ``device``, the same bits; None: numpy)."""
    if not interp:
        return q * np.int64(step) if integer else q * step
    if device is not None:
        return decoded_on(device, q, step, integer, interp, axes, levels)
    dec = np.zeros(q.shape, np.int64 if integer else np.float64)
    first, s0, passes = stepped_passes(q.shape, step, integer, axes, levels)
    dec[first] = q[first] * (np.int64(s0) if integer else s0)
    for a, h, sel, s in passes:
        pred = interp_prediction(dec, a, h, sel, interp == "cubic")
        dec[sel] = pred + (q[sel] * np.int64(s) if integer else q[sel] * s)
    return dec
