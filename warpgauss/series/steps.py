"""Time series: one model per timestep, each of the same N, each refined from the previous one.

A series is a list of volumes (paths, a glob pattern, or arrays). Every input is checked before
any work (files exist, one grid for all, outputs writable); timestep 0 is encoded as usual, and
timestep t > 0 starts from timestep t-1's model (:func:`warpgauss.encode`'s ``warm_start``) with
``warm_iterations`` (default: the configured iterations) unless ``cold``. Key frames: a warm
timestep whose PSNR falls more than ``keyframe_drift`` dB below the best warm PSNR since the
chain's last cold timestep is encoded again cold and the better of the two kept; the chain goes on
from it. One ``.wgs`` per timestep: each stays an
ordinary model that decode, render and eval read alone.
"""

from __future__ import annotations

import contextlib
import dataclasses
import glob as _glob
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import WarpgaussError
from ..format.model import Model
from ..readers.timesteps import TimeStep, time_arrays, time_steps

__all__ = ["TimeStep", "encode_series", "iter_series", "series_chains", "series_sources", "time_steps"]

# A warm timestep this many dB below the best warm one since the last cold timestep is re-encoded
# cold. 16-step chains at 512^3, N 400k, 375 warm iterations (benchmarks/results/series/warm_vs_cold_series512_*_stay_h100.json):
# bubbles stay within 0.9 dB of their best (never re-encoded); the vortex drifts 3 dB from step 5,
# the interface 10 dB (1-1.7 dB a step), where a cold timestep costs 2.5-3x a warm one.
KEYFRAME_DRIFT_DB = 1.0


def series_sources(sources) -> list:
    """The series' inputs: the timesteps of a file with a time axis (its first 4D array), the
    matches of a glob pattern (sorted), or a list of paths and arrays."""
    if isinstance(sources, (str, os.PathLike)):
        steps = time_steps(sources)
        if steps is not None:
            return steps
    return _listed(sources)


def _listed(sources) -> list:
    """A glob pattern's matches (sorted), or the list given."""
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
    if isinstance(src, TimeStep):
        kind, found = time_arrays(Path(src.path))
        return tuple(int(v) for v in dict(found)[src.key][1:][::-1])
    if isinstance(src, np.ndarray):
        if src.ndim != 3:
            raise WarpgaussError(f"a series array is {src.ndim}D (shape {src.shape}); warpgauss encodes 3D volumes")
        return tuple(int(v) for v in src.shape[::-1])
    from ..readers import ReadOptions

    p = Path(src)
    if not p.exists():
        raise WarpgaussError(f"no such file in the series: {p}")
    vol = (read or ReadOptions()).read(p, lazy=True)
    return tuple(int(v) for v in vol.data.shape[::-1])


def series_chains(sources, variables=None, read=None) -> list[tuple[str | None, list, Any]]:
    """The series to encode: one chain (variable, timesteps, reader options) per variable.

    A container file whose variable is ``(t, z, y, x)`` gives its timesteps
    (:class:`TimeStep`); otherwise ``sources`` is a glob or a list of files (each holding the
    variable) or arrays. Several ``variables`` give several chains, each warm-started on its own.
    """
    from ..readers import ReadOptions

    read = read or ReadOptions()
    names = list(variables or [])
    if len(set(names)) != len(names):
        raise WarpgaussError(f"a variable is named twice in {names}")
    if not names:
        names = [read.variable if read.variable is not None else read.dataset]
    chains = []
    for var in names:
        opts = read if var is None else dataclasses.replace(read, variable=var, dataset=var)
        steps = None
        if isinstance(sources, (str, os.PathLike)):
            steps = time_steps(sources, var)
        chains.append((var, steps if steps is not None else _listed(sources), opts))
    return chains


def encode_series(
    sources,
    *,
    variables=None,
    budget: int | None = None,
    ratio: float | None = None,
    output_pattern: str | None = None,
    cold: bool = False,
    warm_iterations: int | None = None,
    keyframe_drift: float | None = KEYFRAME_DRIFT_DB,
    force: bool = False,
    read=None,
    on_step=None,
    client=None,
    **encode_kwargs: Any,
) -> list[Model]:
    """Encode every timestep of a series at the same N (see the module docstring).

    Args:
        sources: A glob pattern, a list of paths / 3D arrays in time order, or one HDF5 /
            netCDF / Zarr file whose variable has a time axis ``(t, z, y, x)``.
        variables: Several variables (datasets, arrays) of the files: one chain of models each.
        budget: The budget of timestep 0 (``warpgauss.encode``'s); later timesteps take its N
            exactly.
        ratio: The same as a compression ratio, instead of ``budget``.
        output_pattern: If given, timestep t of variable v is written to
            ``output_pattern.format(t=t, var=v)`` (``{var}`` is needed with several variables).
        cold: Encode every timestep from its own analytic allocation.
        warm_iterations: Refinement iterations of a warm-started timestep (default: as
            configured).
        keyframe_drift: A warm-started timestep whose PSNR falls more than this many dB below
            the best warm PSNR since the chain's last cold timestep is encoded again, cold, and
            the better of the two kept (the cold one: a key frame the chain goes on warm from);
            its report's ``series.keyframe`` says what happened. None or <= 0: never.
        on_step: Optional callback(t, steps, model) after each timestep (on a cluster: as each
            part comes back).
        client: A ``distributed.Client``: the timesteps are spread over its workers, each
            chain split into one run of consecutive timesteps per worker, each run's first
            timestep cold at the chain's N and the rest warm (``cold``: every timestep on its
            own). With ``budget`` (N given) every run starts at once; with ``ratio`` timestep 0
            runs first (it fixes N) and the rest is split, the first run continuing warm from
            it. A part that fails is retried once.
        encode_kwargs: Passed to :func:`warpgauss.encode` (seed, device, format, iterations ...).

    Returns:
        The models, variable by variable, each in time order (each with its report;
        ``report["series"]`` says which variable and step, and whether it was warm-started).
    """
    plan = _plan(
        sources,
        variables=variables,
        budget=budget,
        ratio=ratio,
        output_pattern=output_pattern,
        cold=cold,
        warm_iterations=warm_iterations,
        keyframe_drift=keyframe_drift,
        force=force,
        read=read,
        **encode_kwargs,
    )
    if client is None:
        models: list[Model] = []
        for seg in plan:
            models += encode_segment(seg, on_step)
        return models
    from ..encoding.scale.cluster import share_arrays

    arrays = [x for seg in plan for x in seg.items if isinstance(x, np.ndarray)]
    with contextlib.ExitStack() as stack:
        files, _ = share_arrays(client, arrays, stack) if arrays else (None, None)
        if files is not None:  # the workers of this machine read the timesteps from files, not through the graph
            by_id = {id(a): sf for a, sf in zip(arrays, files)}
            plan = [dataclasses.replace(seg, items=[by_id.get(id(x), x) for x in seg.items]) for seg in plan]
        return _on_cluster(plan, client, on_step)


def iter_series(sources, **kwargs: Any) -> Iterator[Model]:
    """:func:`encode_series` in this process, one model at a time: each is yielded (written, when
    ``output_pattern`` is given) as soon as it is encoded, and only the previous timestep's model
    is held, so a long series needs the memory of two models, not of all. Takes
    :func:`encode_series`'s arguments except ``client`` and ``on_step``; every input is checked
    before the first timestep is encoded."""
    for seg in _plan(sources, **kwargs):
        yield from iter_segment(seg)


def _plan(
    sources,
    *,
    variables=None,
    budget: int | None = None,
    ratio: float | None = None,
    output_pattern: str | None = None,
    cold: bool = False,
    warm_iterations: int | None = None,
    keyframe_drift: float | None = KEYFRAME_DRIFT_DB,
    force: bool = False,
    read=None,
    **encode_kwargs: Any,
) -> list[Segment]:
    """Check a series' inputs before any work and lay out one :class:`Segment` per variable."""
    from ..core.files import check_writable
    from ..encoding.driver.config import EncodeConfig

    for name in ("output", "warm_start", "session", "example"):
        if name in encode_kwargs:
            raise WarpgaussError(f"a series does not take {name}=: it is set per timestep (output_pattern= names the files)")
    EncodeConfig.from_kwargs(**encode_kwargs)  # an unknown option is refused before any timestep

    chains = series_chains(sources, variables, read)
    for var, items, opts in chains:
        grids = {_grid(s, opts) for s in items}
        if len(grids) > 1:
            shown = ", ".join("x".join(map(str, g)) for g in sorted(grids))
            what = "the series' volumes" if var is None else f"the series of {var!r}"
            raise WarpgaussError(f"{what} are on different grids ({shown}); a series shares one grid")
    outputs: list[list[str]] | None = None
    if output_pattern is not None:
        if "{t" not in output_pattern:
            raise WarpgaussError("the output pattern must hold {t} (the timestep), e.g. out_{t:03d}.wgs")
        if len(chains) > 1 and "{var" not in output_pattern:
            raise WarpgaussError("several variables need {var} in the output pattern, e.g. out_{var}_{t:03d}.wgs")
        outputs = [[output_pattern.format(t=t, var=var or "") for t in range(len(items))] for var, items, _ in chains]
        flat = [o for chain in outputs for o in chain]
        if len(set(flat)) != len(flat):
            raise WarpgaussError(f"the output pattern {output_pattern!r} gives one name to several timesteps")
        for o in flat:
            check_writable(o, force=force)
    if warm_iterations is not None and warm_iterations < 0:
        raise WarpgaussError(f"warm iterations must be >= 0, got {warm_iterations}")
    return [
        Segment(
            var,
            opts,
            list(range(len(items))),
            list(items),
            None if outputs is None else outputs[c],
            None,
            None,
            cold,
            warm_iterations,
            force,
            encode_kwargs,
            len(items),
            budget,
            ratio,
            keyframe_drift,
        )
        for c, (var, items, opts) in enumerate(chains)
    ]


@dataclass
class Segment:
    """Consecutive timesteps of one variable's chain, encoded in order by one process: the first
    from ``start`` (the previous timestep's model, warm) or from its own allocation at ``n``
    Gaussians (cold; ``n`` None: the budget or ratio given), the rest each from the one before."""

    var: str | None
    read: Any
    steps: list[int]
    items: list
    outputs: list[str] | None
    start: Model | None
    n: int | None
    cold: bool
    warm_iterations: int | None
    force: bool
    kwargs: dict
    total: int  # timesteps of the whole chain
    budget: int | None = None
    ratio: float | None = None
    keyframe_drift: float | None = KEYFRAME_DRIFT_DB

    def split(self, k: int) -> list[Segment]:
        """Up to ``k`` contiguous parts (the first keeps ``start``; the others start cold at ``n``)."""
        k = max(1, min(k, len(self.steps)))
        bounds = np.linspace(0, len(self.steps), k + 1).round().astype(int)
        parts = []
        for a, b in zip(bounds[:-1], bounds[1:]):
            if b <= a:
                continue
            parts.append(
                dataclasses.replace(
                    self,
                    steps=self.steps[a:b],
                    items=self.items[a:b],
                    outputs=None if self.outputs is None else self.outputs[a:b],
                    start=self.start if a == 0 else None,
                )
            )
        return parts


def encode_segment(seg: Segment, on_step=None) -> list[Model]:
    """Encode a :class:`Segment`'s timesteps in order (in this process or on a Dask worker)."""
    chain: list[Model] = []
    for m in iter_segment(seg):
        chain.append(m)
        if on_step is not None:
            on_step(m.run_report["series"]["step"], seg.total, m)
    return chain


def iter_segment(seg: Segment) -> Iterator[Model]:
    """A :class:`Segment`'s models in time order, each yielded once encoded (only the previous one held)."""
    from ..encoding.entry import encode

    before, first_n = seg.start, seg.n
    best = None  # the best warm PSNR since the last cold timestep (the key-frame rule)
    drift = seg.keyframe_drift if seg.keyframe_drift is not None and seg.keyframe_drift > 0 else None
    from ..readers.lazy import Shared, opened

    for k, (t, item) in enumerate(zip(seg.steps, seg.items)):
        src = opened(item)
        warm = before is not None and not seg.cold
        kw = dict(seg.kwargs)
        n = first_n
        if n is None:
            kw.update(budget=seg.budget, ratio=seg.ratio)
        else:
            kw.update(budget=n)
            kw.pop("file_bytes", None)  # a byte budget sized timestep 0's N; the rest take that N
        out = None if seg.outputs is None else seg.outputs[k]
        cold_kw = dict(kw)
        if warm:
            kw["warm_start"] = before
            if seg.warm_iterations is not None:
                kw["iterations"] = seg.warm_iterations
        m = encode(src, read=seg.read, output=out, force=seg.force, **kw)
        keyframe = None
        psnr = m.run_report.get("psnr_db")
        if warm and drift is not None and psnr is not None:
            if best is not None and psnr < best - drift:
                cold = encode(src, read=seg.read, **cold_kw)
                keyframe = {
                    "why": f"the warm PSNR {psnr:.2f} dB fell more than {drift:g} dB below the chain's best {best:.2f}",
                    "warm_psnr_db": psnr,
                    "cold_psnr_db": cold.run_report.get("psnr_db"),
                    "kept": "warm",
                }
                if (cold.run_report.get("psnr_db") or float("-inf")) > psnr:  # else the field changed: the warm one stays
                    if out is not None:
                        cold.save(out, force=True)  # over the warm model this call wrote
                        cold.run_report["output"] = str(Path(out))
                    m, warm, keyframe["kept"] = cold, False, "cold"
                best = psnr if warm else None  # a new baseline either way
            else:
                best = psnr if best is None else max(best, psnr)
        elif not warm:
            best = None
        m.run_report["series"] = {
            "variable": seg.var,
            "step": t,
            "steps": seg.total,
            "warm_start": warm,
            "source": "array" if isinstance(item, (np.ndarray, Shared)) else str(item),
        }
        if keyframe is not None:
            m.run_report["series"]["keyframe"] = keyframe
        if first_n is None:
            first_n = m.n  # timestep 0 fixes N for the rest of the chain
        before = m
        yield m


def _on_cluster(plan: list[Segment], client, on_step) -> list[Model]:
    """The segments on a Dask cluster, each chain split into one contiguous part per worker
    (timesteps cold: one part each). Where ``budget`` gives N, every part starts at once (a
    part's first timestep is cold at that N); where N comes from a ratio or byte budget, the
    chain's timestep 0 runs first (it fixes N, the other parts wait for it) and the rest is
    split. A part that fails is retried once, one that fails twice fails the run."""
    workers = max(1, len(client.scheduler_info().get("workers", {})))

    def parts_of(seg: Segment) -> list[Segment]:
        return seg.split(len(seg.steps) if seg.cold else workers) if seg.steps else []

    waiting = [seg for seg in plan if seg.budget is None]  # N from a ratio or byte budget: timestep 0 first
    firsts = [
        dataclasses.replace(seg, steps=seg.steps[:1], items=seg.items[:1], outputs=None if seg.outputs is None else seg.outputs[:1])
        for seg in waiting
    ]
    parts = [part for seg in plan if seg.budget is not None for part in parts_of(seg)]
    done = _gather(client, firsts + parts, on_step)
    heads, done = done[: len(firsts)], done[len(firsts) :]
    rests: list[Segment] = []
    for seg, head in zip(waiting, heads):
        rest = dataclasses.replace(
            seg,
            steps=seg.steps[1:],
            items=seg.items[1:],
            outputs=None if seg.outputs is None else seg.outputs[1:],
            start=head[0],
            n=head[0].n,
        )
        rests += parts_of(rest)
    done += _gather(client, rests, on_step)
    parts += rests
    by_var: dict = {}
    for seg, head in zip(waiting, heads):
        by_var.setdefault(seg.var, []).extend(head)
    for part, models in zip(parts, done):
        by_var.setdefault(part.var, []).extend(models)
    return [m for seg in plan for m in sorted(by_var[seg.var], key=lambda m: m.run_report["series"]["step"])]


def _gather(client, segments: list[Segment], on_step) -> list[list[Model]]:
    from ..encoding.scale.cluster import map_on_cluster

    def after(done: int, i: int, models: list[Model]) -> None:
        if on_step is not None:
            for m in models:
                on_step(m.run_report["series"]["step"], segments[i].total, m)

    keys = [f"warpgauss-series-{i}-{id(s)}" for i, s in enumerate(segments)]
    return map_on_cluster(client, encode_segment, segments, keys, "a series part", after=after) if segments else []
