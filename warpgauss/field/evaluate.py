"""Stage EV: PSNR of a model against its normalised field (SPEC section 7).

PSNR = 10 log10(1 / MSE) on the normalised field at 500,000 voxel centres drawn uniformly with a
fixed evaluation seed, or on the full grid (on request, and always when the grid has no more
voxels than that). Masked (NaN/Inf/fill) voxels are left out of every metric. The model's values
are clamped to [0, 1], the source's range, as every decode clamps them; ``clamped_voxels`` counts
the voxels (or sampled points) that moved.
"""

from __future__ import annotations

import numpy as np

from .analysis import OCCUPIED, Field
from .gaussians import GaussianField

EVAL_POINTS = 500_000
EVAL_SEED = 2_026_1123
MSE_FLOOR = 1e-20  # reported PSNR saturates at 200 dB for an exact model
PSNR_CAP_DB = 200.0  # 10 log10(1 / MSE_FLOOR): what an exact decode (MSE 0) reports


def psnr_from_mse(mse: float) -> float:
    """10 log10(1 / MSE) on the normalised field, capped at :data:`PSNR_CAP_DB` (an exact decode,
    MSE 0, reports the cap rather than infinity, which JSON cannot hold)."""
    return float(10.0 * np.log10(1.0 / max(mse, MSE_FLOOR)))


def score_decode(out: np.ndarray, source: np.ndarray, valid: np.ndarray | None, value_range: tuple[float, float]) -> dict:
    """A bounded decode (the source's grid and units) scored against the source's own values in
    float64: the one measurement behind an encode's ``residual`` report and ``warpgauss eval``, so
    the two agree to the last digit (a lossless file: max abs error 0 and PSNR at the cap in both,
    where a float32 normalised copy of the source made eval see 7e-8 and 153 dB).

    Returns ``max_abs_error`` (source units), ``max_abs_error_normalised`` (a share of the value
    range), ``psnr_db`` and ``psnr_occupied_db`` (range-normalised, as :func:`evaluate_field`),
    ``mse``, ``points`` and ``occupied_points`` over the valid voxels."""
    lo, hi = float(value_range[0]), float(value_range[1])
    span = hi - lo if hi > lo else max(abs(lo), 1.0)  # a constant volume: its magnitude, as the residual's bound_rel
    src = np.asarray(source).astype(np.float64)
    err = np.asarray(out).astype(np.float64) - src
    if valid is not None:
        err, src = err[valid], src[valid]
    sq = (err / span) ** 2
    occ = (src - lo) / span > OCCUPIED
    worst = float(np.abs(err).max()) if err.size else 0.0
    mse = float(sq.mean()) if sq.size else 0.0
    n_occ = int(np.count_nonzero(occ))
    return {
        "max_abs_error": worst,
        "max_abs_error_normalised": worst / span,
        "psnr_db": psnr_from_mse(mse),
        "psnr_occupied_db": psnr_from_mse(float(sq[occ].mean())) if n_occ else None,
        "mse": mse,
        "points": int(sq.size),
        "occupied_points": n_occ,
    }


class _Accumulator:
    """float64 error sums over all and over occupied evaluation points."""

    def __init__(self):
        self.sse = self.sse_occ = 0.0
        self.n = self.n_occ = 0
        self.max_abs = 0.0

    def add(self, pred: np.ndarray, truth: np.ndarray, valid: np.ndarray | None) -> None:
        pred = pred.astype(np.float64).ravel()
        truth = truth.astype(np.float64).ravel()
        if valid is not None:
            pred, truth = pred[valid.ravel()], truth[valid.ravel()]
        err = pred - truth
        sq = err * err
        occ = truth > OCCUPIED
        self.sse += float(sq.sum())
        self.n += int(sq.size)
        self.sse_occ += float(sq[occ].sum())
        self.n_occ += int(np.count_nonzero(occ))
        if err.size:
            self.max_abs = max(self.max_abs, float(np.abs(err).max()))

    def result(self, mode: str) -> dict:
        mse = self.sse / max(self.n, 1)
        mse_occ = self.sse_occ / max(self.n_occ, 1)
        return {
            "psnr_db": psnr_from_mse(mse),
            "psnr_occupied_db": psnr_from_mse(mse_occ) if self.n_occ else None,
            "mse": mse,
            "max_abs_error": self.max_abs,
            "points": self.n,
            "occupied_points": self.n_occ,
            "mode": mode,
        }


def evaluate_field(gf: GaussianField, f: Field, *, full: bool = False, progress=None) -> dict:
    """PSNR, occupied-only PSNR, max abs error of ``gf`` against the normalised field ``f``.

    Args:
        gf: The model resident on a device.
        f: The normalised field it encodes (same grid).
        full: Evaluate every voxel instead of the 500,000-point sample.
        progress: Optional callback(done, total).
    """
    acc = _Accumulator()
    if full or f.n_voxels <= EVAL_POINTS:
        nz = f.values.shape[0]
        for z0, slab in gf.iter_slabs():
            z1 = z0 + slab.shape[0]
            acc.add(slab, f.values[z0:z1], None if f.mask is None else f.mask[z0:z1])
            if progress is not None:
                progress(z1, nz)
        res = acc.result("full grid")
        res["bricks_evaluated_share"] = gf.active_fraction  # the rest no primitive reaches: written 0
        res["clamped_voxels"] = gf.clamped_voxels  # decoded values outside the source's range, clamped
        return res
    idx = np.random.default_rng(EVAL_SEED).integers(0, f.n_voxels, EVAL_POINTS, dtype=np.int64)
    nz, ny, nx = f.values.shape
    pts = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1).astype(np.float32)
    if hasattr(f.values, "take_flat"):  # a volume read on demand (warpgauss.readers.lazy): by z-slabs
        truth = f.values.take_flat(idx)
        valid = None if f.mask is None else f.mask.take_flat(idx)  # type: ignore[attr-defined]
    else:
        truth = f.values.reshape(-1)[idx]
        valid = None if f.mask is None else f.mask.reshape(-1)[idx]
    pred = gf.evaluate(pts)
    outside = (pred < 0.0) | (pred > 1.0)
    acc.add(np.clip(pred, 0.0, 1.0), truth, valid)  # as a decode clamps (GaussianField.decode_slab)
    if progress is not None:
        progress(1, 1)
    res = acc.result(f"{EVAL_POINTS} sampled voxel centres (seed {EVAL_SEED})")
    res["clamped_voxels"] = int(np.count_nonzero(outside))  # of the sampled points
    return res


def evaluate_against(
    model, volume, *, full: bool = False, device: str | None = None, read=None, fill_value=None, residual: bool = True
) -> dict:
    """Evaluate a model against a volume (path or 3D array) normalised by the model's value range.

    Args:
        model: A :class:`warpgauss.Model`.
        volume: File path or (nz, ny, nx) array on the model's grid.
        full: Full grid instead of 500,000 sampled voxels.
        device: Warp device.
        read: :class:`warpgauss.readers.ReadOptions` for a file (stride defaults to the model's).
        fill_value: Source value marking missing data.
        residual: Score the bounded decode where the model has a residual (on the full grid,
            against the source's own values in float64 by :func:`score_decode`, as the encode's
            report did; the result adds ``bound`` and ``max_abs_error_source``, in source units);
            False: the Gaussians alone.

    Returns:
        ``psnr_db``, ``psnr_occupied_db``, ``mse``, ``max_abs_error`` (normalised: a share of the
        value range), ``max_abs_error_source`` (the same error in source units), ``points``,
        ``occupied_points``, ``mode``, ``n``; with the residual also ``bound`` (source units).
    """
    from ..errors import WarpgaussError
    from ..readers import ReadOptions
    from .analysis import normalise

    read = read or ReadOptions(stride=int(model.header.get("encoding", {}).get("stride", 1)))
    fill = fill_value if fill_value is not None else read.fill_value
    if isinstance(volume, np.ndarray):
        data = volume[:: read.stride, :: read.stride, :: read.stride]
    else:
        vol = read.read(volume)
        data = vol.data
        if fill is None:
            fill = getattr(vol, "fill_value", None)
    if data.ndim != 3:
        raise WarpgaussError(f"the volume is {data.ndim}D (shape {data.shape}); warpgauss encodes 3D volumes")
    shape_xyz = tuple(int(s) for s in data.shape[::-1])
    if shape_xyz != model.shape_xyz:
        raise WarpgaussError(
            f"the volume is {'x'.join(map(str, shape_xyz))} but the model's grid is "
            f"{'x'.join(map(str, model.shape_xyz))}; use the volume (and --stride) the model was encoded from"
        )
    f = normalise(data, fill_value=fill, value_range=model.value_range, count_candidates=False)
    if residual and model.residual is not None:
        out = model.decode(device=device, residual=True)
        s = score_decode(out, np.asarray(data), f.mask, model.value_range)  # as the encode's report measured it
        result = {
            "psnr_db": s["psnr_db"],
            "psnr_occupied_db": s["psnr_occupied_db"],
            "mse": s["mse"],
            "max_abs_error": s["max_abs_error_normalised"],
            "max_abs_error_source": s["max_abs_error"],
            "points": s["points"],
            "occupied_points": s["occupied_points"],
            "mode": "full grid, Gaussians and residual",
            "bound": float(model.residual.info["bound"]),
        }
    else:
        result = evaluate_field(model.field(device), f, full=full)
        lo, hi = model.value_range
        result["max_abs_error_source"] = result["max_abs_error"] * (hi - lo)  # the same error in source units
    result["n"] = model.n
    return result
