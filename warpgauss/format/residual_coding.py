"""The bounded residual's coder (:mod:`.residual`): the choices made on the source (the
interpolation's axis order and level-wise bounds on a central block; the final indices' storage
order and codec) and the predictors' codings, run side by side (:class:`Coder`)."""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from .interpolation import AXES, CHOOSE_BLOCK, FLAT, LEVELWISE, ORDERS, cast, feedback
from .planes import byte_planes, byte_width, bzip2_parts, compress, zigzag

# bzip2 tries the layouts Zstandard codes smallest, this many: on the three head MRIs at 1e-2 and
# 1e-3 of the range the smallest bzip2 frame was always in Zstandard's best two (see final_symbols)
BZIP2_LAYOUTS = 2
# on a tie the first: it needs no prediction. "-linear": linear interpolation where cubic would be used
# (cubic codes smaller on smooth fields and mean_reg2mean, linear on inia19: 83.7 against 76.9 at 1e-2)
PREDICTORS = ("interp", "interp-linear", "gaussians+interp", "gaussians+interp-linear", "gaussians")


def parts(name: str) -> tuple[bool, str]:
    """(the Gaussians used?, interpolation "cubic", "linear" or "" for none) of a predictor."""
    kind = "" if name == "gaussians" else "linear" if name.endswith("-linear") else "cubic"
    return name.startswith("gaussians"), kind


STREAMS = ("symbols", "positions", "values", "mask")
MIN_FRAME_BYTES = 9  # the smallest Zstandard frame (bzip2's is larger): a stream with content is at least this
LATTICE_LIMIT = float(1 << 50)  # |V / s| beyond this is stored outright (keeps every int64 sum exact)

CODE_BYTES_PER_VOXEL = 120  # host memory coding a residual takes: float64/int64 copies of the grid, and the chosen indices in six storage orders on threads (measured: 101-114 on the head MRIs at 1e-2 and 1e-4)
# what one predictor's coding holds at once beside that (the differences, q's, decoded values, the
# checks, the zigzagged q's), for the codings run on threads side by side
CANDIDATE_BYTES_PER_VOXEL = 56


def choose_interpolation(
    source: np.ndarray, usable: np.ndarray, step: float, integer: bool, device: str | None = None
) -> tuple[str, dict[str, tuple[float, float]]]:
    """The interpolation's axis order, and each kind's level-wise bounds, that code a central block
    of the source (at most :data:`CHOOSE_BLOCK` a side, no Gaussians, Zstandard 3) smallest: the
    order first (cubic, flat bounds), then (alpha, beta) from :data:`LEVELWISE` for "cubic" and for
    "linear"; ties to the earlier (the passes on ``device``: the same bits). Measured on the three
    head MRIs at 1e-2 and 1e-3: the block picked the order that is best or within 0.1 % of it on
    the whole volume."""
    flat = {"cubic": FLAT, "linear": FLAT}
    if min(source.shape) < 4:
        return AXES, flat
    sl = tuple(slice(max(0, n // 2 - CHOOSE_BLOCK // 2), max(0, n // 2 - CHOOSE_BLOCK // 2) + CHOOSE_BLOCK) for n in source.shape)
    block, ok = source[sl], usable[sl]
    with np.errstate(invalid="ignore", over="ignore"):
        t = np.where(ok, block, 0).astype(np.int64) if integer else np.where(ok, block.astype(np.float64), 0.0)

    def size(kind: str, axes: str, levels: tuple[float, float]) -> int:
        q, _ = feedback(t, ~ok, step, integer, kind, axes, levels, device)
        u = zigzag(q.ravel())
        return len(compress(byte_planes(u, byte_width(u)), 3))

    by_axes = {axes: size("cubic", axes, FLAT) for axes in ORDERS}
    axes = min(ORDERS, key=lambda a: (by_axes[a], ORDERS.index(a)))
    chosen = {}
    for kind in ("cubic", "linear"):
        sizes = [size(kind, axes, lw) for lw in LEVELWISE]
        chosen[kind] = LEVELWISE[int(np.argmin(sizes))]
    return axes, chosen


def final_symbols(u: np.ndarray) -> tuple[bytes, str, str]:
    """The chosen predictor's zigzagged q's (on the grid, in their narrowest width) coded harder:
    in each of the six axis orders (``layout``: the array transposed so, then raster) with
    Zstandard, and in the :data:`BZIP2_LAYOUTS` orders Zstandard coded smallest with bzip2 too (its
    Burrows-Wheeler transform suits runs of small q's: 15-25 % below Zstandard 3 on the head MRIs,
    at 10-20x its time; in parts on threads, :func:`~.planes.bzip2_parts`); the smallest kept.
    Returns (frame, codec, layout)."""
    width = u.dtype.itemsize

    def raw(layout: str) -> bytes:
        return byte_planes(np.ascontiguousarray(u.transpose([int(c) for c in layout])).ravel(), width)

    def zstd(layout: str) -> tuple[int, int, bytes, str, str]:
        f = compress(raw(layout))
        return len(f), ORDERS.index(layout), f, "zstd", layout

    workers = max(1, os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=workers) as pool:  # bz2 and Zstandard let go of the GIL
        tried = list(pool.map(zstd, ORDERS))
        best = [t[4] for t in sorted(tried, key=lambda t: (t[0], t[1]))[:BZIP2_LAYOUTS]]
        raws = list(pool.map(raw, best))
        with ThreadPoolExecutor(max_workers=workers) as part_pool:  # each layout's parts beside the other's
            coded = list(pool.map(lambda r: bzip2_parts(r, part_pool), raws))
        tried += [(len(f), ORDERS.index(lay), f, codec, lay) for lay, (f, codec) in zip(best, coded)]
    _, _, frame, codec, layout = min(tried, key=lambda t: (t[0], t[1], t[3]))
    return frame, codec, layout


class Coder:
    """The codings of one residual: each predictor's error-feedback passes (from the calling thread,
    where a device runs them: Warp's streams belong to it) and its streams (on threads)."""

    def __init__(self, source, valid, pred, fragile, bound: float, margin: float, step: float, integer: bool, out_dtype, device=None):
        self.source, self.valid, self.pred, self.fragile = source, valid, pred, fragile
        self.bound, self.margin, self.step, self.integer, self.out_dtype, self.device = bound, margin, step, integer, out_dtype, device
        self.ok = np.ones(source.shape, bool) if valid is None else valid
        self.src64 = source.astype(np.float64)
        self.seconds: dict = {"passes": {}, "code": {}}  # where the coding's time went (the report's residual.seconds)
        t0 = time.perf_counter()
        self.axes, self.levelwise = choose_interpolation(source, self.ok & np.isfinite(self.src64), step, integer, device)
        self.seconds["choose"] = time.perf_counter() - t0
        self.lattice: dict[bool, tuple] = {}  # by gauss: what the passes code (base, shaky, t, fits), the same for both kinds

    def prepare(self, gauss: bool) -> None:
        base_, shaky = base(self.pred, self.fragile, self.margin, self.integer, gauss)
        with np.errstate(invalid="ignore", over="ignore"):
            t = self.source.astype(np.int64) - base_ if self.integer else self.src64 - base_
            fits = self.ok & np.isfinite(self.src64) & (np.abs(t) < LATTICE_LIMIT * self.step)
        self.lattice[gauss] = base_, shaky, t, fits

    def passes(self, name: str):
        t0 = time.perf_counter()
        gauss, kind = parts(name)
        if gauss not in self.lattice:
            self.prepare(gauss)
        base_, shaky, t, fits = self.lattice[gauss]
        q_dec = feedback(t, ~fits, self.step, self.integer, kind, self.axes, self.levelwise.get(kind, FLAT), self.device)
        self.seconds["passes"][name] = time.perf_counter() - t0
        return base_, shaky, fits, q_dec

    def code(self, name: str, done_passes=None) -> tuple[int, dict[str, bytes], np.ndarray, int, np.ndarray]:
        """(bytes, streams, literal voxels, index width, zigzagged indices) of one predictor."""
        gauss, _ = parts(name)
        base_, shaky, fits, (q, dec) = self.passes(name) if done_passes is None else done_passes
        t0 = time.perf_counter()
        x = base_ + dec
        if self.integer or not gauss:
            good = within(x, self.out_dtype, self.src64, self.bound)
        else:  # a reader's prediction lies within the margin: every value between decodes within the bound
            good = within(x - self.margin, self.out_dtype, self.src64, self.bound) & within(
                x + self.margin, self.out_dtype, self.src64, self.bound
            )
        literal = self.ok & ~(fits & good & ~shaky)
        u = zigzag(q.ravel())
        width = byte_width(u)
        coded = streams(u, width, literal, self.source.astype(self.out_dtype, copy=False), self.valid)
        self.seconds["code"][name] = time.perf_counter() - t0
        return sum(len(b) for b in coded.values()), coded, literal, width, u.astype(f"<u{width}").reshape(q.shape)

    def best(self, predictors: tuple[str, ...], sizes: dict[str, int]) -> tuple[int, str, dict[str, bytes], np.ndarray, int, np.ndarray]:
        """The smallest coding, in the serial order (the result a serial loop gives); ``sizes``
        gets every predictor the rule codes. The predictors that do not depend on others' sizes
        are coded on threads (numpy and Zstandard release the GIL), then the Gaussians plus the
        interpolation that coded smaller. On a device the passes run one after the other, each
        predictor's coding on a thread as soon as its passes are done; where the threads and memory
        allow, the Gaussians plus both interpolations too (the one the rule picks is kept, the
        other dropped: the same file, without a coding after the others)."""
        done: dict[str, tuple[int, dict[str, bytes], np.ndarray, int, np.ndarray]] = {}
        alone = [n for n in predictors if not all(parts(n))]
        both = [n for n in predictors if all(parts(n))]
        n = self.source.size
        ahead = alone + both if self.device is not None and coding_threads(len(alone) + len(both), n) >= len(alone) + len(both) else alone
        for gauss in sorted({parts(p)[0] for p in ahead}):  # here, not racing on the threads
            self.prepare(gauss)
        with ThreadPoolExecutor(max_workers=coding_threads(len(ahead), n)) as ex:
            coding = [ex.submit(self.code, p, self.passes(p) if self.device is not None else None) for p in ahead]
            done.update(zip(ahead, (c.result() for c in coding)))
        del coding
        self.lattice.pop(False, None)  # the interpolations' alone: not needed again
        alone_sizes = {p: done[p][0] for p in alone}
        best = None
        for name in candidates(predictors, alone_sizes):
            if name not in done:
                done[name] = self.code(name)
            sizes[name] = done[name][0]
            if best is None or done[name][0] < best[0]:
                best = (done[name][0], name, *done[name][1:])
        assert best is not None
        return best


def coding_threads(jobs: int, n_voxels: int) -> int:
    """Threads for ``jobs`` predictor codings at once: the cores, and what memory holds beside the
    coding's own :data:`CODE_BYTES_PER_VOXEL` (:data:`CANDIDATE_BYTES_PER_VOXEL` a coding)."""
    from ..core.limits import available_memory

    free = available_memory()
    room = jobs if free is None else int((free - n_voxels * CODE_BYTES_PER_VOXEL) // max(n_voxels * CANDIDATE_BYTES_PER_VOXEL, 1))
    return max(1, min(jobs, os.cpu_count() or 1, room))


def candidates(predictors: tuple[str, ...], sizes: dict[str, int]):
    """The predictors to code, in order; the Gaussians plus interpolation only with the kind that
    coded smaller alone (``sizes`` fills as they are coded), so four codings and not five."""
    for name in predictors:
        gauss, kind = parts(name)
        cubic, linear = sizes.get("interp"), sizes.get("interp-linear")
        if gauss and kind and cubic is not None and linear is not None and kind != ("cubic" if cubic <= linear else "linear"):
            continue
        yield name


def base(pred: np.ndarray, fragile: np.ndarray, margin: float, integer: bool, gauss: bool) -> tuple[np.ndarray, np.ndarray]:
    """What the residual is added to (the Gaussians, rounded on an integer step; or 0) and the
    voxels where a reader's may differ (a pair on the cut; a prediction within the margin of .5)."""
    if not gauss:
        return np.zeros(pred.shape, np.int64 if integer else np.float64), np.zeros(pred.shape, bool)
    if not integer:
        return pred, fragile
    ambiguous = np.abs(pred - np.floor(pred) - 0.5) <= margin + 4e-16 * np.abs(pred)
    return np.rint(pred).astype(np.int64), fragile | ambiguous


def within(x: np.ndarray, dtype: np.dtype, src64: np.ndarray, bound: float) -> np.ndarray:
    with np.errstate(invalid="ignore", over="ignore"):
        return np.abs(cast(x, dtype).astype(np.float64) - src64) <= bound


def streams(u: np.ndarray, width: int, literal: np.ndarray, source: np.ndarray, valid: np.ndarray | None) -> dict[str, bytes]:
    pos = np.flatnonzero(literal.ravel()).astype(np.int64)
    gaps = np.diff(pos, prepend=np.int64(0)).astype("<u8")
    return {
        "symbols": compress(byte_planes(u, width)),
        "positions": compress(byte_planes(gaps, 8)),
        "values": compress(np.ascontiguousarray(source.ravel()[pos]).astype(source.dtype.newbyteorder("<")).tobytes()),
        "mask": b"" if valid is None else compress(np.packbits(~valid.ravel()).tobytes()),
    }
