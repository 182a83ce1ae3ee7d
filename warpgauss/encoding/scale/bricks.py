"""Bricked encoding: the grid split into bricks with a halo, the budget split before any refinement,
each brick encoded on its own (serially or on Dask workers), the primitives merged into one model.

A brick's own seeds are drawn in its interior only, while its training samples cover the halo
too. The model's value is a normalised blend (a primitive's effect depends on its neighbours), so
a brick must be fitted beside what the merged model will hold around it: the bricks run in waves
(:func:`brick_colour`, bricks of one wave share no box), and a brick refines its own primitives
beside the finished neighbours' primitives that reach its box (frozen: evaluated, never moved)
and beside stand-ins for the neighbours still to come (seeded in their part of the halo at the
density the budget rule gives there, refined, then dropped). The merged model holds only the
bricks' own primitives: exactly N. A brick caps sigma by the primitive spacing and its default
halo is twice that cap (:func:`warpgauss.encoding.scale.plan.brick_cap`, :func:`~warpgauss.encoding.scale.plan.default_halo`). Measured
(``benchmarks/bricked/README_seams_and_out_of_core.md``, H100, 2x2x2): without the frozen neighbours and stand-ins a
bricking lost 15.7 dB on a 512^3 vortex and 11.5 dB on the interface; with them and the cap,
-0.35 / +0.33 dB at 512^3 and -0.38 / +0.71 dB at 1024^3, in 2.4-3.2x the monolithic time.

Values are normalised once, by the whole volume's min/max, so every brick fits the same field. The
budget is split analytically from brick statistics, as the monolithic allocation would spend it:
the detail share floor(0.55 N) in proportion to each interior's sum of |grad V| over
detail-eligible voxels, the coverage share in proportion to its occupied voxels, rounded by
largest remainders so that the bricks hold exactly N, and no brick above its own seed limit. A
brick draws the monolithic encode's samples per iteration times its box's share of the grid
(:func:`brick_samples`).

Each brick is a pure function of its inputs (sub-volume, its count, the seed, the settings, the
finished neighbours): the same seed and bricking give the same model whether the bricks run in
this process or on a Dask cluster (tested bit for bit on the CPU). Dask (:mod:`warpgauss.encoding.scale.cluster`) moves only our own arrays
and settings between our own workers; no model or checkpoint is ever loaded through it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Generator
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...core.limits import brick_device_bytes, default_device_limit
from ...core.together import finish
from ...field.analysis import Field, count_seed_candidates, seed_limit
from ..allocate import AllocationConfig
from ..refine.config import RefineConfig
from .plan import Brick, grad_sum, sigma_reach

MIN_BRICK_SAMPLES = 512  # samples per iteration a brick draws at least


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


@dataclass(frozen=True)
class BrickFields:
    """A brick's three views of its box, all normalised by the volume's min/max (values as they
    are): ``interior`` and ``halo`` mask the seeds (the brick's own primitives, and the stand-ins
    for its pending neighbours' that are trained beside them and dropped), ``train`` is the whole
    box."""

    interior: Field
    halo: Field
    train: Field
    halo_grad_sum: float | None = None  # |grad V| over the halo's occupied voxels, where taken on the device


# A brick's start on the device (its masks, counts and sums by warpgauss.field.boxstats, its box a view of
# the volume put there once or uploaded) rather than on the host: None (the default) where the
# brick runs on CUDA. At 1024^3 in 2x2x2 bricks (one H200) the host's passes took 1.9 s of each
# brick's 2.2 s start while the GPU waited (results/bricked/setup_profile_1024_h200.json). The
# counts are the host's exactly; the stand-ins' |grad V| sum differs in its last bits.
DEVICE_SETUP: bool | None = None


def device_setup(device: str) -> bool:
    """Whether a brick on ``device`` starts on the device (:data:`DEVICE_SETUP`)."""
    from ...core.warp import warp

    return bool(warp().get_device(device).is_cuda) if DEVICE_SETUP is None else DEVICE_SETUP


def resident_volume(dv) -> tuple[Any, Any]:
    """A :class:`~warpgauss.field.analysis.DeviceVolume` as a task's ``volume``: the bricks of this
    process cut their boxes from it on the device (no host copy, no upload)."""
    from ...field.device import DeviceMask, DeviceValues

    return DeviceValues(dv.values), DeviceMask(dv.mask) if dv.has_mask else None


def resident_bytes(dv) -> int:
    """The device bytes a :class:`~warpgauss.field.analysis.DeviceVolume` holds (values and mask)."""
    return int(dv.values.capacity) + (int(dv.mask.capacity) if dv.has_mask else 0)


def device_brick_fields(values: Any, valid: Any, brick: Brick, pending: tuple | None, meta: dict) -> BrickFields:
    """:func:`brick_fields` where the box is on a device: ``values`` (Warp float32, the box alone)
    and ``valid`` (Warp uint8 or None); ``brick`` in box coordinates. The fields hold device
    arrays (:class:`~warpgauss.field.device.DeviceValues`, :class:`~warpgauss.field.device.DeviceMask`)."""
    from ...field.boxstats import box_counts, region_mask
    from ...field.device import DeviceMask, DeviceValues

    shape = tuple(int(s) for s in values.shape)
    dev = str(values.device)
    inner = tuple(brick.interior)
    regions = [tuple((0, n) for n in shape)] if pending is None else [tuple(r) for r in pending]
    own = region_mask(shape, dev, [inner], valid=valid)
    halo = region_mask(shape, dev, regions, exclude=inner, valid=valid)
    box: Any = DeviceValues(values)  # a Field's values where they live, as devicefield's fields hold them

    def masked(m: Any) -> tuple[Field, float]:
        c = box_counts(values, m)
        on: Any = None if m is None else DeviceMask(m)
        return Field(box, on, occupied=c.occupied, eligible=c.eligible, n_valid=c.n_valid, **meta), c.grad_sum

    (fi, _), (fh, g), (ft, _) = masked(own), masked(halo), masked(valid)
    return BrickFields(fi, fh, ft, halo_grad_sum=g)


def brick_fields(f: Field, brick: Brick, pending: tuple | None = None) -> BrickFields:
    """The brick's :class:`BrickFields`; ``pending``: the parts of the box (``(z, y, x)`` start,
    stop pairs in box coordinates) where stand-ins go (None: the whole halo)."""
    box = brick.slices("box")
    values = np.ascontiguousarray(f.values[box])
    valid = None if f.mask is None else np.ascontiguousarray(f.mask[box])
    inner = np.zeros(values.shape, bool)
    inner[brick.interior_in_box()] = True
    base = _field_meta(f)

    def masked(m: np.ndarray | None) -> Field:
        occ, elig = count_seed_candidates(values, m)
        return Field(values, m, occupied=occ, eligible=elig, n_valid=values.size if m is None else int(m.sum()), **base)

    halo = ~inner
    if pending is not None:
        halo = np.zeros(values.shape, bool)
        for region in pending:
            halo[tuple(slice(a, b) for a, b in region)] = True
        halo &= ~inner
    own = inner if valid is None else inner & valid
    return BrickFields(masked(own), masked(halo if valid is None else halo & valid), masked(valid))


@dataclass
class BrickTask:
    """What one worker needs for one brick: plain arrays and settings (no model, no file).

    The box's voxels come from ``values``/``valid`` (the box alone, copied) or, with those None,
    from ``volume``: the volume's (values, mask or None), read box by box where the task runs: a
    file read on demand (:class:`~warpgauss.readers.lazy.LazyValues`), a file this machine shares
    (:class:`~warpgauss.readers.lazy.Shared`) or, in this process, the arrays themselves (a task sent to
    another machine takes its box along: :meth:`shipped`).

    ``frozen``: the finished neighbours' primitives that reach the box (box coordinates), trained
    beside and never moved; ``pending``: where in the box the unfinished neighbours' interiors lie
    (stand-ins go there); ``rates``: how many stand-ins a region gets (see :func:`split_bricks`).
    """

    index: int
    brick: Brick
    values: np.ndarray | None  # None: read from ``volume`` where the task runs
    valid: np.ndarray | None
    field_meta: dict
    n: int
    seed: int
    allocation: AllocationConfig
    refine: RefineConfig
    device: str | None
    rates: tuple[float, float] = (0.0, 0.0)
    frozen: np.ndarray | None = None
    pending: tuple = ()
    volume: tuple | None = None  # (values, mask or None) of the whole volume, read box by box
    beside: bool = False  # steps beside other bricks (a wave of several): see SIDE_BY_SIDE_SPLIT

    def box_arrays(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The brick's box: normalised values and validity (read now from ``volume``)."""
        if self.values is not None or self.volume is None:
            return self.values, self.valid  # type: ignore[return-value]
        box = self.brick.slices("box")
        values, mask = self.volume
        return np.ascontiguousarray(values[box]), None if mask is None else np.ascontiguousarray(mask[box])

    def on_device(self) -> bool:
        """Whether the box comes from a volume on this process's device (:func:`resident_volume`)."""
        from ...field.device import DeviceValues

        return self.values is None and self.volume is not None and isinstance(self.volume[0], DeviceValues)

    def device_box(self, device: str) -> tuple[Any, Any]:
        """The brick's box on ``device``: Warp values and validity (uint8, or None), a contiguous
        copy of a view where the volume is on that device already, else the box uploaded."""
        from ...core.warp import warp

        wp = warp()
        if self.volume is not None and self.on_device():
            from ...field.boxstats import box_view

            values, mask = self.volume
            return (
                wp.clone(box_view(values.array, self.brick.box), device=device),
                None if mask is None else wp.clone(box_view(mask.array, self.brick.box), device=device),
            )
        from ...field.analysis import mask_to_device

        values, valid = self.box_arrays()
        return wp.array(values, dtype=float, device=device), None if valid is None else mask_to_device(valid, device)

    def shipped(self) -> BrickTask:
        """This task as it may travel to any process: a volume held in this process's memory is
        replaced by the box's own copy (files, read on demand or shared, travel by name)."""
        if self.on_device():
            raise ValueError("internal: a task whose volume is on this process's device cannot travel")
        if self.volume is None or not isinstance(self.volume[0], np.ndarray):
            return self
        values, valid = self.box_arrays()
        return dataclasses.replace(self, values=values, valid=valid, volume=None)


def brick_seed(seed: int, index: int) -> int:
    """The brick's own encoding seed, from the run's seed and its index (same for every run)."""
    return int((seed * 1_000_003 + 7919 * (index + 1)) % (2**31 - 1))


def stand_in_count(fields: BrickFields, rates: tuple[float, float]) -> int:
    """Stand-ins for the pending neighbours' primitives in ``fields.halo``: as many as the budget
    rule gives that region (detail by its |grad V| sum, coverage by its occupied voxels)."""
    h = fields.halo
    if h.occupied == 0:
        return 0
    g = grad_sum(h.values, h.mask) if fields.halo_grad_sum is None else fields.halo_grad_sum
    want = rates[0] * g + rates[1] * h.occupied
    return int(min(round(want), seed_limit(h.eligible, h.occupied)))


def encode_brick(task: BrickTask) -> dict:
    """Allocate and refine one brick; its own primitives in the volume's voxel coordinates (every
    step of :func:`brick_job`)."""
    return finish(brick_job(task))


def encode_bricks(tasks: list[BrickTask], at_once: int | None = None, limit: int | None = None, on_done=None) -> list[dict]:
    """Several bricks (of one wave: they share no box) on one device, ``at_once`` of them stepping
    side by side (:func:`warpgauss.core.together.run_together`; default: as many as
    :func:`bricks_at_once` lets ``limit`` bytes of the device hold, one at a time on the CPU). Each brick's result is
    the one :func:`encode_brick` gives, bit for bit. Runs wherever it is called (a Dask worker
    takes a group of a wave's bricks this way; this process a whole wave). ``on_done(i, result)``
    as each brick ends."""
    from ...core.together import run_together
    from ...core.warp import resolve_device

    if not tasks:
        return []
    dev = resolve_device(tasks[0].device)
    if at_once is None:
        at_once = bricks_at_once(tasks, dev, limit)
    t0 = time.perf_counter()
    out = run_together([functools.partial(brick_job, t) for t in tasks], dev, at_once, on_done=on_done)
    facts = _group_facts(dev, time.perf_counter() - t0, at_once)
    return [r | facts for r in out]


def prepare_brick(task: BrickTask, device: str | None = None) -> tuple[Field, BrickFields]:
    """A brick's work before its refinement: its box (read or copied) as a :class:`Field` and its
    :class:`BrickFields`, on the host, or on ``device`` where :func:`device_setup` says so (a pure
    function of the task)."""
    local = dataclasses.replace(task.brick, interior=task.brick.interior_local(), box=_whole(task.brick))
    if device is not None and device_setup(device):
        values, valid = task.device_box(device)
        fields = device_brick_fields(values, valid, local, task.pending, task.field_meta)
        return fields.train, fields
    values, valid = task.box_arrays()
    f = Field(values, valid, **task.field_meta)
    return f, brick_fields(f, local, task.pending)


def _group_facts(dev: str, seconds: float, at_once: int) -> dict:
    """What a group of bricks reports of the process that ran it: bricks at once, the group's
    seconds, the process (a Dask worker's name, else "this process") and its high-water marks of
    device memory (Warp's pool; None on the CPU) and host memory (peak RSS)."""
    from ...core.profiling import peak_rss_bytes
    from ...core.warp import warp

    wp = warp()
    d = wp.get_device(dev)
    peak = int(wp.get_mempool_used_mem_high(dev)) if d.is_cuda and wp.is_mempool_enabled(dev) else None
    worker = "this process"
    try:
        from distributed import get_worker

        worker = str(get_worker().name)
    except (ImportError, ValueError):
        pass
    rss = peak_rss_bytes()  # this worker's own (ru_maxrss holds the client's peak in a spawned worker)
    return {"at_once": at_once, "group_seconds": seconds, "worker": worker, "device_peak_bytes": peak, "host_peak_rss_bytes": rss}


def brick_job(task: BrickTask) -> Generator[None, None, dict]:
    """One brick's encode, a refinement iteration per ``next()``; its result as the return value.

    The brick's own seeds are drawn in its interior; stand-ins for the pending neighbours in their
    part of the halo, and the finished neighbours' primitives, are refined beside them (the
    stand-ins stepped and then dropped, the finished ones never moved), so that the brick's own
    primitives are fitted to what the merged model will hold around them. Runs wherever it is
    called (this process or a Dask worker) on ``task.device`` (None: CUDA when present, else the
    CPU).
    """
    from ...core.warp import resolve_device

    t0 = time.perf_counter()
    dev = resolve_device(task.device)
    done = {"index": task.index, "device": dev, "iterations": 0, "stand_ins": 0, "frozen": 0, "samples": 0}
    if task.n == 0:
        return done | {"params": np.zeros((0, 12), np.float32), "seconds": time.perf_counter() - t0}
    params, refiner, k = brick_refiner(task, dev)
    if refiner is not None:
        cfg, frozen = task.refine, 0 if task.frozen is None else len(task.frozen)
        t1 = time.perf_counter()
        yield from refiner.steps()
        params = refiner.model_params()[: task.n]
        done["setup_seconds"], done["refine_seconds"] = t1 - t0, time.perf_counter() - t1
        done.update(iterations=refiner.iteration, stand_ins=k, frozen=frozen, samples=cfg.samples)
        if refiner.iteration > 0:  # the coded grids follow the accuracy (the driver's coded_bits)
            done["sample_psnr_db"] = refiner.losses()["sample_psnr_db"]
    out = np.array(params, np.float32, copy=True)
    out[:, :3] += _origin_xyz(task.brick)
    return done | {"params": out, "seconds": time.perf_counter() - t0}


def brick_refiner(task: BrickTask, dev: str, timer=None):
    """A brick's start: ``(own, refiner, stand-ins)``: its own primitives allocated in its interior
    (box coordinates), and, when it refines, the refiner over its box that holds them, the
    stand-ins for the pending neighbours (another RNG stream than the brick's own seeds) and the
    finished neighbours' primitives (frozen), with the number of stand-ins (``refiner`` None and
    0 without refinement). ``timer``: a :class:`~warpgauss.core.profiling.StageRecorder` that times
    each phase (with its ``device`` set, synchronised: a profile; None: untimed)."""
    from ...core.profiling import StageRecorder
    from ...field.analysis import DeviceVolume
    from ..allocate import allocate

    timer = StageRecorder() if timer is None else timer
    with timer.stage("Bh", "box cut, masks and seed-candidate counts"):
        f, fields = prepare_brick(task, dev)
    with timer.stage("Bu", "box values and masks to the device"):
        train = DeviceVolume(fields.train, dev)  # the box's values go to the device once, for all three masks
        inner = DeviceVolume(fields.interior, dev, train)
    params, _ = allocate(inner, task.n, task.seed, task.allocation, timer)
    if task.refine.iterations <= 0:
        return params, None, 0
    from ..refine import Refiner, load_kernels

    parts = [np.asarray(params, np.float32)]
    with timer.stage("Bs", "stand-in count"):
        k = stand_in_count(fields, task.rates)
    if k:
        with timer.stage("Bu", "box values and masks to the device"):
            halo = DeviceVolume(fields.halo, dev, train)
        stand_ins, _ = allocate(halo, k, task.seed + 1, task.allocation, timer)
        parts.append(np.asarray(stand_ins, np.float32))
    frozen = np.zeros((0, 12), np.float32) if task.frozen is None else task.frozen
    parts.append(frozen)
    load_kernels(dev)
    with timer.stage("Br", "refiner set-up"):
        refiner = Refiner(
            train,
            np.concatenate(parts),
            task.refine,
            task.seed,
            task.allocation.scale_min,
            task.allocation.resolved_cap(f.shape_xyz),  # set by the bricked driver (brick_cap)
            frozen=len(frozen),
            split_dense=SIDE_BY_SIDE_SPLIT or not task.beside,
        )
    return params, refiner, k


def _origin_xyz(b: Brick) -> np.ndarray:
    return np.array([b.box[2][0], b.box[1][0], b.box[0][0]], np.float32)


def _whole(b: Brick) -> tuple[tuple[int, int], ...]:
    return tuple((0, hi - lo) for lo, hi in b.box)


def brick_samples(refine: RefineConfig, n: int, shape_xyz, brick: Brick, device: str) -> RefineConfig:
    """The brick's refinement settings: the monolithic encode's samples per iteration (for ``n``
    on the whole grid) times the brick box's share of the grid's voxels, at least
    :data:`MIN_BRICK_SAMPLES`, so that the bricks together draw about what the monolithic encode
    draws (more by the halos' overlap), at the same samples per primitive."""
    if refine.iterations == 0:
        return refine
    total = int(np.prod(shape_xyz))
    whole = refine.for_budget(n, total, device).samples
    box = brick.box_voxels
    s = max(MIN_BRICK_SAMPLES, int(round(whole * box / total)))
    return dataclasses.replace(refine, samples=s, auto_samples=False)


def brick_tasks(
    f: Field,
    bricks: list[Brick],
    stats: list[dict],
    seed: int,
    allocation,
    refine,
    device,
    n: int | None = None,
    volume: tuple | None = None,
) -> list[BrickTask]:
    """One task per brick, from :func:`split_bricks`' statistics (``n``, ``rates``); the
    samples per brick by :func:`brick_samples` (``n``: the whole budget, default the bricks' sum).
    Each task reads its box from ``volume`` (default the field's own values and mask) where it
    runs; nothing is copied here."""
    from ...core.warp import resolve_device

    meta = _field_meta(f)
    total = sum(st["n"] for st in stats) if n is None else n
    dev = resolve_device(device)
    volume = (f.values, f.mask) if volume is None else volume
    tasks = []
    for i, (b, st) in enumerate(zip(bricks, stats)):
        cfg = brick_samples(refine, total, f.shape_xyz, b, dev)
        tasks.append(BrickTask(i, b, None, None, meta, st["n"], brick_seed(seed, i), allocation, cfg, device, st["rates"], volume=volume))
    return tasks


def reaching(params: np.ndarray, brick: Brick) -> np.ndarray:
    """The rows of ``params`` (volume coordinates) whose 5-sigma box reaches ``brick``'s box, in box
    coordinates."""
    if len(params) == 0:
        return params
    # 5 sigma. Until 2026-11-27 this read 5 x log-sigma, which left out frozen neighbours that reach the box
    ext = sigma_reach(params, 5.0)
    keep = np.ones(len(params), bool)
    for col, (lo, hi) in zip((2, 1, 0), brick.box):  # z, y, x box ranges against mu columns
        keep &= (params[:, col] + ext >= lo - 0.5) & (params[:, col] - ext <= hi - 0.5)
    out = np.array(params[keep], np.float32, copy=True)
    out[:, :3] -= _origin_xyz(brick)
    return out


def pending_regions(brick: Brick, others: list[Brick]) -> tuple:
    """Where the ``others``' interiors lie in ``brick``'s box (box coordinates)."""
    out = []
    for o in others:
        region = []
        for (b0, b1), (i0, i1) in zip(brick.box, o.interior):
            lo, hi = max(b0, i0), min(b1, i1)
            if lo >= hi:
                break
            region.append((lo - b0, hi - b0))
        else:
            out.append(tuple(region))
    return tuple(out)


# Bricks that step beside others (a wave of more than one brick) drop the split forward pass's rule
# for dense models (SIDE_BY_SIDE_SPLIT False; the split pass stays up to SPLIT_MAX_POINTS points an
# iteration, where the settings leave the pass to the refiner): beside other bricks the split
# pass's extra work competes where alone it fills an idle GPU. Measured (H200, bricks started
# together, benchmarks/bricked/profile_wave.py --together, results/bricked/profile_wave_*_together_*):
# 512^3 N 400,000, 8 bricks of 2x2x2 (40,178 points, 72k primitives each) side by side 21.7 ms a
# round split against 11.5 point-major (vortex), 13.5 against 8.5 (interface); 64 bricks of 4x4x4
# (6-9k points) 36.3 against 35.5; 1024^3 N 1,000,000, 64 bricks of 4x4x4 (5-7k points) 32.6
# against 36.8, and the waves of 8 slower with point-major (multi_gpu1024_together_h200x2.json:
# 167 s against 122-151 s in earlier runs). A function of the bricking alone (the wave's size),
# not of the workers, so that one GPU and several give the same model.
SIDE_BY_SIDE_SPLIT = False


# bricks stepping side by side on one device at most. Measured (one H200, 512^3 vortex, N 400,000,
# benchmarks/results/bricked/): the 8 bricks of a 4x4x4 wave took 5.0 ms a round side by side
# against 7.6 one after another when stepped alone, about 6.3 inside the encode; a wave of one
# brick (2x2x2) gains nothing. The split forward pass fills the GPU with 27 L threads a sample, so
# streams overlap only what it leaves idle. Every brick started at once (profile_wave.py
# --together): 64 bricks of 4x4x4 side by side 35.5-36.3 ms a round (0.55 ms a brick's step), where
# 8 at a time took 0.91 ms a brick's step inside the encode; the encode with up to 32 at once took
# 85.1 s against 95.6 s with 8 (vortex 512^3; one_gpu_512_together44_h200.json, split pass, against
# one_gpu_512_together_pm_h200.json, point-major).
MAX_AT_ONCE = 32


def bricks_at_once(tasks: list[BrickTask], device: str, limit: int | None) -> int:
    """How many of ``tasks`` may step side by side on ``device``: 1 on the CPU (its kernels run one
    after another anyway); on CUDA as many of the largest as ``limit`` bytes hold (default
    :func:`default_device_limit`, by :func:`brick_device_bytes`), at most :data:`MAX_AT_ONCE`."""
    from ...core.warp import warp

    if not tasks or not warp().get_device(device).is_cuda:
        return 1
    limit = default_device_limit(device) if limit is None else limit
    need = max(brick_device_bytes(t.brick.box_voxels, 1.5 * t.n) for t in tasks)
    return int(max(1, min(MAX_AT_ONCE, len(tasks), (limit or 0) // need)))
