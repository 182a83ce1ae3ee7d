"""Time series: one model per timestep, each of the same N, each refined from the previous one.

A series is a list of volumes (paths, a glob pattern, or arrays). Every input is checked before
any work (files exist, one grid for all, outputs writable); timestep 0 is encoded as usual, and
timestep t > 0 starts from timestep t-1's model (:func:`warpgauss.encode`'s ``warm_start``) with
``warm_iterations`` (default: the configured iterations) unless ``cold``. One ``.wgs`` per
timestep: each stays an ordinary model that decode, render and eval read alone.
"""

from __future__ import annotations

import glob as _glob
import os
from pathlib import Path
from typing import Any

import numpy as np

from .errors import WarpgaussError
from .model import Model


def series_sources(sources) -> list:
    """The series' inputs: a glob pattern (sorted matches), or a list of paths and arrays."""
    if isinstance(sources, (str, os.PathLike)):
        pattern = str(sources)
        found = sorted(_glob.glob(pattern))
        if not found:
            raise WarpgaussError(f"no file matches {pattern!r}; give a glob such as 'run/t_*.raw' or a list of files")
        return found
    out = list(sources)
    if not out:
        raise WarpgaussError("the series is empty; give at least one volume")
    return out


def _grid(src, read) -> tuple[int, ...]:
    """(x, y, z) of a series input, reading no voxels where the format allows."""
    if isinstance(src, np.ndarray):
        if src.ndim != 3:
            raise WarpgaussError(f"a series array is {src.ndim}D (shape {src.shape}); warpgauss encodes 3D volumes")
        return tuple(int(v) for v in src.shape[::-1])
    from .io import ReadOptions

    p = Path(src)
    if not p.exists():
        raise WarpgaussError(f"no such file in the series: {p}")
    vol = (read or ReadOptions()).read(p, lazy=True)
    return tuple(int(v) for v in vol.data.shape[::-1])


def encode_series(
    sources,
    *,
    budget: int | None = None,
    ratio: float | None = None,
    output_pattern: str | None = None,
    cold: bool = False,
    warm_iterations: int | None = None,
    force: bool = False,
    read=None,
    on_step=None,
    **encode_kwargs: Any,
) -> list[Model]:
    """Encode every timestep of a series at the same N (see the module docstring).

    Args:
        sources: A glob pattern, or a list of paths / 3D arrays, in time order.
        budget, ratio: The budget of timestep 0 (``warpgauss.encode``'s); later timesteps take
            its N exactly.
        output_pattern: If given, timestep t is written to ``output_pattern.format(t=t)``.
        cold: Encode every timestep from its own analytic allocation.
        warm_iterations: Refinement iterations of a warm-started timestep (default: as
            configured).
        on_step: Optional callback(t, steps, model) after each timestep.
        encode_kwargs: Passed to :func:`warpgauss.encode` (seed, device, format, iterations ...).

    Returns:
        The models, in time order (each with its report; ``report["series"]`` says which step
        and whether it was warm-started).
    """
    from ._fs import check_writable
    from .pipeline import encode

    items = series_sources(sources)
    grids = {_grid(s, read) for s in items}
    if len(grids) > 1:
        shown = ", ".join("x".join(map(str, g)) for g in sorted(grids))
        raise WarpgaussError(f"the series' volumes are on different grids ({shown}); a series shares one grid")
    outputs = None
    if output_pattern is not None:
        if "{t" not in output_pattern:
            raise WarpgaussError("the output pattern must hold {t} (the timestep), e.g. out_{t:03d}.wgs")
        outputs = [output_pattern.format(t=t) for t in range(len(items))]
        if len(set(outputs)) != len(outputs):
            raise WarpgaussError(f"the output pattern {output_pattern!r} gives one name to several timesteps")
        for o in outputs:
            check_writable(o, force=force)
    if warm_iterations is not None and warm_iterations < 0:
        raise WarpgaussError(f"warm iterations must be >= 0, got {warm_iterations}")
    models: list[Model] = []
    for t, src in enumerate(items):
        warm = t > 0 and not cold
        kw = dict(encode_kwargs)
        if t == 0:
            kw.update(budget=budget, ratio=ratio)
        else:
            kw.update(budget=models[0].n)
        if warm:
            kw["warm_start"] = models[-1]
            if warm_iterations is not None:
                kw["iterations"] = warm_iterations
        m = encode(
            src,
            read=read,
            output=None if outputs is None else outputs[t],
            force=force,
            **kw,
        )
        m.report["series"] = {
            "step": t,
            "steps": len(items),
            "warm_start": warm,
            "source": "array" if isinstance(src, np.ndarray) else str(src),
        }
        models.append(m)
        if on_step is not None:
            on_step(t, len(items), m)
    return models
