"""Bricked encoding: the grid split into bricks with a halo, the budget split before any refinement,
each brick encoded on its own (serially or on Dask workers), the primitives merged into one model.

A brick's seeds are drawn in its interior only (the halo is masked for the allocation), while its
training samples cover the halo too, so that primitives near a face see both sides of it. Values
are normalised once, by the whole volume's min/max, so every brick fits the same field. The budget
is split analytically from brick statistics, as the monolithic allocation would spend it: the
detail share floor(0.55 N) in proportion to each interior's sum of |grad V| over detail-eligible
voxels, the coverage share in proportion to its occupied voxels, rounded by largest remainders so
that the bricks hold exactly N, and no brick above its own seed limit.

Each brick is a pure function of its inputs (sub-volume, its count, the seed, the settings): the
same seed and bricking give the same model whether the bricks run in this process or on a Dask
cluster, in any order (tested bit for bit on the CPU). Dask moves only our own arrays and settings
between our own workers; no model or checkpoint is ever loaded through it.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .allocate import AllocationConfig
from .analysis import OCCUPIED, Field, count_seed_candidates, seed_limit, split_budget
from .errors import WarpgaussError
from .refine.config import RefineConfig

DEFAULT_HALO = 4  # voxels on each side: more than a sigma cap of 2 voxels' reach at 2 sigma


@dataclass(frozen=True)
class Brick:
    """One brick: its index, its interior and its halo box, ``(z, y, x)`` voxel slices as
    ``(start, stop)`` pairs (interior within the halo box)."""

    index: tuple[int, int, int]
    interior: tuple[tuple[int, int], ...]
    box: tuple[tuple[int, int], ...]

    def slices(self, which: str = "box") -> tuple[slice, ...]:
        return tuple(slice(a, b) for a, b in getattr(self, which))

    def interior_in_box(self) -> tuple[slice, ...]:
        return tuple(slice(i0 - b0, i1 - b0) for (i0, i1), (b0, _) in zip(self.interior, self.box))


def parse_bricks(text) -> tuple[int, int, int]:
    """'2x2x2' (x, y, z), an int (the same on every axis) or a 3-tuple -> counts (x, y, z)."""
    counts: tuple[int, ...]
    if isinstance(text, (int, np.integer)):
        counts = (int(text),) * 3
    elif isinstance(text, str):
        try:
            counts = tuple(int(p) for p in text.lower().replace(",", "x").split("x"))
        except ValueError:
            counts = ()
    else:
        counts = tuple(int(c) for c in text)
    if len(counts) != 3 or min(counts) < 1:
        raise WarpgaussError(f"--bricks must be three positive integers XxYxZ (e.g. 2x2x2), got {text!r}")
    return (counts[0], counts[1], counts[2])


def plan_bricks(shape_xyz, counts_xyz, halo: int = DEFAULT_HALO) -> list[Brick]:
    """Bricks of nearly equal size covering the grid (interiors disjoint), each with ``halo``
    voxels more on every side where the grid allows; x fastest in the list."""
    if halo < 0:
        raise WarpgaussError(f"the halo must be >= 0 voxels, got {halo}")
    shape_zyx = tuple(int(s) for s in shape_xyz)[::-1]
    counts_zyx = tuple(int(c) for c in counts_xyz)[::-1]
    for s, c, axis in zip(shape_zyx, counts_zyx, "zyx"):
        if c > s or s // c < 2:
            raise WarpgaussError(f"{c} bricks along {axis} leave fewer than 2 voxels each ({s} voxels); use fewer bricks")
    edges = [np.linspace(0, s, c + 1).round().astype(int) for s, c in zip(shape_zyx, counts_zyx)]
    out = []
    for k in range(counts_zyx[0]):
        for j in range(counts_zyx[1]):
            for i in range(counts_zyx[2]):
                idx = (k, j, i)
                interior = tuple((int(edges[a][idx[a]]), int(edges[a][idx[a] + 1])) for a in range(3))
                box = tuple((max(0, lo - halo), min(shape_zyx[a], hi + halo)) for a, (lo, hi) in enumerate(interior))
                out.append(Brick((i, j, k), interior, box))
    return out


def _grad_sum(values: np.ndarray, mask: np.ndarray | None, inner: tuple[slice, ...]) -> float:
    """Sum of |grad V| (central differences) over the detail-eligible voxels of ``inner``."""
    v = values.astype(np.float64)
    g = np.zeros_like(v)
    for axis in range(3):
        if v.shape[axis] > 1:
            g += np.gradient(v, axis=axis) ** 2
    g = np.sqrt(g)[inner]
    occ = v[inner] > OCCUPIED
    if mask is not None:
        occ &= mask[inner]
    return float(g[occ & (g > 0)].sum())


def seam_weights(brick: Brick) -> np.ndarray:
    """The brick's share of the field over its box: 1 inside, ramping linearly to 0 across the
    2 x halo band of every face it shares with a neighbour (separable over the axes), so that
    the shares of all bricks sum to 1 at every voxel. Each brick fits its share; the merged
    model, their sum, fits the field with no doubling where neighbouring boxes overlap."""
    shape = tuple(b1 - b0 for b0, b1 in brick.box)
    w = np.ones(shape, np.float32)
    for axis, ((i0, i1), (b0, b1)) in enumerate(zip(brick.interior, brick.box)):
        p = np.arange(b0, b1, dtype=np.float64)
        ramp = np.ones_like(p)
        lo, hi = i0 - b0, b1 - i1  # the halo on each side: > 0 only where a neighbour shares the face
        if lo > 0:
            ramp *= np.clip((p - (i0 - 0.5) + lo) / (2 * lo), 0.0, 1.0)
        if hi > 0:
            ramp *= np.clip(1.0 - (p - (i1 - 0.5) + hi) / (2 * hi), 0.0, 1.0)
        view = [1, 1, 1]
        view[axis] = len(p)
        w *= ramp.astype(np.float32).reshape(view)
    return w


def _field_meta(f: Field) -> dict[str, Any]:
    """What a brick's Field shares with the volume's: the normalisation and the source facts."""
    return dict(
        vmin=f.vmin,
        vmax=f.vmax,
        spacing=f.spacing,
        origin=f.origin,
        name=f.name,
        source_dtype=f.source_dtype,
        source_itemsize=f.source_itemsize,
    )


def face_band(shape_xyz, bricks: list[Brick], width: int = 2) -> np.ndarray:
    """Voxels within ``width`` of an inner brick face, (z, y, x) booleans: where seams show."""
    shape_zyx = tuple(int(s) for s in shape_xyz)[::-1]
    near = np.zeros(shape_zyx, bool)
    for b in bricks:
        for axis, (i0, i1) in enumerate(b.interior):
            for face in (i0, i1):
                if 0 < face < shape_zyx[axis]:
                    sl = [slice(None)] * 3
                    sl[axis] = slice(max(0, face - width), face + width)
                    near[tuple(sl)] = True
    return near


def brick_fields(f: Field, brick: Brick) -> tuple[Field, Field]:
    """(allocation field: the halo masked out; training field: the whole box), both normalised by
    the volume's min/max (the values as they are: the mixture's normalisation blends overlapping
    bricks; :func:`seam_weights` is kept for a blended-target experiment, unused by the encode)."""
    box = brick.slices("box")
    values = np.ascontiguousarray(f.values[box])
    valid = None if f.mask is None else np.ascontiguousarray(f.mask[box])
    interior = np.zeros(values.shape, bool)
    interior[brick.interior_in_box()] = True
    seed_mask = interior if valid is None else interior & valid
    base = _field_meta(f)
    occ, elig = count_seed_candidates(values, seed_mask)
    alloc = Field(values, seed_mask, occupied=occ, eligible=elig, n_valid=int(seed_mask.sum()), **base)
    t_occ, t_elig = count_seed_candidates(values, valid)
    n_valid = values.size if valid is None else int(valid.sum())
    train = Field(values, valid, occupied=t_occ, eligible=t_elig, n_valid=n_valid, **base)
    return alloc, train


def split_bricks(f: Field, bricks: list[Brick], n: int) -> tuple[list[int], list[dict]]:
    """Exactly ``n`` primitives over the bricks (see the module docstring), and each brick's
    statistics."""
    stats = []
    for b in bricks:
        box = b.slices("box")
        values = f.values[box]
        valid = None if f.mask is None else f.mask[box]
        alloc, _ = brick_fields(f, b)
        stats.append(
            {
                "occupied": alloc.occupied,
                "eligible": alloc.eligible,
                "grad_sum": _grad_sum(values, valid, b.interior_in_box()),
                "n_max": seed_limit(alloc.eligible, alloc.occupied),
            }
        )
    nd, nc = split_budget(n)
    grad_total = sum(s["grad_sum"] for s in stats) or 1.0
    occ_total = sum(s["occupied"] for s in stats) or 1
    want = np.array([nd * s["grad_sum"] / grad_total + nc * s["occupied"] / occ_total for s in stats])
    cap = np.array([s["n_max"] for s in stats])
    if cap.sum() < n:
        raise WarpgaussError(
            f"the bricks can hold at most {int(cap.sum()):,} primitives (their seed limits), fewer than {n:,}; use fewer bricks or a smaller budget"
        )
    counts = np.minimum(np.floor(want).astype(np.int64), cap)
    # largest remainders first; a brick at its seed limit passes its share on
    order = sorted(range(len(bricks)), key=lambda i: (-(want[i] - np.floor(want[i])), i))
    while counts.sum() < n:
        for i in order:
            if counts.sum() == n:
                break
            if counts[i] < cap[i]:
                counts[i] += 1
    for s, c, w in zip(stats, counts, want):
        s.update(n=int(c), share=float(w))
    return [int(c) for c in counts], stats


@dataclass
class BrickTask:
    """What one worker needs for one brick: plain arrays and settings (no model, no file)."""

    index: int
    brick: Brick
    values: np.ndarray
    valid: np.ndarray | None
    field_meta: dict
    n: int
    seed: int
    allocation: AllocationConfig
    refine: RefineConfig
    device: str | None


def brick_seed(seed: int, index: int) -> int:
    """The brick's own encoding seed, from the run's seed and its index (same for every run)."""
    return int((seed * 1_000_003 + 7919 * (index + 1)) % (2**31 - 1))


def encode_brick(task: BrickTask) -> dict:
    """Allocate and refine one brick; its primitives in the volume's voxel coordinates.

    Runs wherever it is called (this process or a Dask worker) on ``task.device`` (None: CUDA when
    present, else the CPU).
    """
    from ._warp import resolve_device
    from .allocate import allocate
    from .analysis import DeviceVolume
    from .profiling import StageRecorder

    t0 = time.perf_counter()
    dev = resolve_device(task.device)
    f = Field(task.values, task.valid, **task.field_meta)
    alloc_f, train_f = brick_fields(f, dataclasses.replace(task.brick, interior=_local(task.brick), box=_whole(task.brick)))
    if task.n == 0:
        return {
            "index": task.index,
            "params": np.zeros((0, 12), np.float32),
            "seconds": time.perf_counter() - t0,
            "device": dev,
            "iterations": 0,
        }
    params, _ = allocate(DeviceVolume(alloc_f, dev), task.n, task.seed, task.allocation, StageRecorder())
    iterations = 0
    cfg = task.refine
    if cfg.iterations > 0:
        from .refine import Refiner, load_kernels

        load_kernels(dev)
        voxels = int(np.prod(train_f.values.shape))
        cfg = cfg.for_budget(task.n, voxels, dev)
        refiner = Refiner(DeviceVolume(train_f, dev), params, cfg, task.seed, task.allocation.scale_min, task.allocation.scale_cap)
        refiner.run()
        params = refiner.model_params()
        iterations = refiner.iteration
    out = np.array(params, np.float32, copy=True)
    z0, y0, x0 = (a for a, _ in task.brick.box)
    out[:, 0] += x0
    out[:, 1] += y0
    out[:, 2] += z0
    return {"index": task.index, "params": out, "seconds": time.perf_counter() - t0, "device": dev, "iterations": iterations}


def _whole(b: Brick) -> tuple[tuple[int, int], ...]:
    return tuple((0, hi - lo) for lo, hi in b.box)


def _local(b: Brick) -> tuple[tuple[int, int], ...]:
    return tuple((i0 - b0, i1 - b0) for (i0, i1), (b0, _) in zip(b.interior, b.box))


def brick_tasks(f: Field, bricks: list[Brick], counts: list[int], seed: int, allocation, refine, device) -> list[BrickTask]:
    meta = _field_meta(f)
    tasks = []
    for i, (b, n) in enumerate(zip(bricks, counts)):
        box = b.slices("box")
        valid = None if f.mask is None else np.ascontiguousarray(f.mask[box])
        tasks.append(BrickTask(i, b, np.ascontiguousarray(f.values[box]), valid, meta, n, brick_seed(seed, i), allocation, refine, device))
    return tasks


def run_bricks(tasks: list[BrickTask], client=None, progress=None) -> list[dict]:
    """Every brick's result, in brick order: in this process (``client`` None) or on a Dask
    cluster, where a failed brick is retried once and a brick that fails twice fails the run."""
    if client is None:
        out = []
        for t in tasks:
            out.append(encode_brick(t))
            if progress is not None:
                progress(len(out), len(tasks))
        return out
    from distributed import as_completed

    futures = client.map(encode_brick, tasks, retries=1, pure=False, key=[f"warpgauss-brick-{t.index}-{id(t)}" for t in tasks])
    results: dict[int, dict] = {}
    try:
        for fut in as_completed(futures):
            r = fut.result()
            results[r["index"]] = r
            if progress is not None:
                progress(len(results), len(tasks))
    except Exception as e:  # a brick that failed twice (its retry included)
        for fut in futures:
            fut.cancel()
        raise WarpgaussError(
            f"a brick failed on the Dask cluster twice: {type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}; no model written"
        ) from None
    return [results[t.index] for t in tasks]


def local_client(workers: int):
    """A local Dask cluster of ``workers`` single-threaded processes (Warp's CPU device runs a
    kernel on one thread), and its client."""
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster)


def default_client(workers: int | None, scheduler: str | None, device: str | None):
    """The cluster a bricked encode runs on, and a note of why.

    ``scheduler``: connect to that running cluster. ``workers`` 0: this process. Otherwise a local
    cluster: one worker per GPU through dask-cuda where it is installed and several GPUs exist;
    this process on a single GPU (the bricks share it anyway); on the CPU ``workers`` processes
    (default: up to 4, one per core).
    """
    import os

    if scheduler is not None:
        from distributed import Client

        return Client(scheduler), f"the cluster at {scheduler}"
    if workers == 0:
        return None, "this process (--workers 0)"
    from ._warp import resolve_device, warp

    dev = resolve_device(device)
    if dev.startswith("cuda"):
        gpus = warp().get_cuda_device_count()
        if gpus > 1:
            try:
                from dask_cuda import LocalCUDACluster
                from distributed import Client
            except ImportError:
                return None, f"this process: {gpus} GPUs but dask-cuda is not installed (pip install dask-cuda)"
            return Client(
                LocalCUDACluster(n_workers=workers or gpus, threads_per_worker=1)
            ), f"a local cluster of {workers or gpus} GPU workers (dask-cuda)"
        return None, "this process (one GPU: the bricks share it)"
    k = workers or max(1, min(4, os.cpu_count() or 1))
    return local_client(k), f"a local cluster of {k} CPU processes"
