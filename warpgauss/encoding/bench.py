"""Kernel microbenchmarks: ``warpgauss bench kernels``.

Times each stage of a refinement iteration, the whole iteration (CUDA graph replay and plain
launches), decode, and the dense all-pairs evaluator, over primitive counts N and samples per
iteration M, on a smooth fully occupied field of ``size``^3 voxels. Primitives are spread
uniformly with sigma = ``sigma_spacing`` x the mean spacing (anisotropic, randomly rotated), which
gives about 150-200 contributing pairs per sample, as a refined model does.

Stage times on CUDA come from events around ``repeat`` back-to-back calls (GPU time, including
any gaps from launch overhead); on the CPU from the wall clock. The iteration is timed by wall
clock over ``repeat`` :meth:`~warpgauss.encoding.refine.Refiner.step` calls, re-bins included.
"""

from __future__ import annotations

import datetime as dt
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._version import __version__
from ..core.warp import device_name, resolve_device, warp
from ..errors import WarpgaussError
from ..field.analysis import DeviceVolume, normalise

GPU_DEFAULTS: dict[str, Any] = {
    "size": 1024,
    "ns": (2_000, 20_000, 200_000, 650_000, 1_400_000),
    "samples": (3_072, 65_536, 262_144, 1_048_576),
}
CPU_DEFAULTS: dict[str, Any] = {"size": 48, "ns": (500, 2_000), "samples": (1_024, 4_096)}


@dataclass
class KernelBenchConfig:
    size: int
    ns: tuple[int, ...]
    samples: tuple[int, ...]
    repeat: int = 10
    dense_max_n: int = 0  # dense evaluator at N up to this (smallest M only); 0: none
    decode: bool = True
    sigma_spacing: float = 0.7
    seed: int = 0
    atomic_baseline: bool = True  # also time the point-major atomic scatter (the pre-sort baseline)


def source_commit(where) -> str | None:
    """The commit the benchmark ran from: $WARPGAUSS_COMMIT where set (a copy of the work tree, as
    on a lent GPU machine, has no or a stale git directory), else ``git rev-parse HEAD`` in
    ``where``; None when neither says."""
    import os
    import subprocess

    if os.environ.get("WARPGAUSS_COMMIT"):
        return os.environ["WARPGAUSS_COMMIT"]
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, check=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def result_header(benchmark: str, script: str, argv, device: str) -> dict:
    """The fields every benchmark's JSON starts with: what it measures, the command that produced it
    (``script``: the benchmark's ``__file__``; ``argv``: its arguments, None: ``sys.argv[1:]``), the
    warpgauss version and commit, the device, its name, the Warp version and the date (UTC)."""
    import sys

    parts = Path(script).resolve().parts
    rel = "/".join(parts[parts.index("benchmarks") :]) if "benchmarks" in parts else Path(script).name
    args = list(sys.argv[1:] if argv is None else argv)
    return {
        "benchmark": benchmark,
        "command": " ".join(["python", rel, *args]),
        "warpgauss_version": __version__,
        "commit": source_commit(Path(script).resolve().parent),
        "device": device,
        "device_name": device_name(device),
        "warp_version": warp().config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
    }


def warmed_device(device: str | None = None) -> str:
    """``device`` resolved (None: CUDA when present), its refinement kernels loaded and a tiny
    encode run, so that no timed encode pays for compiling or loading them."""
    from ..readers.synthetic import generate
    from .entry import encode
    from .refine import load_kernels

    dev = resolve_device(device)
    load_kernels(dev)
    encode(generate("vortex", 24), budget=60, device=dev, iterations=3, samples=64, format="full", self_test=False)
    return dev


def bench_field(size: int):
    """A smooth, fully occupied field of size^3 voxels in [0.1, 0.9] (cheap to make at 1024^3)."""
    c = ((np.arange(size, dtype=np.float32) + 0.5) / size) * np.float32(2 * math.pi)
    v = np.empty((size, size, size), np.float32)
    sx = np.sin(c)[None, :]
    sy = np.sin(2 * c)[:, None]
    cz = np.cos(c)
    for k in range(size):  # slab by slab: no 3-volume temporaries
        np.multiply(sy, cz[k], out=v[k])
        v[k] += sx
        v[k] *= np.float32(0.2)
        v[k] += np.float32(0.5)
    return normalise(v, value_range=(0.0, 1.0), count_candidates=False)


def bench_primitives(n: int, shape_xyz: tuple[int, int, int], sigma_spacing: float, seed: int) -> np.ndarray:
    """(n, 12) model parameters spread uniformly over the grid, anisotropic up to 2:1, rotated."""
    rng = np.random.default_rng(seed)
    shape = np.asarray(shape_xyz, np.float64)
    spacing = (float(np.prod(shape)) / n) ** (1.0 / 3.0)
    p = np.zeros((n, 12), np.float32)
    p[:, 0:3] = rng.uniform(0.0, 1.0, (n, 3)) * (shape - 1.0)
    p[:, 3:6] = math.log(sigma_spacing * spacing) + rng.uniform(-0.35, 0.35, (n, 3))
    q = rng.normal(size=(n, 4))
    p[:, 6:10] = q / np.linalg.norm(q, axis=1, keepdims=True)
    p[:, 10] = rng.uniform(0.1, 0.9, n)
    p[:, 11] = 0.5
    return p


class Timer:
    def __init__(self, device: str):
        self.wp = warp()
        self.device = device
        self.cuda = self.wp.get_device(device).is_cuda

    def ms(self, fn: Callable[[], None], repeat: int, warmup: int = 2) -> float:
        """Milliseconds per call of ``fn`` (GPU time on CUDA, wall time on the CPU)."""
        wp = self.wp
        for _ in range(warmup):
            fn()
        wp.synchronize_device(self.device)
        if self.cuda:
            stream = wp.get_stream(self.device)
            e0 = wp.Event(self.device, enable_timing=True)
            e1 = wp.Event(self.device, enable_timing=True)
            stream.record_event(e0)
            for _ in range(repeat):
                fn()
            stream.record_event(e1)
            return wp.get_event_elapsed_time(e0, e1) / repeat
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn()
        return 1000.0 * (time.perf_counter() - t0) / repeat

    def wall_ms(self, fn: Callable[[], None], repeat: int, warmup: int = 2) -> float:
        wp = self.wp
        for _ in range(warmup):
            fn()
        wp.synchronize_device(self.device)
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn()
        wp.synchronize_device(self.device)
        return 1000.0 * (time.perf_counter() - t0) / repeat

    def each_ms(self, fn: Callable[[], None], repeat: int) -> list[float]:
        """Wall milliseconds of each call, synchronised after every one (shows periodic work)."""
        wp, out = self.wp, []
        wp.synchronize_device(self.device)
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            wp.synchronize_device(self.device)
            out.append(1000.0 * (time.perf_counter() - t0))
        return out


STEADY_TRIES = 4  # timing windows tried for one without a graph capture
STEADY_ROUNDS = 3  # windows of each mode, the graph's and the plain launches' taken in turn


def _steady_step_ms(r, timer: Timer, repeat: int) -> tuple[float, int]:
    """Wall milliseconds per :meth:`~warpgauss.encoding.refine.Refiner.step` over ``repeat`` steps, re-bins
    included, in a window without a CUDA graph capture where one of :data:`STEADY_TRIES` has
    none (a capture, after a re-plan or new list arrays, costs tens of steps and happens a few
    times a run: timed in, it doubled the graph row of earlier benches); and the captures of the
    window timed."""
    wp = warp()
    ms, caught = float("nan"), 0
    for _ in range(STEADY_TRIES):
        r.step()  # warm: a capture the last window ended with happens here
        wp.synchronize_device(timer.device)
        c0, t0 = r.captures, time.perf_counter()
        for _ in range(repeat):
            r.step()
        wp.synchronize_device(timer.device)
        ms, caught = 1000.0 * (time.perf_counter() - t0) / repeat, r.captures - c0
        if caught == 0:
            break
    return ms, caught


def _iteration_rows(r, timer: Timer, repeat: int) -> dict[str, Any]:
    """The iteration's wall time with the refiner's CUDA graph and with plain launches, windows of
    the two taken in turn (:data:`STEADY_ROUNDS` each, the median kept): timed one mode after the
    other, the first mode's windows also held the steps that settle a fresh set of primitives
    and samples (re-lists, deferred steps), which read as a graph cost of 0.7 ms an iteration
    (20,000 x 65,536 on one H200) where real encodes measured the two modes 0-9 % apart
    (results/speed/profile_nograph_h200.json)."""
    graph: list[float] = []
    plain: list[float] = []
    caught = 0
    modes = [True, False] if r.use_graph else [False]
    for _ in range(STEADY_ROUNDS):
        for use in modes:
            r.use_graph = use
            ms, c = _steady_step_ms(r, timer, repeat)
            (graph if use else plain).append(ms)
            caught += c if use else 0
    r.use_graph = modes[0]
    out: dict[str, Any] = {"iteration_ms": float(np.median(graph if graph else plain)), "graph_captures_timed": caught}
    if graph:
        out["iteration_nograph_ms"] = float(np.median(plain))
        out["iteration_windows_ms"] = {"graph": graph, "plain": plain}
    return out


def _device_bytes(wp, device: str) -> int | None:
    if wp.get_device(device).is_cuda and wp.is_mempool_enabled(device):
        return int(wp.get_mempool_used_mem_current(device))
    return None


def run_kernel_bench(cfg: KernelBenchConfig, device: str | None = None, log: Callable[[str], None] = print) -> dict:
    """Run the microbenchmarks; returns the result dict (rows per N and per (N, M))."""
    from ..field.gaussians import GaussianField
    from ..kernels import backward as kb
    from ..kernels import field as kf
    from .refine import LossWeights, RefineConfig, Refiner

    wp = warp()
    dev = resolve_device(device)
    if cfg.size < 8 or not cfg.ns or not cfg.samples or min(cfg.ns) < 1 or min(cfg.samples) < 1:
        raise WarpgaussError("bench kernels needs --size >= 8 and positive --n and --samples lists")
    timer = Timer(dev)
    t0 = time.perf_counter()
    f = bench_field(cfg.size)
    dv = DeviceVolume(f, dev)
    field_seconds = time.perf_counter() - t0
    log(f"field {cfg.size}^3 made and uploaded in {field_seconds:.1f} s on {device_name(dev)}")
    per_n, rows = [], []
    for n in cfg.ns:
        params = bench_primitives(n, f.shape_xyz, cfg.sigma_spacing, cfg.seed)
        # samples and their smoothness partners (the term on, as encodes had it before issue #52
        # turned it off by default), so that rows compare with earlier rounds' pair rates
        rc = RefineConfig(iterations=10_000, samples=cfg.samples[0], weights=LossWeights(smooth=0.01))
        r = Refiner(dv, params, rc, cfg.seed, 0.3, max(2.0, cfg.size / 16))
        entry = {"n": n, "levels": len(r.plan.sizes), "cells": r.plan.total_cells}
        entry["bin_ms"] = timer.ms(r.rebin, cfg.repeat)
        entry["rebin_wall_ms"] = timer.wall_ms(r.rebin, cfg.repeat)
        entry["device_bytes_after_setup"] = _device_bytes(wp, dev)
        raw0 = r.raw_params()
        for m in cfg.samples:
            r.set_samples(m)
            r.set_raw(raw0)  # every sample count sees the same primitives
            row: dict[str, Any] = {"n": n, "samples": m}
            row["sample_ms"] = timer.ms(r.sample, cfg.repeat)
            row["forward_ms"] = timer.ms(r.forward, cfg.repeat)
            pairs = r.pairs.numpy().astype(np.float64)
            row["pairs_per_point"] = float(pairs.mean())
            row["point_sort_ms"] = timer.ms(lambda: r.passes.sort_points(2 * m), cfg.repeat)
            row["backward_ms"] = timer.ms(r.backward, cfg.repeat)
            stats = r.pair_pass_stats()
            row["backward_candidates_per_pair"] = stats["candidates"] / max(2 * m * row["pairs_per_point"], 1.0)
            row["backward_chunks"] = stats["chunks"]
            row["backward_chunk_size"] = stats["chunk_size"]
            row["point_cells"] = stats["point_cells"]
            if cfg.atomic_baseline:  # the point-major atomic scatter the primitive-major pass replaced
                row["backward_atomic_ms"] = timer.ms(lambda: r.passes.atomic_pairs(kb.accumulate_pairs, 2 * m), cfg.repeat)
                r.state.zero_grads()

            def backward_update() -> None:
                r.backward()
                r.update()

            both = timer.ms(backward_update, cfg.repeat)
            row["update_ms"] = max(both - row["backward_ms"], 0.0)
            r.state.zero_grads()
            fb = row["forward_ms"] + row["backward_ms"]
            row["gpairs_per_s"] = 2 * m * row["pairs_per_point"] / (fb * 1e-3) / 1e9 if fb > 0 else None
            row.update(_iteration_rows(r, timer, cfg.repeat))
            each = timer.each_ms(r.step, 2 * cfg.repeat)
            row["step_ms_median"] = float(np.median(each))
            row["step_ms_max"] = float(np.max(each))
            if cfg.dense_max_n and n <= cfg.dense_max_n and m == cfg.samples[0]:
                r.forward()  # the values of the current primitives at the last samples
                p = r.prims
                out = [wp.empty(2 * m, dtype=t, device=dev) for t in (float, float, int)]
                dense = lambda: wp.launch(  # noqa: E731
                    kf.eval_points_dense, dim=2 * m, inputs=[r.points, p.mu, p.conic, p.ext, p.a, p.w], outputs=out, device=dev
                )
                row["dense_forward_ms"] = timer.ms(dense, max(1, cfg.repeat // 5), warmup=1)
                row["dense_over_binned"] = row["dense_forward_ms"] / max(row["forward_ms"], 1e-9)
                np.testing.assert_array_equal(out[2].numpy(), r.pairs.numpy())  # same pairs
            rows.append(row)
            log(_format_row(row))
        if cfg.decode:
            entry.update(_decode_rows(GaussianField(r.model_params(), f.shape_xyz, device=dev), timer, cfg.size))
        entry["device_bytes_peak_so_far"] = (
            int(wp.get_mempool_used_mem_high(dev)) if wp.get_device(dev).is_cuda and wp.is_mempool_enabled(dev) else None
        )
        per_n.append(entry)
        log(
            f"N {n:>9,d}: bin {entry['bin_ms']:8.3f} ms, {entry['levels']} levels, "
            + (f"decode {cfg.size}^3 {entry['decode_ms'] / 1e3:7.3f} s" if cfg.decode else "")
        )
        del r
    return {
        "benchmark": "kernel microbenchmarks (warpgauss bench kernels)",
        "warpgauss_version": __version__,
        "commit": source_commit(Path(__file__).resolve().parent),
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "config": {**cfg.__dict__, "ns": list(cfg.ns), "samples": list(cfg.samples)},
        "field_seconds": field_seconds,
        "volume_bytes": int(f.values.nbytes),
        "per_n": per_n,
        "rows": rows,
        "notes": [
            "stage times: CUDA events around repeat back-to-back calls (GPU time incl. launch gaps); CPU: wall clock",
            "stages and their units (warpgauss/encoding/refine/): sample = schedule.begin + Sampler.draw (draw.py); forward, "
            "point_sort, backward = PairPasses (passes.py); update = Update (update.py); bin = Binner.rebin + support "
            "marks (bins.py, draw.py)",
            "forward = point order by cell + evaluation + per-point loss gradients; backward = point-grid sort + balanced "
            "chunk pass (backward_candidates_per_pair: candidate points visited per contributing pair; backward_atomic_ms: "
            "the point-major atomic scatter); "
            "update = fused chain rule + sparse Adam + re-preparation (measured as backward+update minus backward)",
            "iteration = wall clock per Refiner.step (median of windows with the graph and with plain launches taken in turn), re-bins every 10 iterations included, in a window without a graph "
            "capture (graph_captures_timed: those in the window kept, 0 unless every try had one)",
            "gpairs_per_s = contributing Gaussian-sample pairs (samples and partners) / (forward + backward time)",
            "points = the samples and their smoothness partners (LossWeights.smooth 0.01): the work earlier rounds measured; "
            "default encodes have the term off since issue #52 and evaluate the samples alone (half the points)",
        ],
    }


def _decode_on_device(gf, path: str = "lists") -> None:
    """Evaluate the whole model grid slab by slab into one device buffer (no host copy).

    ``path``: "lists" (what decode runs: per-brick primitive lists), "walk" (the binned cell walk in
    8^3 thread blocks with brick skip, the decode before brick lists), "rowmajor" (the cell walk
    over every voxel, one thread per voxel in row-major order).
    """
    wp = warp()
    from ..field.gaussians import DECODE_SLAB_VOXELS
    from ..kernels import field as kf

    nx, ny, nz = gf.shape_xyz
    slab = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
    buf = wp.empty((slab, ny, nx), dtype=float, device=gf.device)
    one = wp.vec3(1.0, 1.0, 1.0)
    for z0 in range(0, nz, slab):
        h = min(slab, nz - z0)
        view = buf if h == slab else wp.empty((h, ny, nx), dtype=float, device=gf.device)
        if path == "lists":
            gf.decode_slab(view, z0, one)
        elif path == "walk":
            gf.decode_walk(view, z0, one)
        else:
            wp.launch(kf.eval_grid_binned, dim=(h, ny, nx), inputs=[z0, one, gf.prims], outputs=[view], device=gf.device)


def _decode_rows(gf, timer, size: int) -> dict:
    """The decode's rows of a bench entry: the brick lists, the cell walk and the row-major kernel
    timed over the whole grid, whether the slab equals the row-major values, and (``decode_fit_slices``)
    the slab height whose lists fit MAX_BRICK_LIST where a slab had to be halved (None: none was)."""
    rows: dict = {"decode_ms": timer.ms(lambda: _decode_on_device(gf), 1, warmup=1)}
    rows["decode_fit_slices"] = min(gf._fit_height.values()) if gf._fit_height else None
    rows["decode_walk_ms"] = timer.ms(lambda: _decode_on_device(gf, "walk"), 1, warmup=1)
    rows["decode_rowmajor_ms"] = timer.ms(lambda: _decode_on_device(gf, "rowmajor"), 1, warmup=1)
    rows["decode_slab_equal_to_rowmajor"] = _decode_agrees(gf)
    rows["decode_voxels"] = size**3
    rows["decode_gvoxels_per_s"] = size**3 / (rows["decode_ms"] * 1e-3) / 1e9
    return rows


def _decode_agrees(gf) -> bool:
    """Whether the middle slab of a decode equals the row-major kernel's, bit for bit, clamped to
    [0, 1] as the decode clamps (a trained model may pass the source's range by a little)."""
    wp = warp()
    from ..field.gaussians import DECODE_SLAB_VOXELS
    from ..kernels import field as kf

    nx, ny, nz = gf.shape_xyz
    h = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
    z0 = max(0, nz // 2 - h // 2)
    h = min(h, nz - z0)
    one = wp.vec3(1.0, 1.0, 1.0)
    a = wp.empty((h, ny, nx), dtype=float, device=gf.device)
    b = wp.empty((h, ny, nx), dtype=float, device=gf.device)
    gf.decode_slab(a, z0, one)
    wp.launch(kf.eval_grid_binned, dim=(h, ny, nx), inputs=[z0, one, gf.prims], outputs=[b], device=gf.device)
    return bool(np.array_equal(a.numpy(), np.clip(b.numpy(), 0.0, 1.0)))


def _format_row(r: dict) -> str:
    s = (
        f"N {r['n']:>9,d} M {r['samples']:>9,d} | sample {r['sample_ms']:8.3f} fwd {r['forward_ms']:8.3f} "
        f"bwd {r['backward_ms']:8.3f}"
        + (f" (atomic {r['backward_atomic_ms']:8.3f})" if "backward_atomic_ms" in r else "")
        + f" upd {r['update_ms']:8.3f} | iter {r['iteration_ms']:8.3f}"
    )
    if "iteration_nograph_ms" in r:
        s += f" (no graph {r['iteration_nograph_ms']:8.3f})"
    s += f" ms, step median {r['step_ms_median']:.3f} max {r['step_ms_max']:.3f}"
    s += f" ms | {r['pairs_per_point']:7.1f} pairs/pt {r['gpairs_per_s'] or 0:7.2f} Gpairs/s"
    if "dense_forward_ms" in r:
        s += f" | dense fwd {r['dense_forward_ms']:9.3f} ms = {r['dense_over_binned']:6.1f}x"
    return s


def format_table(result: dict) -> str:
    """Markdown table of a result."""
    lines = [
        f"{result['device_name']}, Warp {result['warp_version']}, field {result['config']['size']}^3",
        "",
        "| N | samples | sample ms | forward ms | backward ms | atomic bwd ms | update ms | iteration ms | no-graph ms | pairs/point | G pairs/s | dense x |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['n']:,} | {r['samples']:,} | {r['sample_ms']:.3f} | {r['forward_ms']:.3f} | {r['backward_ms']:.3f} | "
            f"{r.get('backward_atomic_ms', float('nan')):.3f} | {r['update_ms']:.3f} | {r['iteration_ms']:.3f} | {r.get('iteration_nograph_ms', float('nan')):.3f} | "
            f"{r['pairs_per_point']:.1f} | {r['gpairs_per_s'] or 0:.2f} | {r.get('dense_over_binned', float('nan')):.1f} |"
        )
    lines += [
        "",
        "| N | levels | bin ms | decode s | cell-walk decode s | row-major decode s | Gvoxels/s |",
        "|---|---|---|---|---|---|---|",
    ]
    for e in result["per_n"]:
        lines.append(
            f"| {e['n']:,} | {e['levels']} | {e['bin_ms']:.3f} | {e.get('decode_ms', float('nan')) / 1e3:.3f} | "
            f"{e.get('decode_walk_ms', float('nan')) / 1e3:.3f} | {e.get('decode_rowmajor_ms', float('nan')) / 1e3:.3f} | "
            f"{e.get('decode_gvoxels_per_s', float('nan')):.3f} |"
        )
    return "\n".join(lines)
