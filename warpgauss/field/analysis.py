"""Stage P (normalise, mask) and the checks that run before any heavy work.

Everything up to the budget check is plain numpy over z-slabs and needs no Warp: an infeasible
request is refused before Warp is even imported. The structure statistics of SPEC section 5 run
as Warp kernels (:func:`structure_stats`).
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import WarpgaussError
from ..readers.lazy import valid_mask as _valid
from . import limits
from .limits import MAX_HOST_VOXELS, MAX_SLICE_VOXELS, MAX_VOXELS, voxels_problem  # noqa: F401 (their home before field.limits)

OCCUPIED = 0.02  # normalised value above which a voxel is occupied (SPEC section 2)
DETAIL_PERCENT = 55  # detail share of the budget (SPEC section 3); coverage gets the rest
SLAB = 32  # z-slices per numpy pass
# voxels per numpy pass at most (fewer slices where the slices are large: at 2048^2 a pass of 32
# slices held 134M voxels and their temporaries on every core's thread); the same values and counts
SLAB_VOXELS = 1 << 25
LAZY_SLAB_VOXELS = 4 * 2**20  # voxels per pass (and thread) of a volume read on demand
# threads counting a volume read on demand, each over 4 x LAZY_SLAB_VOXELS voxels (about 0.3 GB
# with its temporaries): at most 2.4 GB of host memory however many cores
LAZY_COUNT_THREADS = 8
STATS_EXACT_VOXELS = 1 << 22  # up to this many voxels the statistics use every voxel
STATS_SAMPLES = 1 << 21  # voxels drawn (with replacement) for the statistics of larger volumes
STRUCTURE_LAG = 16


@dataclass
class Field:
    """A normalised volume: float32 values in [0, 1], (nz, ny, nx), invalid voxels set to 0.

    Attributes:
        values: Normalised values; masked voxels hold 0.
        mask: Boolean validity (True = usable) or None when every voxel is valid.
        vmin, vmax: The finite min/max used for normalisation (original units).
        occupied: Valid voxels with normalised value > 0.02.
        eligible: Occupied voxels with a non-zero gradient (detail-seed candidates).
        counted: Whether ``occupied`` and ``eligible`` have been counted (a file read on demand
            for a bricked encode is counted by the bricks' statistics instead, stage Sb).
    """

    values: np.ndarray
    mask: np.ndarray | None
    vmin: float
    vmax: float
    spacing: tuple[float, ...] = (1.0, 1.0, 1.0)
    origin: tuple[float, ...] = (0.0, 0.0, 0.0)
    name: str = "volume"
    source_dtype: str = "float32"
    source_itemsize: int = 4
    occupied: int = 0
    eligible: int = 0
    n_valid: int = 0
    notes: list[str] = field(default_factory=list)
    counted: bool = True
    host_arrays: Any = None  # (values, mask or None): the Warp host arrays behind values and mask (normalise(pinned=True))

    @property
    def shape_xyz(self) -> tuple[int, int, int]:
        nz, ny, nx = self.values.shape
        return (nx, ny, nz)

    @property
    def n_voxels(self) -> int:
        return int(self.values.size)

    @property
    def source_bytes(self) -> int:
        """S_src of SPEC section 4: voxels at the evaluated resolution x the source dtype's size."""
        return self.n_voxels * self.source_itemsize

    @property
    def occupancy(self) -> float:
        return self.occupied / max(self.n_valid, 1)

    def to_original(self, normalised: np.ndarray) -> np.ndarray:
        """Map normalised values back to the source's units (see :func:`denormalise`)."""
        return denormalise(normalised, self.vmin, self.vmax)


F32_MAX = float(np.finfo(np.float32).max)
F32_TINY = float(np.finfo(np.float32).tiny)  # smallest normal float32
_F32_SAFE = 1e30  # float32 normalisation only where values, range and scale stay within 1e-30..1e30


class NormPlan:
    """How stage P maps source values to (x - lo) / (hi - lo) without overflow, NaN or lost scale.

    float32 arithmetic (fast, exact enough for <= 4-byte sources) is used only while neither the
    values, nor the range, nor 1 / range leave 1e-30..1e30; otherwise float64, dividing by the range
    where 1 / range would overflow (subnormal data) and halving first where hi - lo itself overflows
    (float64 data near +-1.8e308). Values normalised by a given range are clamped to finite float32.
    """

    def __init__(self, lo: float, hi: float, data_lo: float, data_hi: float, exact: bool, clip: bool):
        self.lo, self.clip = lo, clip
        self.lo_value, self.hi_value = lo, hi
        span = hi - lo
        self.halve = not np.isfinite(span)
        if self.halve:
            self.lo, span = 0.5 * lo, 0.5 * hi - 0.5 * lo
        self.span = span
        self.scale = 1.0 / span
        reach = max(abs(lo), abs(hi), abs(data_lo), abs(data_hi))
        # the largest |normalised| value (outside [0, 1] only with a given value range)
        h = 0.5 if self.halve else 1.0
        out = max(abs(data_lo * h - self.lo), abs(data_hi * h - self.lo)) / span
        self.f32 = not exact and not self.halve and reach <= _F32_SAFE and 1 / _F32_SAFE <= span <= _F32_SAFE
        self.f32 = self.f32 and out <= _F32_SAFE
        self.divide = not (np.isfinite(self.scale) and abs(self.scale) >= np.finfo(np.float64).tiny)
        self.bound = not clip and not out <= F32_MAX

    def apply(self, s: np.ndarray) -> np.ndarray:
        if self.f32:
            v = s.astype(np.float32, copy=True)
            v -= np.float32(self.lo)
            v *= np.float32(self.scale)
        else:
            v = s.astype(np.float64, copy=True)
            if self.halve:
                v *= 0.5
            v -= self.lo
            if self.divide:
                v /= self.span
            else:
                v *= self.scale
        if self.clip:
            np.clip(v, 0.0, 1.0, out=v)
        elif self.bound:
            np.clip(v, -F32_MAX, F32_MAX, out=v)
        return v


def denormalise(normalised: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Normalised values back to source units: lo + v (hi - lo), overflow-safe.

    Returns float32, or float64 where float32 cannot hold the range: beyond +-3.4e38 (a float64
    source near +-1e308) or narrower than float32's smallest normal number (subnormal data), so that
    no finite source value decodes to inf or to a few subnormal steps.
    """
    v = np.asarray(normalised, dtype=np.float64)
    lo, hi = float(lo), float(hi)
    if np.isfinite(hi - lo):
        out = v * (hi - lo) + lo
    else:  # hi - lo overflows: interpolate from both ends, each term bounded by max(|lo|, |hi|)
        out = lo * (1.0 - v) + hi * v
    if max(abs(lo), abs(hi)) > F32_MAX or hi - lo < F32_TINY:
        return out
    return np.clip(out, -F32_MAX, F32_MAX).astype(np.float32)  # an overshoot past the range stays finite


def normalise(
    data: np.ndarray,
    *,
    fill_value: float | None = None,
    spacing=(1.0, 1.0, 1.0),
    origin=(0.0, 0.0, 0.0),
    name: str = "volume",
    source_dtype: str | None = None,
    value_range: tuple[float, float] | None = None,
    count_candidates: bool = True,
    lazy: bool = False,
    max_voxels: int | None = None,
    pinned: bool = False,
) -> Field:
    """Stage P: mask NaN/Inf/fill voxels, normalise by the finite min/max, count occupancy.

    Args:
        data: 3D array (nz, ny, nx) of any real dtype (may be a memmap).
        fill_value: Source value that marks missing data; such voxels are masked.
        value_range: Normalise by this (min, max) instead of the volume's own (evaluating a
            model against a volume uses the model's range); values are then not clipped.
        count_candidates: Count occupied and detail-eligible voxels (needed to validate a
            budget, not to evaluate a model; the counts stay 0 when skipped).
        lazy: Keep the values where they are (``data`` a memory-mapped or chunked source, see
            :mod:`warpgauss.readers.lazy`): one streaming pass for the min/max and the counts, and the
            field's ``values`` and ``mask`` read and normalised on demand (a bricked encode).
            The counts are then per z-slab (gradients one-sided at slab faces): within a few
            per cent.
        max_voxels: The most voxels the encode that follows indexes: None for
            ``field.limits.MAX_VOXELS`` (the volume on the device), or ``MAX_HOST_VOXELS`` (in
            host memory, --volume-on-host).
        pinned: Normalise straight into page-locked host memory, a slab at a time from ``data``
            (a memory map is read, not copied whole), which ``DeviceVolume(on_host=True)`` then
            reads as it is: one copy of the volume in host memory where there were two
            (:func:`warpgauss.field.slabs.host_buffers`).
    """
    if data.ndim != 3:
        raise WarpgaussError(f"the volume is {data.ndim}D (shape {data.shape}); warpgauss encodes 3D volumes")
    problem = None if lazy else voxels_problem(data.shape, max_voxels)
    if problem is not None:
        raise WarpgaussError(problem)
    if not (np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.floating)):
        raise WarpgaussError(f"the volume's dtype {data.dtype} is not a real number type")
    if lazy:  # every read through the source: nothing stays mapped (see warpgauss.readers.lazy)
        from ..readers.lazy import Lazy3D, require_source

        src = require_source(data, name)
        data = Lazy3D(src)  # type: ignore[assignment]
    nz = data.shape[0]
    exact = np.dtype(data.dtype).itemsize > 4 or np.dtype(data.dtype) in (np.int32, np.uint32)
    maybe_invalid = np.issubdtype(data.dtype, np.floating) or fill_value is not None

    def scan(z0: int):
        s = np.asarray(data[z0 : z0 + slab])
        if not maybe_invalid:
            return s.min(), s.max(), 0
        ok = _valid(s, fill_value)
        n_ok = int(np.count_nonzero(ok))
        if n_ok == ok.size:
            return s.min(), s.max(), 0
        if n_ok == 0:
            return np.inf, -np.inf, ok.size
        return s[ok].min(), s[ok].max(), ok.size - n_ok

    # read on demand, a slab is the source's copy and its temporaries on every thread: keep it small
    plane = int(np.prod(data.shape[1:], dtype=np.int64))
    slab = slab_slices(plane) if not lazy else max(1, min(SLAB, LAZY_SLAB_VOXELS // max(plane, 1)))
    parts = map_slabs(scan, nz, slab)
    lo = min(float(p[0]) for p in parts)
    hi = max(float(p[1]) for p in parts)
    n_invalid = sum(p[2] for p in parts)
    if not np.isfinite(lo):
        raise WarpgaussError("the volume has no finite value (all NaN/Inf or fill); nothing to encode")
    data_lo, data_hi = lo, hi
    clip = value_range is None
    if value_range is not None:
        lo, hi = float(value_range[0]), float(value_range[1])
        if not (np.isfinite(lo) and np.isfinite(hi)):
            raise WarpgaussError(f"the value range ({lo:g}, {hi:g}) is not finite; the model is damaged")
    if hi <= lo:
        raise WarpgaussError(f"the volume is constant ({lo:g} everywhere it is valid); there is no structure to encode")
    plan = NormPlan(lo, hi, data_lo, data_hi, exact, clip)
    if lazy:
        return _lazy_field(src, plan, fill_value, n_invalid, spacing, origin, name, source_dtype or data.dtype, count_candidates)
    finish = None
    if pinned:
        from .slabs import host_buffers

        values, mask, finish = host_buffers(data.shape, bool(n_invalid))
    else:
        values = np.empty(data.shape, np.float32)
        mask = np.ones(data.shape, bool) if n_invalid else None

    def fill(z0: int):
        s = np.asarray(data[z0 : z0 + slab])
        v = plan.apply(s)
        if mask is not None:
            ok = _valid(s, fill_value)
            v[~ok] = 0.0
            mask[z0 : z0 + slab] = ok
        values[z0 : z0 + slab] = v

    map_slabs(fill, nz, slab)
    f = new_field(values, mask, lo, hi, spacing, origin, name, source_dtype or data.dtype, n_invalid)
    f.host_arrays = None if finish is None else finish()  # page-locked now that every page is written
    f.counted = count_candidates
    if count_candidates:
        f.occupied, f.eligible = count_seed_candidates(values, mask)
    return f


def new_field(values, mask, lo, hi, spacing, origin, name, source_dtype, n_invalid: int) -> Field:
    """The Field of normalised ``values`` (an array, or read on demand) and its stage-P facts."""
    f = Field(
        values=values,
        mask=mask,
        vmin=float(lo),
        vmax=float(hi),
        spacing=tuple(float(x) for x in spacing),
        origin=tuple(float(x) for x in origin),
        name=name,
        source_dtype=str(source_dtype),
        source_itemsize=int(np.dtype(source_dtype).itemsize),
    )
    f.n_valid = f.n_voxels - n_invalid
    if n_invalid:
        f.notes.append(f"{n_invalid} voxels are NaN/Inf/fill: masked out of seeding, sampling and every metric")
    return f


def _lazy_field(src, plan, fill_value, n_invalid, spacing, origin, name, source_dtype, count_candidates) -> Field:
    """The Field of a volume read on demand from ``src`` (a :class:`warpgauss.readers.lazy.ArraySource`)."""
    from ..readers.lazy import LazyMask, LazyValues

    values = LazyValues(src, plan, fill_value, n_invalid > 0)
    mask = LazyMask(src, fill_value) if n_invalid else None
    f = new_field(values, mask, plan.lo_value, plan.hi_value, spacing, origin, name, source_dtype, n_invalid)
    f.counted = count_candidates
    if count_candidates:
        step = max(1, 4 * LAZY_SLAB_VOXELS // max(1, values.shape[1] * values.shape[2]))

        def count(z0: int):
            return count_seed_candidates(values[z0 : z0 + step], None if mask is None else mask[z0 : z0 + step], threads=1)

        # each slab read, normalised and counted on its own thread: one after another, these took
        # most of stage P (75 s at 2048^3)
        parts = map_slabs(count, values.shape[0], step, threads=LAZY_COUNT_THREADS)
        f.occupied, f.eligible = sum(p[0] for p in parts), sum(p[1] for p in parts)
    return f


def slab_slices(plane: int) -> int:
    """z slices per numpy pass over slices of ``plane`` voxels: :data:`SLAB`, fewer where that
    would pass :data:`SLAB_VOXELS`."""
    return max(1, min(SLAB, SLAB_VOXELS // max(plane, 1)))


def map_slabs(fn, nz: int, slab: int = SLAB, threads: int | None = None) -> list:
    """Run fn(z0) for every z-slab, on a thread pool (numpy releases the GIL in its loops; at
    most ``threads``, default one per core; 1: in this thread); the results in slab order."""
    starts = list(range(0, nz, slab))
    if len(starts) == 1 or threads == 1:
        return [fn(z0) for z0 in starts]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=min(len(starts), threads or os.cpu_count() or 1)) as pool:
        return list(pool.map(fn, starts))


def count_seed_candidates(values: np.ndarray, mask: np.ndarray | None, threads: int | None = None) -> tuple[int, int]:
    """(occupied voxels, occupied voxels with a non-zero gradient), z-slab by z-slab on up to
    ``threads`` threads (default one per core).

    The gradient test mirrors ``kernels.analysis.gradient_at`` exactly: on each axis a central
    difference, one-sided next to the border or a masked voxel; non-zero iff the two values differ.
    """
    nz = values.shape[0]
    slab = slab_slices(int(values.shape[1]) * int(values.shape[2]))

    def count(z0: int) -> tuple[int, int]:
        z1 = min(nz, z0 + slab)
        a, b = max(0, z0 - 1), min(nz, z1 + 1)  # one halo slice each side
        v = values[a:b]
        core = slice(z0 - a, z0 - a + (z1 - z0))
        if mask is None:
            occ = v[core] > OCCUPIED
            differs = _differs_unmasked(v, 2)[core] | _differs_unmasked(v, 1)[core]
            differs |= _differs_unmasked(v, 0)[core]
        else:
            ok = mask[a:b]
            occ = (ok & (v > OCCUPIED))[core]
            differs = (_differs(v, ok, 2) | _differs(v, ok, 1) | _differs(v, ok, 0))[core]
        return int(np.count_nonzero(occ)), int(np.count_nonzero(occ & differs))

    parts = map_slabs(count, nz, slab, threads=threads)
    return sum(p[0] for p in parts), sum(p[1] for p in parts)


def _axis_slice(axis: int, a: int, b: int) -> tuple:
    """Index selecting [a, b) along one axis of a 3D array."""
    return tuple(slice(a, b) if ax == axis else slice(None) for ax in range(3))


def _differs_unmasked(v: np.ndarray, axis: int) -> np.ndarray:
    """_differs without a mask: comparisons of shifted views, no copies of the values."""
    n = v.shape[axis]
    out = np.zeros(v.shape, bool)
    if n < 2:
        return out

    sl = functools.partial(_axis_slice, axis)

    np.not_equal(v[sl(2, n)], v[sl(0, n - 2)], out=out[sl(1, n - 1)])
    np.not_equal(v[sl(1, 2)], v[sl(0, 1)], out=out[sl(0, 1)])
    np.not_equal(v[sl(n - 1, n)], v[sl(n - 2, n - 1)], out=out[sl(n - 1, n)])
    return out


def _differs(v: np.ndarray, ok: np.ndarray, axis: int) -> np.ndarray:
    """Whether the gradient test along ``axis`` sees two different values: the neighbours on both
    sides where both are valid, else the voxel and its one valid neighbour, else nothing. Whole-array
    selects of shifted views (boolean-mask indexing took 7x as long and held the interpreter)."""
    n = v.shape[axis]
    if n < 2:
        return np.zeros(v.shape, bool)

    sl = functools.partial(_axis_slice, axis)

    lo = v.copy()  # the value behind each voxel: its neighbour where that is valid, else itself
    np.copyto(lo[sl(1, n)], v[sl(0, n - 1)], where=ok[sl(0, n - 1)])
    hi = v.copy()  # the value ahead of it, the same way
    np.copyto(hi[sl(0, n - 1)], v[sl(1, n)], where=ok[sl(1, n)])
    some = np.zeros(v.shape, bool)  # at least one valid neighbour
    some[sl(1, n)] = ok[sl(0, n - 1)]
    some[sl(0, n - 1)] |= ok[sl(1, n)]
    return np.not_equal(lo, hi) & some


# ----------------------------------------------------------------------------------------------
# budget (SPEC section 4)


def split_budget(n: int) -> tuple[int, int]:
    """(detail seeds, coverage seeds) for a budget of n: floor(0.55 n) detail, the rest coverage."""
    nd = (DETAIL_PERCENT * n) // 100
    return nd, n - nd


def seed_limit(eligible: int, occupied: int) -> int:
    """N_max = floor(min(eligible / 0.55, occupied / 0.45)) of SPEC section 4, in exact integers.

    Every N <= N_max fits the split of :func:`split_budget`: floor(0.55 N) <= 0.55 N <= eligible
    and N - floor(0.55 N) = ceil(0.45 N) <= occupied.
    """
    return min((100 * eligible) // DETAIL_PERCENT, (100 * occupied) // (100 - DETAIL_PERCENT))


def budget_from_ratio(source_bytes: int, ratio: float, header_bytes: int, bytes_per_primitive: int = 48) -> int:
    """N = floor((S_src / R - H) / bytes per primitive) (SPEC section 4)."""
    if not ratio > 0:
        raise WarpgaussError(f"--ratio must be positive, got {ratio}")
    return budget_from_bytes(source_bytes / ratio, source_bytes, header_bytes, bytes_per_primitive)


def budget_from_bytes(
    total_bytes: float,
    source_bytes: int,
    header_bytes: int,
    bytes_per_primitive: int,
    format: str | None = None,
    measured: tuple[float, float] | None = None,
) -> int:
    """N = floor((B - H) / bytes per primitive) for a file of B bytes; refused when none fits
    (``format`` "coded": the bytes per primitive are what a coded primitive is sized at, and
    ``measured`` the range refined models coded at, which the refusal quotes)."""
    n = int(np.floor((total_bytes - header_bytes) / bytes_per_primitive))
    if n < 1:
        per = f"{bytes_per_primitive} per primitive"
        if format == "coded":
            seen = f"{measured[0]:g}-{measured[1]:g} bytes on refined models, " if measured else ""
            per = f"a coded Gaussian takes {seen}{bytes_per_primitive} assumed here"
        about = "about " if format == "coded" else ""
        raise WarpgaussError(
            f"a budget of {total_bytes:.0f} bytes leaves no room for a single primitive ({header_bytes} header bytes, "
            f"{per}); the largest possible ratio is {about}{source_bytes / (header_bytes + bytes_per_primitive):.4g}"
        )
    return n


def ratio_for_budget(source_bytes: int, n: int, header_bytes: int, bytes_per_primitive: int = 48) -> float:
    """Compression ratio S_src / (bytes per primitive * N + H)."""
    return source_bytes / (bytes_per_primitive * n + header_bytes)


def check_budget(f: Field, n: int, header_bytes: int, bytes_per_primitive: int = 48) -> None:
    """Refuse a budget of zero or beyond the seed limit, naming N_max and the nearest feasible ratio."""
    if n < 1:
        raise WarpgaussError(f"the budget must be at least 1 primitive, got {n}")
    if not f.counted:  # checked once the bricks' statistics have counted it (encode_bricked)
        return
    n_max = seed_limit(f.eligible, f.occupied)
    if n_max < 1:
        raise WarpgaussError(
            f"the volume has {f.occupied} occupied voxels (normalised value > {OCCUPIED}) and {f.eligible} with a "
            "non-zero gradient: too few to place any primitive"
        )
    if n > n_max:
        r = ratio_for_budget(f.source_bytes, n_max, header_bytes, bytes_per_primitive)
        raise WarpgaussError(
            f"budget {n} exceeds the seed limit N_max = {n_max} of this volume ({f.eligible} occupied voxels "
            f"with non-zero gradient, {f.occupied} occupied); use --budget {n_max} or less, i.e. --ratio {r:.4g} "
            "or more"
        )


# ----------------------------------------------------------------------------------------------
# device volume and structure statistics (SPEC section 5)


class DeviceVolume:
    """The normalised field and its validity mask resident on a Warp device."""

    def __init__(self, f: Field, device: str, same_values: DeviceVolume | None = None, on_host: bool = False):
        """``same_values``: a volume on ``device`` whose field holds the very same values array
        (another mask over one box): its device values are shared, not copied again. ``on_host``:
        on a CUDA device, the values and mask in pinned host memory, which its kernels read over
        the bus (``on_host`` then True; on the CPU device it changes nothing)."""
        from ..core.warp import warp

        wp = warp()
        self.field = f
        self.device = device
        self.values: Any
        self.mask: Any
        problem = voxels_problem(f.values.shape, limits.MAX_HOST_VOXELS if on_host else None)
        if problem is not None:
            raise WarpgaussError(problem)
        host = bool(on_host) and wp.get_device(device).is_cuda and not hasattr(f.values, "array")
        self.on_host = host
        where, pinned = ("cpu", True) if host else (device, False)
        # normalised into host memory of its own (normalise(pinned=True)): read there, not copied
        held = f.host_arrays if (host or not wp.get_device(device).is_cuda) else None
        if same_values is not None and same_values.field.values is f.values and str(same_values.device) == str(device):
            self.values = same_values.values
        elif held is not None:
            self.values = held[0]
        elif hasattr(f.values, "array"):  # normalised on a device (warpgauss.field.device): used where it is
            self.values = _on(f.values.array, device)
        else:
            self.values = wp.array(f.values, dtype=float, device=where, pinned=pinned)
        if f.mask is not None:
            m = f.mask
            if held is not None and held[1] is not None:
                self.mask = held[1]
            else:  # hasattr: on a device already
                self.mask = _on(m.array, device) if hasattr(m, "array") else mask_to_device(m, where, pinned)
            self.has_mask = 1
        else:
            self.mask = wp.zeros((1, 1, 1), dtype=wp.uint8, device=device)
            self.has_mask = 0


def mask_to_device(mask: np.ndarray, device: str, pinned: bool = False):
    """A host validity mask as a Warp uint8 array on ``device`` (``pinned``: page-locked host
    memory): booleans are bytes already, so they are viewed as uint8, not converted (a copy on the host)."""
    from ..core.warp import warp

    wp = warp()
    host = np.ascontiguousarray(mask).view(np.uint8) if mask.dtype == np.bool_ else mask.astype(np.uint8)
    return wp.array(host, dtype=wp.uint8, device=device, pinned=pinned)


def _on(arr, device: str):
    """A device array on ``device``: itself, or a copy made there."""
    from ..core.warp import warp

    return arr if str(arr.device) == str(device) else warp().clone(arr, device=device)


def structure_stats(dv: DeviceVolume, seed: int = 0) -> dict:
    """Occupancy, gradient top-10 % share and S(1)/S(16) (SPEC section 5).

    Uses every voxel up to :data:`STATS_EXACT_VOXELS`, else :data:`STATS_SAMPLES` voxels drawn
    uniformly (with replacement) with a fixed seed.
    """
    from ..core.warp import warp
    from ..kernels import analysis as ka

    wp = warp()
    f = dv.field
    exact = f.n_voxels <= STATS_EXACT_VOXELS
    if exact:
        idx = np.arange(f.n_voxels, dtype=np.int64)
    else:
        idx = np.random.default_rng(seed).integers(0, f.n_voxels, STATS_SAMPLES, dtype=np.int64)
    voxel = wp.array(idx, dtype=wp.int64, device=dv.device)
    out = wp.empty((idx.size, 6), dtype=float, device=dv.device)
    wp.launch(
        ka.structure_samples,
        dim=idx.size,
        inputs=[dv.values, dv.mask, dv.has_mask, voxel, STRUCTURE_LAG],
        outputs=[out],
        device=dv.device,
    )
    t = out.numpy()
    g = t[t[:, 0] > 0, 1].astype(np.float64)
    top = max(1, int(np.ceil(0.1 * g.size))) if g.size else 0
    total = g.sum()
    # the largest tenth by a partition, not a sort of every occupied voxel (most of this stage's
    # host time on a head MRI); summed in descending order as before
    grad_top10 = float(np.sort(np.partition(g, g.size - top)[g.size - top :])[::-1].sum() / total) if g.size and total > 0 else 0.0
    s1, n1, s16, n16 = (t[:, c].astype(np.float64).sum() for c in (2, 3, 4, 5))
    s1 = s1 / max(n1, 1.0)
    s16 = s16 / max(n16, 1.0)
    return {
        "occupancy": f.occupancy,
        "occupied_voxels": f.occupied,
        "eligible_detail_voxels": f.eligible,
        "valid_voxels": f.n_valid,
        "grad_top10": grad_top10,
        "s1": float(s1),
        "s16": float(s16),
        "s1_s16": float(s1 / s16) if s16 > 0 else None,  # None: no structure at lag 16 (or a grid under 17 voxels)
        "sampled": not exact,
        "samples": int(idx.size),
    }
