"""How the bricks run: in waves of neighbours (:func:`brick_colour`) or all at once, whether the
seams are then refit (:class:`BrickSchedule`, :func:`choose_schedule`), and the waves run in
this process or on a Dask cluster (:func:`run_bricks`), each group of bricks side by side on
one device (:mod:`warpgauss.core.together`)."""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ...core.limits import brick_device_bytes, default_device_limit
from .bricks import BrickTask, encode_bricks, pending_regions, reaching
from .plan import Brick


def brick_colour(b: Brick) -> int:
    """The brick's wave: bricks of one colour (index parities) never share a box, so they run at
    once; the waves run in colour order."""
    i, j, k = b.index
    return (i % 2) + 2 * (j % 2) + 4 * (k % 2)


# True: a brick waits for its finished neighbours (the waves of brick_colour, up to 8, each brick
# refined beside the primitives its finished neighbours left in its box). False: every brick starts
# at once, with stand-ins for all its neighbours (what the first wave does), so that a GPU steps
# them side by side (a 2x2x2 bricking is otherwise 8 waves of one brick), and the seams are then
# refit together (SEAM_REFIT). None (the default): :func:`choose_schedule` decides per encode.
# Stand-ins alone do not do the frozen neighbours' work: 2x2x2 at 48^3 on the CPU
# (benchmarks/bricked/seam_cpu.py --together, results/bricked/seam_together_cpu.json) lost 10.5 /
# 9.7 dB on the vortex and 3.0 / 2.4 dB on the interface against the waves without a refit.
NEIGHBOURS_FIRST: bool | None = None


def brick_wave(b: Brick, together: bool | None = None) -> int:
    """The wave the brick runs in: its :func:`brick_colour`, or 0 for every brick when the bricks
    start ``together`` (None: :data:`NEIGHBOURS_FIRST` is False)."""
    together = NEIGHBOURS_FIRST is False if together is None else together
    return 0 if together else brick_colour(b)


# A joint refit of the seams after the bricks: this share of the iterations, the primitives
# whose 3-sigma box comes within SEAM_BAND voxels of an inner face refined together over the whole
# grid, every other primitive frozen, at SEAM_LR x the learning rate. It needs the whole volume on
# one device. None (the default): TOGETHER_SEAM_REFIT for bricks started together, none after the
# waves. For bricks started at once, CPU at 96^3, N 12,000
# (benchmarks/bricked/seam_refit_cpu.py, results/bricked/seam_refit96*_cpu.json; full-grid PSNR,
# waves 53.47 / 37.30 dB on vortex / interface, together without refit 47.39 / 35.62): 0.25 at
# 0.3x 52.54 / 37.24, 0.5 at 1x 52.55 / 37.27, 0.25 at 1x 48.74 / 35.12, 0.1 at 0.3x 50.15 / 36.32;
# at 128^3, N 28,000, 0.25 at 0.3x: 50.85 / 36.81 against the waves' 51.88 / 36.24; 0.5 at 0.3x
# 52.29 on the vortex (0.5 at 1x: 50.14).
SEAM_REFIT: float | None = None
# One H200, format full, N 400,000 at 512^3 and 1,400,000 at 1024^3, against the monolithic encode
# of the same run (benchmarks/bricked/one_gpu.py --together 0.25, results/bricked/one_gpu_*together*_h200.json):
# 512^3 2x2x2 vortex +0.32 dB in 1.64x its time, interface +0.83 dB in 1.71x (the waves: -0.23 /
# +0.02 dB in 2.67x / 2.59x); 4x4x4 +0.37 / +0.50 dB in 4.08x / 3.87x (the waves, an earlier run:
# -1.11 / -0.90 dB in 5.11x / 4.38x); 1024^3 2x2x2 +0.00 / +2.13 dB in 1.86x / 2.00x; half the
# iterations: +0.58 / +1.52 dB at 512^3 2x2x2 in 2.56x / 2.16x (split forward pass). Since the
# bricks start on the device (DEVICE_SETUP; one_gpu_*_device_setup_h200.json): the same models in
# 1.42x / 1.46x at 512^3 and 1.17x / 1.19x at 1024^3.
TOGETHER_SEAM_REFIT = 0.25
# On the CPU, where the bricks run in waves with the whole volume in this process, the seams are
# refit after the waves for this share of the iterations. 2x2x2 at 48^3, 3,000 Gaussians, 200
# iterations, seed 3, coded (issue #55; monolithic: bubbles 68.21, vortex 55.14, interface 40.05
# dB): without a refit bubbles 65.86, vortex 54.21, interface 39.14; at 0.25 66.93 / 54.82 /
# 39.85 (0-14 % more time); at 0.5 69.32 / 55.76 / 40.78 (about 8-15 % more time than 0.25)
CPU_WAVES_SEAM_REFIT = 0.5
# Bricks started together on a Dask cluster of CPU processes (choose_schedule), the seams then
# refit on this process's CPU for this share of the iterations. The 48^3 case above: bubbles 66.22
# dB at 0.25, 68.78 at 0.5; at 0.5 vortex 54.89, interface 40.34 (0.5 under the waves' 0.5 refit)
CPU_TOGETHER_SEAM_REFIT = 0.5
# After the waves of a Dask cluster of GPU workers, where this process holds the whole volume and
# its GPU holds it for the refit (as TOGETHER_SEAM_REFIT's rule), the seams are refit there for
# this share of the iterations. Before it, 1024^3 vortex 4x4x4 on two H200 workers lost 1.11 dB
# against the monolithic encode (69.50 / 70.61 dB, results/scale/multi_gpu1024_dask_r3_h200x2.json);
# the share is TOGETHER_SEAM_REFIT's, measured on one GPU, not yet on a cluster
GPU_WAVES_SEAM_REFIT = TOGETHER_SEAM_REFIT


@dataclass(frozen=True)
class BrickSchedule:
    """How an encode runs its bricks: ``together`` (every brick at once) or in waves, the share of
    the iterations the seams are then refit for (0: none), and why."""

    together: bool
    seam_refit: float
    why: str

    def report(self) -> dict:
        return {"waves": "together" if self.together else "neighbours first", "seam_refit_share": self.seam_refit, "why": self.why}


def choose_schedule(
    device: str, client, lazy: bool, shape_xyz, n: int, iterations: int, limit: int | None, counts=None, workers: int = 1
) -> BrickSchedule:
    """The bricks' :class:`BrickSchedule`: :data:`NEIGHBOURS_FIRST` and :data:`SEAM_REFIT` where set;
    otherwise every brick at once and the seams refit (:data:`TOGETHER_SEAM_REFIT`) in this
    process on a GPU whose ``limit`` (default :func:`default_device_limit`) holds the whole volume
    for the refit; every brick at once too, and the seams refit on this process's CPU
    (:data:`CPU_TOGETHER_SEAM_REFIT`), on a Dask cluster of CPU ``workers`` that the waves of a
    bricking of ``counts`` (x, y, z) would leave idle (:func:`~warpgauss.encoding.scale.plan.smallest_wave`
    smaller than the workers: 2x2x2 runs 8 waves of one brick); and the waves everywhere else: on
    the CPU in this process (bricks step one at a time there, so starting them together buys no
    time), on a GPU cluster (measured with the waves; bit for bit the same model on any number of
    workers either way), for a volume read brick by brick (the refit needs it whole), without
    refinement. After waves whose volume this process holds whole on its CPU the seams are refit
    for :data:`CPU_WAVES_SEAM_REFIT` of the iterations; after a GPU cluster's waves, on this
    process's GPU where it holds the whole volume, for :data:`GPU_WAVES_SEAM_REFIT`."""
    from ...core.warp import warp
    from .plan import smallest_wave

    on_cpu = not warp().get_device(device).is_cuda
    if NEIGHBOURS_FIRST is not None:
        together, why = not NEIGHBOURS_FIRST, "set (bricked.NEIGHBOURS_FIRST)"
    elif iterations <= 0:
        together, why = False, "no refinement"
    elif lazy:
        together, why = False, "the volume is read brick by brick (the seams' refit needs it whole on one device)"
    elif client is not None and on_cpu and counts is not None and smallest_wave(counts) < workers:
        together = True
        why = f"a Dask cluster of {workers} CPU processes that waves of {smallest_wave(counts)} brick(s) would leave idle; the seams refit on this process's CPU"
    elif client is not None:
        together, why = False, "a Dask cluster whose waves hold a brick for every worker" if on_cpu else "a Dask cluster"
    elif on_cpu:
        together, why = False, "the CPU steps bricks one at a time"
    else:
        together, need, limit = _refit_fits(device, limit, shape_xyz, n)
        why = "one GPU that holds the whole volume for the seams' refit"
        if limit is not None and not together:
            why = f"the seams' refit would need about {need / 2**30:.1f} GiB of the device, {limit / 2**30:.1f} GiB allowed"
    share = (CPU_TOGETHER_SEAM_REFIT if on_cpu else TOGETHER_SEAM_REFIT) if together else 0.0
    if SEAM_REFIT is None and not together and iterations > 0 and not lazy and on_cpu:
        # this process holds the whole volume on the CPU: the seams are refit after the waves, on
        # a cluster as here (the same model on any number of workers)
        share, why = CPU_WAVES_SEAM_REFIT, f"{why}; the seams refit after the waves on this process's CPU"
    elif SEAM_REFIT is None and not together and iterations > 0 and not lazy and client is not None:
        if _refit_fits(device, limit, shape_xyz, n)[0]:  # a GPU here that holds the whole volume for the refit
            share, why = GPU_WAVES_SEAM_REFIT, f"{why}; the seams refit after the waves on this process's GPU"
    share = share if SEAM_REFIT is None else float(SEAM_REFIT)
    return BrickSchedule(together, share, why)


def _refit_fits(device: str, limit: int | None, shape_xyz, n: int) -> tuple[bool, int, int | None]:
    """(whether ``device`` holds the whole volume and 1.5 ``n`` primitives for the seams' refit
    under ``limit`` bytes, default :func:`default_device_limit`; the bytes needed; the limit)."""
    limit = default_device_limit(device) if limit is None else limit
    need = brick_device_bytes(int(np.prod(shape_xyz)), 1.5 * n)
    return limit is None or need <= limit, need, limit


@contextlib.contextmanager
def schedule(neighbours_first: bool | None = True, seam_refit: float | None = 0.0) -> Iterator[None]:
    """:data:`NEIGHBOURS_FIRST` and :data:`SEAM_REFIT` set for a block (the benchmarks that
    compare the schedules; None: the default rule), the values before it restored after it."""
    global NEIGHBOURS_FIRST, SEAM_REFIT
    saved = NEIGHBOURS_FIRST, SEAM_REFIT
    NEIGHBOURS_FIRST = None if neighbours_first is None else bool(neighbours_first)
    SEAM_REFIT = None if seam_refit is None else float(seam_refit)
    try:
        yield
    finally:
        NEIGHBOURS_FIRST, SEAM_REFIT = saved


def wave_tasks(tasks: list[BrickTask], finished: dict[int, np.ndarray], wave: list[int]) -> list[BrickTask]:
    """This wave's tasks, given the finished bricks' primitives (volume coordinates, by index): each
    with the finished primitives that reach its box frozen and the rest of its neighbours pending,
    and whether it steps beside others (a wave of several bricks; :data:`SIDE_BY_SIDE_SPLIT`)."""
    # in brick order, whatever order the bricks finished in (the frozen rows' order is part of the result)
    done = np.concatenate([finished[i] for i in sorted(finished)]) if finished else np.zeros((0, 12), np.float32)
    out = []
    for i in wave:
        t = tasks[i]
        others = [u.brick for u in tasks if u.index != i and u.index not in finished]
        out.append(dataclasses.replace(t, frozen=reaching(done, t.brick), pending=pending_regions(t.brick, others), beside=len(wave) > 1))
    return out


def run_bricks(
    tasks: list[BrickTask],
    client=None,
    progress=None,
    fn=None,
    at_once: int | None = None,
    limit: int | None = None,
    waves_out: list[dict] | None = None,
    together: bool | None = None,
) -> list[dict]:
    """Every brick's result, in brick order, wave by wave (:func:`brick_wave`): in this process
    (``client`` None), the bricks of a wave stepping side by side on the device (``at_once`` of
    them, default :func:`bricks_at_once` under ``limit`` bytes of device memory), or on a Dask cluster, a wave's bricks split into one
    group per worker, each group run side by side there (:func:`encode_bricks`); a failed task is
    retried once and one that fails twice fails the run. ``fn``: what runs one task (tests inject
    failures; a task at a time then). ``waves_out``: a list that gets each wave's timing (its wall
    seconds here, and the longest time a process spent on its bricks: the difference is what
    reaching the workers cost). ``together``: every brick in one wave (None: as
    :data:`NEIGHBOURS_FIRST` says)."""
    waves: dict[int, list[int]] = {}
    for t in tasks:
        waves.setdefault(brick_wave(t.brick, together), []).append(t.index)
    finished: dict[int, np.ndarray] = {}
    results: dict[int, dict] = {}
    for colour in sorted(waves):
        t0 = time.perf_counter()
        batch = wave_tasks(tasks, finished, waves[colour])
        t1 = time.perf_counter()
        got = _run_wave(fn, batch, client, progress, len(results), len(tasks), at_once, limit)
        for r in got:
            results[r["index"]] = r
            finished[r["index"]] = r["params"]
        if waves_out is not None:
            waves_out.append(
                {
                    "colour": colour,
                    "bricks": len(batch),
                    "seconds": time.perf_counter() - t0,
                    "prepare_seconds": t1 - t0,
                    "worker_seconds": max((r.get("group_seconds", r["seconds"]) for r in got), default=0.0),
                }
            )
    return [results[t.index] for t in tasks]


def brick_groups(batch: list[BrickTask], groups: int) -> list[list[BrickTask]]:
    """``batch`` in at most ``groups`` groups of nearly equal work (largest box first, each to the
    group with the fewest voxels so far), each group in brick order."""
    out: list[list[BrickTask]] = [[] for _ in range(max(1, min(groups, len(batch))))]
    load = [0] * len(out)
    for t in sorted(batch, key=lambda t: (-t.brick.box_voxels, t.index)):
        g = int(np.argmin(load))
        out[g].append(t)
        load[g] += t.brick.box_voxels
    return [sorted(g, key=lambda t: t.index) for g in out if g]


def _run_wave(
    fn, batch: list[BrickTask], client, progress, done: int, total: int, at_once: int | None = None, limit: int | None = None
) -> list[dict]:
    def after(n: int, i: int, r) -> None:
        if progress is not None:
            progress(done + n, total)

    if client is None:
        if fn is None:
            count = [0]

            def one_done(i: int, r) -> None:
                count[0] += 1
                after(count[0], i, r)

            return encode_bricks(batch, at_once, limit, on_done=one_done)
        out = []
        for t in batch:
            out.append(fn(t))
            after(len(out), len(out) - 1, out[-1])
        return out
    from .cluster import map_on_cluster

    tail = "; no model written"
    batch = [t.shipped() for t in batch]
    if fn is None:
        workers = max(1, len(client.scheduler_info().get("workers", {})))
        groups = brick_groups(batch, workers)
        keys = [f"warpgauss-bricks-{'-'.join(str(t.index) for t in g)}-{id(g)}" for g in groups]
        seen = [0]

        def group_done(n: int, i: int, r) -> None:
            seen[0] += len(r)
            after(seen[0], i, r)

        run = functools.partial(encode_bricks, at_once=at_once, limit=limit)
        parts = map_on_cluster(client, run, groups, keys, "a group of bricks", tail=tail, after=group_done)
        return [r for part in parts for r in part]
    keys = [f"warpgauss-brick-{t.index}-{id(t)}" for t in batch]
    return map_on_cluster(client, fn, batch, keys, "a brick", tail=tail, after=after)
