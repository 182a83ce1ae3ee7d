"""A joint refit of the seams after the bricks: the primitives that reach an inner face refined
together over the whole grid (:func:`refit_seams`), every other primitive frozen; the share of
the iterations it gets is the schedule's (:mod:`.schedule`)."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from ...field.analysis import Field
from ..allocate import AllocationConfig
from ..refine.config import RefineConfig
from .bricks import MIN_BRICK_SAMPLES
from .plan import Brick, inner_faces, sigma_reach

SEAM_BAND = 2.0  # voxels beyond an inner face, past their 3-sigma reach, that make a primitive a seam's
SEAM_LR = 0.3  # the seams' refit runs at this share of the learning rate (see schedule.SEAM_REFIT)


def seam_rows(params: np.ndarray, bricks: list[Brick], shape_xyz, band: float | None = None) -> np.ndarray:
    """Which rows of ``params`` (volume coordinates) have a 3-sigma box within ``band`` (default
    :data:`SEAM_BAND`) voxels of an inner face of ``bricks`` (booleans)."""
    band = SEAM_BAND if band is None else float(band)
    reach = sigma_reach(params, 3.0) + band
    hit = np.zeros(len(params), bool)
    for axis, face in inner_faces(shape_xyz, bricks):  # mu columns are x, y, z; a face sits between voxels
        hit |= np.abs(params[:, 2 - axis].astype(np.float64) - (face - 0.5)) <= reach
    return hit


# True: the seams' refit draws its samples only in the 4^3 cells a stepped primitive's 3-sigma box
# reaches, at the whole grid's samples times their share of the voxels; False (the default): over
# the whole grid. Fewer samples would make the refit cheaper, but on the CPU at 96^3, N 12,000,
# bricks started together, a quarter of the iterations at 0.3x (benchmarks/bricked/seam_refit_cpu.py
# --samples-band 0,1, results/bricked/seam_refit96_band_cpu.json) it gave 52.54 dB against 52.54 on
# the vortex (97 % of the grid sampled) and 36.82 against 37.24 on the interface (69 %): the
# primitives are also moved by samples beyond 3 sigma. Not measured on a GPU.
SEAM_SAMPLES_BAND = False


def seam_support(params: np.ndarray, shape_xyz, cell: int = 4) -> np.ndarray:
    """Where ``params`` (volume coordinates) reach: the voxels (z, y, x booleans) of the ``cell``^3
    cells that some row's 3-sigma box (isotropic, by its largest sigma) overlaps."""
    nx, ny, nz = (int(v) for v in shape_xyz)
    dims = np.array([-(-nx // cell), -(-ny // cell), -(-nz // cell)])
    if len(params) == 0:
        return np.zeros((nz, ny, nx), bool)
    reach = sigma_reach(params, 3.0)
    mu = params[:, :3].astype(np.float64) + 0.5  # voxel i spans [i - 0.5, i + 0.5): cell of a point
    lo = np.clip(np.floor((mu - reach[:, None]) / cell).astype(np.int64), 0, dims - 1)
    hi = np.clip(np.floor((mu + reach[:, None]) / cell).astype(np.int64), 0, dims - 1) + 1
    diff = np.zeros(tuple(dims[::-1] + 1), np.int64)  # z, y, x: a 3D difference array of the boxes
    for corner in range(8):
        pick = [(hi if corner >> a & 1 else lo)[:, a] for a in range(3)]  # x, y, z
        sign = -1 if bin(corner).count("1") % 2 else 1
        np.add.at(diff, (pick[2], pick[1], pick[0]), sign)
    cover = diff.cumsum(0).cumsum(1).cumsum(2)[:-1, :-1, :-1] > 0
    return cover[np.ix_(np.arange(nz) // cell, np.arange(ny) // cell, np.arange(nx) // cell)]


def refit_seams(
    f: Field,
    bricks: list[Brick],
    params: np.ndarray,
    refine: RefineConfig,
    allocation: AllocationConfig,
    seed: int,
    device: str,
    share: float,
    dv=None,
) -> tuple[np.ndarray, dict]:
    """The merged bricks' ``params`` with the primitives near the inner faces (:func:`seam_rows`)
    refined together for ``share`` x ``refine.iterations`` over the whole field (``seed``: the
    refinement's), the others frozen; the same rows in the same order, and what was done. ``dv``:
    the field already on ``device`` (a :class:`~warpgauss.field.analysis.DeviceVolume`; None: put there)."""
    from ...field.analysis import DeviceVolume
    from ..refine import Refiner, load_kernels

    rows = seam_rows(params, bricks, f.shape_xyz)
    its = int(round(share * refine.iterations))
    facts = {"share": share, "iterations": its, "primitives": int(rows.sum()), "band_voxels": SEAM_BAND, "lr_scale": SEAM_LR}
    if its <= 0 or not rows.any():
        return params, facts
    load_kernels(device)
    t0 = time.perf_counter()
    voxels = int(np.prod(f.shape_xyz))
    cfg = dataclasses.replace(refine.for_budget(len(params), voxels, device), iterations=its, lr=refine.lr * SEAM_LR)
    train, frozen = params[rows], params[~rows]
    if SEAM_SAMPLES_BAND:  # only where a stepped primitive reaches, at the same samples per voxel
        band = seam_support(train, f.shape_xyz)
        valid = band if f.mask is None else band & f.mask
        share_voxels = int(valid.sum()) / voxels
        facts["sampled_share"] = share_voxels
        f = dataclasses.replace(f, mask=valid, n_valid=int(valid.sum()))
        cfg = dataclasses.replace(
            cfg, samples=min(cfg.samples, max(MIN_BRICK_SAMPLES, int(round(cfg.samples * share_voxels)))), auto_samples=False
        )
        dv = None
    r = Refiner(
        DeviceVolume(f, device) if dv is None else dv,
        np.concatenate([train, frozen]),
        cfg,
        seed,
        allocation.scale_min,
        allocation.resolved_cap(f.shape_xyz),
        frozen=len(frozen),
    )
    r.run(log_every=its)
    out = np.array(params, np.float32, copy=True)
    out[rows] = r.model_params()[: len(train)]
    return out, facts | {"samples": cfg.samples, "seconds": time.perf_counter() - t0}
