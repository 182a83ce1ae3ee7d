"""A volume held in host memory (``DeviceVolume(on_host=True)``), brought to the device a slab of
z slices at a time for the kernels that read many voxels around each point (the seeds' structure
tensors): over the bus each such read is a transaction of its own, a slab copy is one stream.
Measured at 1024^3 (H200, ``benchmarks/bricked/volume_on_host.py``): the seeds' frames read in
place over the bus took 98.5 s where the same kernel on the device took 0.13 s."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

SLAB_BYTES = 256 << 20  # the device memory one slab of values takes (its halo included), about


def slab_ranges(shape: tuple[int, int, int], reach: int, slab_bytes: int | None = None) -> list[tuple[int, int]]:
    """Consecutive ranges [lo, hi) of z slices that cover a volume of ``shape`` (z, y, x), each
    small enough that it and ``reach`` slices either side take about ``slab_bytes`` as float32."""
    nz, ny, nx = shape
    slab_bytes = SLAB_BYTES if slab_bytes is None else slab_bytes
    own = max(1, slab_bytes // (ny * nx * 4) - 2 * reach)
    return [(lo, min(nz, lo + own)) for lo in range(0, nz, own)]


def z_slabs(dv, reach: int, slab_bytes: int | None = None) -> Iterator[tuple[int, int, int, object, object]]:
    """(lo, hi, kz0, values, mask) for each of :func:`slab_ranges`: ``values`` (and ``mask``
    where the volume has one, else its placeholder) are device copies of slices kz0 .. min(nz,
    hi + reach), kz0 = max(0, lo - reach), so a kernel that reads up to ``reach`` slices beyond a
    point of [lo, hi) finds them all. One slab's buffers are reused for the next (the copies and
    the kernels that read them run in order on the device's stream)."""
    from ..core.warp import warp

    wp = warp()
    nz, ny, nx = dv.values.shape
    ranges = slab_ranges((nz, ny, nx), reach, slab_bytes)
    rows = min(nz, ranges[0][1] - ranges[0][0] + 2 * reach)
    vals = wp.empty((rows, ny, nx), dtype=float, device=dv.device)
    mask = wp.empty((rows, ny, nx), dtype=wp.uint8, device=dv.device) if dv.has_mask else dv.mask
    for lo, hi in ranges:
        kz0, kz1 = max(0, lo - reach), min(nz, hi + reach)
        n = (kz1 - kz0) * ny * nx
        wp.copy(vals, dv.values, src_offset=kz0 * ny * nx, count=n)
        if dv.has_mask:
            wp.copy(mask, dv.mask, src_offset=kz0 * ny * nx, count=n)
        yield lo, hi, kz0, vals[: kz1 - kz0], (mask[: kz1 - kz0] if dv.has_mask else mask)


def host_buffers(shape: tuple[int, ...], masked: bool) -> tuple[np.ndarray, np.ndarray | None, Callable[[], tuple]]:
    """(values, mask, finish) for a volume of ``shape`` normalised straight into host memory that a
    GPU's kernels read over the bus: float32 values and (``masked``) a validity mask to be written
    whole by the caller (on threads), and ``finish()``, called once they are, which returns the Warp
    arrays over the same memory (values, mask or None), page-locked where CUDA is available. A
    volume in host memory is then held once, not as its normalised values and their pinned copy.

    Where the CUDA driver takes it, the memory is ordinary and registered page-locked after the
    caller's writes have touched its pages (:func:`page_locked`): on an H200's host, Warp's pinned
    allocation of 8 GiB took 5.1 s (22.4 s for a 2048^3 volume, most of stage P) where registering
    8 GiB of touched pages took 0.33 s. Elsewhere Warp's pinned allocation (or, without CUDA,
    ordinary host memory), the same arrays."""
    from ..core.warp import warp

    wp = warp()
    if _registers():
        values = _host_array(shape, np.float32)
        mask = _host_array(shape, np.bool_) if masked else None

        def finish() -> tuple:
            v = page_locked(values, float)
            m = None if mask is None else page_locked(mask.view(np.uint8), wp.uint8)
            if v is not None and (mask is None or m is not None):
                return v, m
            pinned = wp.is_cuda_available()  # the driver refused: a pinned copy
            return wp.array(values, dtype=float, device="cpu", pinned=pinned), None if mask is None else wp.array(
                mask.view(np.uint8), dtype=wp.uint8, device="cpu", pinned=pinned
            )

        return values, mask, finish
    pinned = wp.is_cuda_available()
    warr = wp.empty(shape, dtype=float, device="cpu", pinned=pinned)
    marr = wp.empty(shape, dtype=wp.uint8, device="cpu", pinned=pinned) if masked else None
    ok = None if marr is None else marr.numpy().view(np.bool_)
    return warr.numpy(), ok, lambda: (warr, marr)


# the volume's host memory in transparent huge pages (an anonymous map advised MADV_HUGEPAGE) before
# it is registered: fewer translations for the GPU's scattered reads across it. Off until measured
# (on an H200's host registering 8 GiB of huge pages took 0.23 s against 0.33 s of 4 KiB pages;
# the encode's reads not measured); out_of_core.py --huge-pages turns it on for a run
HUGE_PAGES = False


def _host_array(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialised host array of ``shape`` (in transparent huge pages with :data:`HUGE_PAGES`,
    where the platform has them: the array holds its map)."""
    import mmap

    count = int(np.prod(shape, dtype=np.int64))
    advice = getattr(mmap, "MADV_HUGEPAGE", None)
    if not HUGE_PAGES or advice is None or not hasattr(mmap, "MAP_ANONYMOUS") or count == 0:
        return np.empty(shape, dtype)
    m = mmap.mmap(-1, count * np.dtype(dtype).itemsize, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    m.madvise(advice)
    return np.frombuffer(m, dtype, count=count).reshape(shape)


def _registers() -> bool:
    """Whether host memory can be registered page-locked here: CUDA available and its driver loaded."""
    from ..core.warp import warp

    return bool(warp().is_cuda_available()) and _driver() is not None


def _context() -> int:
    """The CUDA context registrations are made in (portable: every context sees them)."""
    from ..core.warp import warp

    return int(warp().get_cuda_device().context)


def _driver():
    """The CUDA driver library (ctypes), None where it does not load."""
    global _DRIVER
    if _DRIVER is None:
        import ctypes

        try:
            lib = ctypes.CDLL("libcuda.so.1")
        except OSError:
            _DRIVER = False
            return None
        lib.cuMemHostRegister_v2.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_uint]
        lib.cuMemHostUnregister.argtypes = [ctypes.c_void_p]
        lib.cuCtxPushCurrent_v2.argtypes = [ctypes.c_void_p]
        lib.cuCtxPopCurrent_v2.argtypes = [ctypes.c_void_p]
        _DRIVER = lib
    return _DRIVER or None


_DRIVER: Any = None  # the ctypes library, False where it did not load, None: not tried
HOST_REGISTER_FLAGS = 3  # CU_MEMHOSTREGISTER_PORTABLE | CU_MEMHOSTREGISTER_DEVICEMAP: every context, mapped


def page_locked(arr: np.ndarray, dtype):
    """A Warp CPU array over ``arr``'s memory (C-contiguous), registered page-locked with the CUDA
    driver so that every GPU's kernels read it over the bus, unregistered when the Warp array goes
    (which keeps ``arr`` alive until then); None where the driver refuses."""
    import ctypes
    import weakref

    from ..core.warp import warp

    wp = warp()
    lib = _driver()
    if lib is None or not arr.flags.c_contiguous or arr.nbytes == 0:
        return None
    ctx = ctypes.c_void_p(_context())
    ptr = int(arr.ctypes.data)
    if lib.cuCtxPushCurrent_v2(ctx) != 0:
        return None
    try:
        if lib.cuMemHostRegister_v2(ptr, arr.nbytes, HOST_REGISTER_FLAGS) != 0:
            return None
    finally:
        lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))
    out = wp.array(ptr=ptr, shape=arr.shape, dtype=dtype, device="cpu", pinned=True)
    weakref.finalize(out, _unregister, lib, ctx, ptr, arr)
    return out


def _unregister(lib, ctx, ptr: int, arr: np.ndarray) -> None:
    """Undo :func:`page_locked` (``arr`` held until now, so its memory outlives the registration)."""
    import ctypes

    if lib.cuCtxPushCurrent_v2(ctx) == 0:
        lib.cuMemHostUnregister(ptr)
        lib.cuCtxPopCurrent_v2(ctypes.byref(ctypes.c_void_p()))


def by_slab(slices: np.ndarray, ranges: list[tuple[int, int]]) -> list[np.ndarray]:
    """Indices of ``slices`` (a z slice each) grouped by the consecutive ``ranges`` [lo, hi) that
    cover them, each group in ascending index order."""
    order = np.argsort(slices, kind="stable")
    cuts = np.searchsorted(slices[order], [lo for lo, _ in ranges] + [ranges[-1][1]])
    return [np.sort(order[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
