"""What one refinement iteration costs after a default encode, piece by piece (issue #52, part 2).

For each volume and ratio: a default encode (after a warm-up that compiles every module), then,
on the refiner it trained (its state as the encode left it): the captured iteration replayed
(GPU time per replay, CUDA events; the host's wall per replay with a sync every step, which
includes the Python loop a real run pays), the same iteration as plain launches, one re-bin, one
loss record, and, where PyTorch is importable, every kernel a replay runs (CUB's sorts and scans
included, which Warp's own activity timing does not see) from PyTorch's profiler.

    python benchmarks/speed/iteration_floor.py --volumes mni_icbm152.npy --ratios 1000,100 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import Timer, result_header
from warpgauss.encoding.refine import Refiner
from warpgauss.readers.synthetic import generate

try:
    from profile_encode import _apply, _patches  # run as a script: benchmarks/speed is on the path
except ImportError:  # imported as a module
    from .profile_encode import _apply, _patches


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--volumes", default="vortex@32", help="paths or NAME@SIZE (a built-in example field), comma-separated")
    ap.add_argument("--ratios", default="1000,100")
    ap.add_argument("--device", default=None)
    ap.add_argument("--repeat", type=int, default=100)
    ap.add_argument("--variants", default="default", help="default and --patch names, comma-separated")
    ap.add_argument("--patch", action="append", default=[], help="as profile_encode.py's --patch")
    ap.add_argument(
        "--sweep",
        action="append",
        default=[],
        help="module.CONST:v1,v2,...: after each encode, every kernel of a plain iteration with the constant at each value (the same "
        "state); set:module.A=v;module.B=w: with several constants set at once; repeat for more",
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    warpgauss.encode(generate("vortex", 32), ratio=10, device=dev)
    patches = _patches(args.patch)
    res = {**result_header("one refinement iteration piece by piece", __file__, argv, dev), "rows": []}
    for vol in args.volumes.split(","):
        src = generate(vol.split("@")[0], int(vol.split("@")[1]), seed=0) if "@" in vol else vol
        for ratio, variant in ((float(r), x) for r in args.ratios.split(",") for x in args.variants.split(",")):
            saved = _apply(patches.get(variant, {}))
            refiner, wall = _encode(src, ratio, dev)
            row = {"volume": Path(vol).name, "ratio": ratio, "variant": variant, "encode_s": wall, **_pieces(refiner, dev, args.repeat)}
            _apply(saved)
            row["kernels_per_replay"] = _kernels(refiner, dev)
            row["kernels_per_rebin"] = _kernels(refiner, dev, 5, refiner.rebin)
            if args.sweep:
                row["sweep"] = {spec: _sweep(refiner, dev, spec) for spec in args.sweep}
            print(json.dumps({k: v for k, v in row.items() if not k.startswith("kernels_per")}))
            print("  rebin kernels us", round(sum(v[0] for v in row["kernels_per_rebin"].values()), 1))
            for name, (us, count) in list(row["kernels_per_rebin"].items())[:8]:
                print(f"    rebin {us:9.1f} us {count:6.2f}x  {name}")
            for name, (us, count) in list(row["kernels_per_replay"].items())[:30]:
                print(f"    {us:9.1f} us {count:6.2f}x  {name}")
            res["rows"].append(row)
            wp.synchronize_device(dev)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


def _encode(src, ratio: float, dev: str):
    """A default encode; the last refiner it stepped and the encode's wall seconds."""
    seen: list[Refiner] = []
    step = Refiner.step

    def spy(self):
        if not seen or seen[-1] is not self:
            seen.append(self)
        return step(self)

    Refiner.step = spy  # type: ignore[method-assign]
    try:
        warp().synchronize_device(dev)
        t = time.perf_counter()
        warpgauss.encode(src, ratio=ratio, device=dev)
        wall = time.perf_counter() - t
    finally:
        Refiner.step = step  # type: ignore[method-assign]
    return seen[-1], wall


def _pieces(r: Refiner, dev: str, repeat: int) -> dict:
    """GPU ms of a replay and of plain launches, host ms of a synced step, a re-bin and a loss record."""
    wp = warp()
    timer = Timer(dev)
    out = {"n": r.n, "m": r.m, "points": r.passes.n_points, "forward_pass": r.forward_pass, "levels": len(r.state.binned.sizes)}
    if r._graph is None and r.use_graph:
        r.step()
    if r._graph is not None:
        out["replay_gpu_ms"] = timer.ms(lambda: wp.capture_launch(r._graph), repeat)
        out["replay_wall_ms"] = timer.wall_ms(lambda: (wp.capture_launch(r._graph), wp.synchronize_device(dev)), repeat)
    out["plain_gpu_ms"] = timer.ms(r._iteration_launches, repeat)
    out["pair_pass"] = r.pair_pass_stats() | _chunk_tail(r)
    out["plain_wall_ms"] = timer.wall_ms(lambda: (r._iteration_launches(), wp.synchronize_device(dev)), repeat)
    out["rebin_wall_ms"] = timer.wall_ms(lambda: (r.rebin(), wp.synchronize_device(dev)), max(repeat // 5, 5))
    r._graph = None
    out["losses_wall_ms"] = timer.wall_ms(r.losses, max(repeat // 5, 5))
    return out


def settings_of(spec: str) -> dict[str, dict[str, float]]:
    """``module.CONST:v1,v2``: value -> {"module.CONST": value}; ``set:module.A=v;module.B=w``: the
    whole text -> {"module.A": v, "module.B": w} (several constants at once)."""
    key, _, values = spec.partition(":")
    if key == "set":
        return {values: {k: float(x) for k, _, x in (a.partition("=") for a in values.split(";"))}}
    return {v: {key: float(v)} for v in values.split(",")}


def _sweep(r: Refiner, dev: str, spec: str) -> dict:
    """Kernel microseconds of a plain iteration with one module constant at each of several values."""
    key = spec.partition(":")[0]
    out = {}
    for v, setting in settings_of(spec).items():
        saved = _apply(setting)
        r._graph = None
        per = _kernels(r, dev)
        _apply(saved)
        out[v] = {"total_us": round(sum(x[0] for x in per.values()), 1), "top": dict(list(per.items())[:4])}
        print(f"  {key}={v}: {out[v]['total_us']} us", {k[:30]: x[0] for k, x in out[v]["top"].items()})
    return out


def _chunk_tail(r: Refiner) -> dict:
    """The last backward pass's largest mean chunk (a primitive's candidates over its chunks: what
    one thread walks where its group's rows hold as many candidates as the others'), the largest
    chunk count and group count of one primitive, and the most candidates of one."""
    import numpy as np

    b = r.passes.buffers()
    work = b["work"].numpy().astype(np.int64)
    chunks = np.maximum(b["chunks"].numpy().astype(np.int64), 1)
    per = -(-work // chunks)
    return {
        "max_chunk": int(per.max(initial=0)),
        "max_chunks": int(chunks.max(initial=0)),
        "max_groups": int(b["groups"].numpy().max(initial=0)),
        "max_work": int(work.max(initial=0)),
    }


def _kernels(r: Refiner, dev: str, replays: int = 20, fn=None) -> dict:
    """Every kernel of a plain iteration (or of ``fn``), from PyTorch's profiler: name -> (us per
    call, launches per call)."""
    try:
        import torch
        from torch.profiler import ProfilerActivity, profile
    except ImportError:
        return {}
    if not torch.cuda.is_available() or not warp().get_device(dev).is_cuda:
        return {}
    wp = warp()
    wp.synchronize_device(dev)
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(replays):
            (fn or r._iteration_launches)()
        wp.synchronize_device(dev)
    per: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    for e in prof.events():
        if e.device_type.name == "CUDA":
            per[e.name[:90]][0] += float(getattr(e, "device_time", None) or getattr(e, "cuda_time", 0.0)) / replays
            per[e.name[:90]][1] += 1.0 / replays
    return {k: (round(v[0], 2), round(v[1], 2)) for k, v in sorted(per.items(), key=lambda kv: -kv[1][0])}


if __name__ == "__main__":
    main()
