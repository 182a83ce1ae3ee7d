"""A brick's box on the device: the masks of its regions, its seed-candidate counts and its |grad V|
sum, where the host took them slab by slab (:func:`warpgauss.field.analysis.count_seed_candidates`,
:func:`warpgauss.encoding.scale.plan.grad_sum`).

A brick's start on one GPU spent most of its time there: at 1024^3 in 2x2x2 bricks, 1.9 s of a
brick's 2.2 s went to the host's masks, counts and sums while the GPU waited, 17.5 s in all for
the 8 bricks (one H200, ``benchmarks/bricked/setup_profile.py``,
``results/bricked/setup_profile_1024_h200.json``). Here the box's values stay on the device (a
view of the whole volume put there once, or the box uploaded) and each pass is one kernel with a
thread per (z, y) row whose results the host sums in row order: the counts are exact (the same
comparisons as the host's), the |grad V| sum the host's float32 arithmetic summed in another
order (equal to about 1e-7).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

Region = tuple[tuple[int, int], ...]  # (z, y, x) start, stop pairs


@dataclass(frozen=True)
class BoxCounts:
    """A masked box's valid, occupied and detail-eligible voxels and |grad V| sum over the occupied."""

    n_valid: int
    occupied: int
    eligible: int
    grad_sum: float


def box_counts(values: Any, mask: Any = None) -> BoxCounts:
    """The :class:`BoxCounts` of ``values`` (a Warp float32 3D array or view) under ``mask`` (a
    Warp uint8 array of the same shape, or None: every voxel valid), on their device."""
    from ..core.warp import warp
    from ..kernels import analysis as ka

    wp = warp()
    dev = values.device
    rows = (int(values.shape[0]), int(values.shape[1]))
    has = int(mask is not None)
    m = mask if mask is not None else wp.zeros((1, 1, 1), dtype=wp.uint8, device=dev)
    ok, occ, elig = (wp.empty(rows, dtype=int, device=dev) for _ in range(3))
    grad = wp.empty(rows, dtype=wp.float64, device=dev)
    wp.launch(ka.row_box_counts, dim=rows, inputs=[values, m, has], outputs=[ok, occ, elig, grad], device=dev)
    return BoxCounts(
        int(ok.numpy().astype(np.int64).sum()),
        int(occ.numpy().astype(np.int64).sum()),
        int(elig.numpy().astype(np.int64).sum()),
        float(grad.numpy().sum()),
    )


def region_mask(shape_zyx: Sequence[int], device: str, regions: Sequence[Region], exclude: Region | None = None, valid: Any = None):
    """A uint8 mask on ``device``: 1 where a voxel is valid (``valid``: a uint8 array or view of
    that shape, or None), inside one of ``regions`` and outside ``exclude``."""
    from ..core.warp import warp
    from ..kernels import analysis as ka

    wp = warp()
    shape = tuple(int(s) for s in shape_zyx)
    boxes = np.array([[a for pair in r for a in pair] for r in regions], np.int32).reshape(-1, 6)
    out_box = np.array([a for pair in exclude for a in pair] if exclude is not None else [0, 0, 0, 0, 0, 0], np.int32)
    out = wp.empty(shape, dtype=wp.uint8, device=device)
    v = valid if valid is not None else wp.zeros((1, 1, 1), dtype=wp.uint8, device=device)
    wp.launch(
        ka.region_mask,
        dim=shape,
        inputs=[v, int(valid is not None), wp.array(boxes, dtype=int, device=device), wp.array(out_box, dtype=int, device=device)],
        outputs=[out],
        device=device,
    )
    return out


def box_view(arr: Any, box: Region):
    """The ``(z, y, x)`` box of a Warp 3D array, as a view (no copy)."""
    (z0, z1), (y0, y1), (x0, x1) = box
    return arr[z0:z1, y0:y1, x0:x1]
