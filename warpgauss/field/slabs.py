"""A volume held in host memory (``DeviceVolume(on_host=True)``), brought to the device a slab of
z slices at a time for the kernels that read many voxels around each point (the seeds' structure
tensors): over the bus each such read is a transaction of its own, a slab copy is one stream.
Measured at 1024^3 (H200, ``benchmarks/bricked/volume_on_host.py``): the seeds' frames read in
place over the bus took 98.5 s where the same kernel on the device took 0.13 s."""

from __future__ import annotations

from collections.abc import Iterator

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


def host_buffers(shape: tuple[int, ...], masked: bool) -> tuple[np.ndarray, np.ndarray | None, tuple]:
    """(values, mask, arrays) for a volume of ``shape`` normalised straight into host memory that a
    GPU's kernels read over the bus: float32 values and (``masked``) a validity mask, all True,
    as numpy views of the Warp arrays that hold them (``arrays`` = (values, mask or None)), in
    page-locked memory where CUDA is available (else ordinary host memory, the same arrays). A
    volume in host memory is then held once, not as its normalised values and their pinned copy."""
    from ..core.warp import warp

    wp = warp()
    pinned = wp.is_cuda_available()
    values = wp.empty(shape, dtype=float, device="cpu", pinned=pinned)
    mask = wp.empty(shape, dtype=wp.uint8, device="cpu", pinned=pinned) if masked else None
    ok = None
    if mask is not None:
        ok = mask.numpy().view(np.bool_)
        ok.fill(True)
    return values.numpy(), ok, (values, mask)


def by_slab(slices: np.ndarray, ranges: list[tuple[int, int]]) -> list[np.ndarray]:
    """Indices of ``slices`` (a z slice each) grouped by the consecutive ``ranges`` [lo, hi) that
    cover them, each group in ascending index order."""
    order = np.argsort(slices, kind="stable")
    cuts = np.searchsorted(slices[order], [lo for lo, _ in ranges] + [ranges[-1][1]])
    return [np.sort(order[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
