"""Planning a bricking: the bricks (:class:`Brick`, :func:`plan_bricks`, their sigma cap and
halo), the budget split over them from their statistics before any refinement
(:func:`split_bricks`, see :mod:`warpgauss.encoding.scale.bricks` for the rule) and the bricking that device and
host memory limits choose (:func:`choose_bricks`, see :mod:`warpgauss.core.limits`). Pure numpy: no
device, no Dask.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from ...core.limits import HOST_BYTES_PER_VOXEL, brick_device_bytes
from ...errors import WarpgaussError
from ...field.analysis import OCCUPIED, Field, count_seed_candidates, map_slabs, seed_limit, split_budget

DEFAULT_HALO = 4  # voxels on each side at least (see default_halo)
CAP_SPACING = 1.25  # a brick's sigma cap in units of the mean primitive spacing (see brick_cap)


def brick_cap(cap: float, shape_xyz, n: int) -> float:
    """A brick's sigma cap: the monolithic cap ``cap``, at most :data:`CAP_SPACING` x the mean
    primitive spacing (voxels / n)^(1/3) (at least 2 voxels), so that primitives reach (2 sigma)
    no further past a brick's faces than its halo (:func:`default_halo`) holds samples. Measured
    (H100, N 400,000, halo 16, ``results/bricked/bricked_vs_mono_512_caps_h100.json``): on a 512^3 vortex the
    bricked encode with the monolithic cap (32 voxels) scored 68.02 dB against 71.51; with cap 8
    (1.16 spacings) 71.50 against the monolithic's 72.10 at cap 8. On 48^3 fields with 1,500
    Gaussians (spacing 4.2) a cap of 2 instead of 3 cost the monolithic encode 5.8 dB: the cap
    must not fall below the spacing."""
    d = (float(np.prod([int(v) for v in shape_xyz])) / max(int(n), 1)) ** (1.0 / 3.0)
    return float(min(cap, max(2.0, CAP_SPACING * d)))


def default_halo(cap: float) -> int:
    """The default halo for a brick sigma cap: 2 sigma, at least :data:`DEFAULT_HALO` voxels."""
    return max(DEFAULT_HALO, int(np.ceil(2.0 * cap)))


@dataclass(frozen=True)
class Brick:
    """One brick: its index, its interior and its halo box, ``(z, y, x)`` voxel slices as
    ``(start, stop)`` pairs (interior within the halo box)."""

    index: tuple[int, int, int]
    interior: tuple[tuple[int, int], ...]
    box: tuple[tuple[int, int], ...]

    @property
    def box_voxels(self) -> int:
        """Voxels in the halo box."""
        return int(np.prod([hi - lo for lo, hi in self.box]))

    def slices(self, which: str = "box") -> tuple[slice, ...]:
        return tuple(slice(a, b) for a, b in getattr(self, which))

    def interior_local(self) -> tuple[tuple[int, int], ...]:
        """The interior in box coordinates, ``(start, stop)`` pairs."""
        return tuple((i0 - b0, i1 - b0) for (i0, i1), (b0, _) in zip(self.interior, self.box))

    def interior_in_box(self) -> tuple[slice, ...]:
        return tuple(slice(a, b) for a, b in self.interior_local())


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
        if c > 1 and (c > s or s // c < 2):  # one brick along an axis is that axis whole, however short
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


GRAD_SLAB = 8  # z-planes per pass of the |grad V| sums (one pass per thread: their temporaries stay small)


def grad_sum(values: np.ndarray, select: np.ndarray | None, threads: int | None = None) -> float:
    """Sum of |grad V| (central differences, one-sided at the box's faces) over the occupied voxels
    of ``select`` (None: all), z-slab by z-slab in float32 on up to ``threads`` threads (default
    one per core)."""
    from ...field.analysis import map_slabs

    nz = values.shape[0]

    def part(z0: int) -> float:
        z1 = min(nz, z0 + GRAD_SLAB)
        lo, hi = max(0, z0 - 1), min(nz, z1 + 1)  # one plane more each side: central differences
        v = np.asarray(values[lo:hi], np.float32)
        g = np.zeros(v.shape, np.float32)
        for axis in range(3):
            if v.shape[axis] > 1:
                d = np.gradient(v, axis=axis)
                g += d * d
        core = slice(z0 - lo, z0 - lo + (z1 - z0))
        g, v = g[core], v[core]
        use = v > OCCUPIED
        if select is not None:
            use &= select[z0:z1]
        return float(np.sqrt(g[use], dtype=np.float32).sum(dtype=np.float64))

    return float(sum(map_slabs(part, nz, GRAD_SLAB, threads)))


def inner_faces(shape_xyz, bricks: list[Brick]) -> list[tuple[int, int]]:
    """The inner faces between ``bricks`` as ``(axis, index)`` pairs, axis in (z, y, x) order, the
    face lying between voxels ``index - 1`` and ``index`` (each face once, sorted)."""
    shape_zyx = tuple(int(s) for s in shape_xyz)[::-1]
    faces = {(axis, face) for b in bricks for axis, pair in enumerate(b.interior) for face in pair}
    return sorted((axis, face) for axis, face in faces if 0 < face < shape_zyx[axis])


def face_band(shape_xyz, bricks: list[Brick], width: int = 2) -> np.ndarray:
    """Voxels within ``width`` of an inner brick face, (z, y, x) booleans: where seams show."""
    near = np.zeros(tuple(int(s) for s in shape_xyz)[::-1], bool)
    for axis, face in inner_faces(shape_xyz, bricks):
        sl = [slice(None)] * 3
        sl[axis] = slice(max(0, face - width), face + width)
        near[tuple(sl)] = True
    return near


def split_bricks(
    f: Field, bricks: list[Brick], n: int, dv=None, host_limit: int | None = None, device: str | None = None
) -> tuple[list[int], list[dict]]:
    """Exactly ``n`` primitives over the bricks (see the module docstring), and each brick's
    statistics, among them ``rates``: primitives per unit of |grad V| sum and per occupied voxel,
    by which a brick sizes the stand-ins for its pending neighbours. ``dv``: the volume on a
    device (:class:`~warpgauss.field.analysis.DeviceVolume`), where the statistics are then taken;
    else ``device``: each box read and taken there (:func:`uploaded_brick_stats`); else on the
    host, within ``host_limit`` bytes (:func:`map_bricks`)."""
    if dv is not None:
        stats = [device_brick_stats(dv, b) for b in bricks]
    elif device is not None:
        stats = uploaded_brick_stats(f, bricks, device, host_limit)
    else:
        stats = map_bricks(functools.partial(brick_stats, f), bricks, host_limit)
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
    rates = (nd / grad_total, nc / occ_total)
    for s, c, w in zip(stats, counts, want):
        s.update(n=int(c), share=float(w), rates=rates)
    return [int(c) for c in counts], stats


def brick_stats(f: Field, b: Brick, threads: int | None = None) -> dict[str, Any]:
    """A brick's occupied and detail-eligible voxels, |grad V| sum and seed limit, over its interior."""
    box = b.slices("box")  # read once (a lazy volume reads it from the file)
    values = np.ascontiguousarray(f.values[box])
    valid = None if f.mask is None else np.ascontiguousarray(f.mask[box])
    own = np.zeros(values.shape, bool)
    own[b.interior_in_box()] = True
    if valid is not None:
        own &= valid
    occ, elig = count_seed_candidates(values, own, threads)
    return {"occupied": occ, "eligible": elig, "grad_sum": grad_sum(values, own, threads), "n_max": seed_limit(elig, occ)}


def device_brick_stats(dv, b: Brick) -> dict[str, Any]:
    """:func:`brick_stats` of the volume on a device (views of its box; :mod:`warpgauss.field.boxstats`)."""
    from ...field.boxstats import box_view

    valid = box_view(dv.mask, b.box) if dv.has_mask else None
    return _box_stats(b, box_view(dv.values, b.box), valid, str(dv.device))


def _box_stats(b: Brick, values, valid, device: str) -> dict[str, Any]:
    """A brick's statistics over its interior from its box's values and validity (Warp arrays or
    views on ``device``; ``valid`` None: every voxel)."""
    from ...field.boxstats import box_counts, region_mask

    own = region_mask(values.shape, device, [b.interior_local()], valid=valid)
    c = box_counts(values, own)
    return {"occupied": c.occupied, "eligible": c.eligible, "grad_sum": c.grad_sum, "n_max": seed_limit(c.eligible, c.occupied)}


def uploaded_brick_stats(f: Field, bricks: list[Brick], device: str, host_limit: int | None = None) -> list[dict[str, Any]]:
    """:func:`device_brick_stats` of a volume not on the device (read on demand from a file): each
    box read and normalised on the host, a few ahead on a thread pool (as many as half the
    available memory and ``host_limit`` hold at :data:`UPLOAD_BYTES_PER_VOXEL`, at most
    :data:`UPLOAD_READERS`), then counted on ``device`` one at a time, in brick order. The numbers
    equal those of the whole volume on the device. On the host, the 36 boxes of a 2048^3 file
    under a 16 GiB limit took 81 s (two at a time on 16 cores each; H200 host, 32 cores), here
    24-26 s (2048^3 on two H200, out_of_core2048_gpus12_h200x2.json). Their device memory goes
    back to the GPU when done (a Dask worker there may need it)."""
    from ...core.warp import warp

    wp = warp()

    def read(b: Brick):  # z-chunks of the box on threads of their own (one box read one slab at a time took most of Sb)
        box = b.slices("box")
        (z0, z1), (y0, y1), (x0, x1) = b.box
        values = np.empty((z1 - z0, y1 - y0, x1 - x0), np.float32)
        valid = None if f.mask is None else np.empty(values.shape, np.uint8)
        step = max(1, READ_CHUNK_VOXELS // max(1, values.shape[1] * values.shape[2]))

        def part(z: int) -> None:
            sl = (slice(z0 + z, z0 + min(z + step, values.shape[0])), box[1], box[2])
            values[z : z + step] = f.values[sl]
            if valid is not None:
                valid[z : z + step] = f.mask[sl]  # type: ignore[index]

        map_slabs(part, values.shape[0], step, threads=READ_THREADS)
        return values, valid

    def count(b: Brick, values: np.ndarray, valid: np.ndarray | None) -> dict[str, Any]:
        ok = None if valid is None else wp.array(valid, dtype=wp.uint8, device=device)
        return _box_stats(b, wp.array(values, dtype=wp.float32, device=device), ok, device)

    if not bricks:
        return []
    try:
        return _uploaded_stats(bricks, read, count, host_limit)
    finally:  # the boxes' device memory back to the GPU, which a Dask worker may share with this process
        dev = wp.get_device(device)
        if dev.is_cuda and wp.is_mempool_enabled(dev):
            keep = wp.get_mempool_release_threshold(dev)
            wp.set_mempool_release_threshold(dev, 0)
            wp.synchronize_device(dev)  # the pool gives back what it holds beyond the threshold here
            wp.set_mempool_release_threshold(dev, keep)


def _uploaded_stats(bricks: list[Brick], read, count, host_limit: int | None) -> list[dict[str, Any]]:
    """:func:`uploaded_brick_stats`' loop: boxes read ahead on a thread pool, counted in order."""
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    fit = boxes_in_room(bricks, UPLOAD_BYTES_PER_VOXEL, host_limit)
    ahead = UPLOAD_READERS if fit is None else fit - 1  # one box being counted, the others read ahead
    ahead = max(0, min(UPLOAD_READERS, ahead, len(bricks) - 1))
    if ahead == 0:
        return [count(b, *read(b)) for b in bricks]
    out = []
    with ThreadPoolExecutor(max_workers=ahead) as pool:
        pending = deque(pool.submit(read, b) for b in bricks[:ahead])
        for i, b in enumerate(bricks):
            values, valid = pending.popleft().result()
            if i + ahead < len(bricks):
                pending.append(pool.submit(read, bricks[i + ahead]))
            out.append(count(b, values, valid))
            del values, valid
    return out


UPLOAD_READERS = 4  # boxes read ahead while one is counted on the device
READ_THREADS = 8  # threads reading one box, each READ_CHUNK_VOXELS at a time
READ_CHUNK_VOXELS = 4 * 2**20
UPLOAD_BYTES_PER_VOXEL = 16  # a box's float32 values and validity, and its read's temporaries, per box voxel
STATS_BYTES_PER_VOXEL = 24  # a box's copy and its slabs' temporaries, per box voxel, while its statistics are taken


def boxes_in_room(bricks: list[Brick], bytes_per_voxel: int, host_limit: int | None = None) -> int | None:
    """How many of the largest of ``bricks``' boxes, at ``bytes_per_voxel``, half the available
    host memory and ``host_limit`` bytes hold (None where neither is known)."""
    from ...core.limits import available_memory

    free = available_memory()
    room = [x for x in (None if free is None else free // 2, host_limit) if x is not None]
    if not room:
        return None
    return int(min(room) // (bytes_per_voxel * max(b.box_voxels for b in bricks)))


def map_bricks(fn, bricks: list[Brick], host_limit: int | None = None) -> list:
    """``fn(brick, threads=t)`` for every brick, the bricks on a thread pool (one per core, as many
    as half the available host memory, and ``host_limit`` bytes, hold at
    :data:`STATS_BYTES_PER_VOXEL`: at 2048^3 in 36 bricks, half of 250 GB let 16 run at once and
    the process peaked at 61.7 GB against a --max-host-memory of 16 GiB), each brick's slabs
    on the ``t`` cores left to it: many small bricks scale with the cores where one box's slabs did
    not (the 64 bricks of 1024^3 took 18.5 s on 32 cores slab by slab). Results in brick order, the
    same as one at a time."""
    from concurrent.futures import ThreadPoolExecutor

    if len(bricks) <= 1:
        return [fn(b) for b in bricks]
    room = boxes_in_room(bricks, STATS_BYTES_PER_VOXEL, host_limit)
    fit = len(bricks) if room is None else max(1, room)
    cores = os.cpu_count() or 1
    k = max(1, min(len(bricks), cores, fit))
    if k == 1:
        return [fn(b) for b in bricks]
    with ThreadPoolExecutor(max_workers=k) as pool:
        return list(pool.map(functools.partial(fn, threads=max(1, cores // k)), bricks))


# -- choosing the bricking from device and host memory limits (see warpgauss.core.limits) ------------


def smallest_wave(counts) -> int:
    """Bricks in the smallest wave of a bricking of ``counts`` (x, y, z) run in waves: along an
    axis of c bricks, c // 2 have odd index (at least 1: one brick has even)."""
    return int(np.prod([max(1, int(c) // 2) for c in counts]))


def choose_bricks(
    shape_xyz, n: int, limit: int | None, halo: int = DEFAULT_HALO, host_limit: int | None = None, workers: int = 1
) -> tuple[int, int, int]:
    """The fewest bricks (x, y, z) whose largest box fits ``limit`` bytes of device memory (by
    :func:`brick_device_bytes`, ``n`` primitives over them), ``host_limit`` bytes of host memory
    (:data:`HOST_BYTES_PER_VOXEL`) and the kernels' voxel index; more bricks go along the axis
    whose bricks are longest. (1, 1, 1) when the whole grid fits. A grid that must be bricked for
    ``workers`` > 1 (a Dask cluster) is split further, the same way, until every wave holds a
    brick for each worker (:func:`smallest_wave`): a 2x2x2 bricking runs in 8 waves of one brick,
    which leaves every worker but one idle; where the grid cannot be split that far, what fits."""
    counts = _fitting_bricks(shape_xyz, n, limit, halo, host_limit)
    if counts == (1, 1, 1) or workers <= 1:
        return counts
    more = list(counts)
    shape = [int(s) for s in shape_xyz]
    while smallest_wave(more) < workers:
        axis = int(np.argmax([s / c for s, c in zip(shape, more)]))
        grown = 2 * (more[axis] // 2 + 1)  # the next count that adds an odd-indexed brick on the axis
        if shape[axis] // grown < max(2, 4 * halo):
            break
        more[axis] = grown
    return (more[0], more[1], more[2])


def _fitting_bricks(shape_xyz, n: int, limit: int | None, halo: int, host_limit: int | None) -> tuple[int, int, int]:
    """:func:`choose_bricks` for one worker."""
    from ...field.analysis import MAX_VOXELS

    counts = [1, 1, 1]
    shape = [int(s) for s in shape_xyz]
    while True:
        boxes = [b.box_voxels for b in plan_bricks(shape, counts, halo if counts != [1, 1, 1] else 0)]
        k = int(np.prod(counts))
        need = brick_device_bytes(max(boxes), 1.5 * n / k if k > 1 else n)
        host = HOST_BYTES_PER_VOXEL * max(boxes)
        if max(boxes) <= MAX_VOXELS and (limit is None or need <= limit) and (host_limit is None or host <= host_limit):
            return (counts[0], counts[1], counts[2])
        axis = int(np.argmax([s / c for s, c in zip(shape, counts)]))
        if shape[axis] // (counts[axis] + 1) < max(2, 4 * halo):
            raise WarpgaussError(
                f"no bricking of {'x'.join(map(str, shape))} fits {limit / 2**30 if limit else 0:.1f} GiB of device memory and "
                f"{host_limit / 2**30 if host_limit else 0:.1f} GiB of host memory (bricks of {'x'.join(map(str, counts))} need about "
                f"{need / 2**30:.1f} and {host / 2**30:.1f} GiB each); raise --max-device-memory / --max-host-memory or lower the budget"
            )
        counts[axis] += 1


def sigma_reach(params: np.ndarray, k: float) -> np.ndarray:
    """``k`` times each row's largest sigma, in voxels (float64): the half-width of the isotropic
    box :func:`seam_rows`, :func:`seam_support` and the frozen neighbours' selection use. Columns
    3:6 hold log-sigmas, clamped as the field kernels clamp them."""
    return k * np.exp(np.clip(params[:, 3:6].max(axis=1).astype(np.float64), -9.0, 12.0))
