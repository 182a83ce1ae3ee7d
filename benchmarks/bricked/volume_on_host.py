"""One model with the volume in host memory (issue #55 part 1): the same example field encoded in
core (the volume on the device) and with ``volume_on_host=True`` (the volume in pinned host memory,
read by the kernels over the bus, the model whole on the device); the bricked out-of-core path is
``out_of_core.py``'s (a file: an array in memory is never bricked by a limit). Same seed and settings; a table of
seconds (the whole ``warpgauss.encode`` after a warm-up), PSNR (every voxel with ``--full-eval``,
else 500,000 sampled), N, and whether the host-volume model equals the in-core one bit for bit.

    python benchmarks/bricked/volume_on_host.py --field vortex --size 1024 --ratio 100 --max-device-memory 8GiB \\
        --out $OUT/volume_on_host1024_h200.json --summary benchmarks/results/scale/round3.json

``--summary`` sets the issue's keys ``ooc1024_db``, ``incore1024_db`` and ``ooc1024_time_ratio``
(host volume against in core) in that JSON, the other keys kept.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--ratio", type=float, default=100.0)
    ap.add_argument("--iterations", type=int, default=None, help="refinement iterations (default: the encode's)")
    ap.add_argument("--max-device-memory", default=None, help="the host-volume run's device limit (the volume beyond it, the model within)")
    ap.add_argument("--full-eval", action="store_true", help="PSNR over every voxel")
    ap.add_argument("--device", default=None)
    ap.add_argument("--host-first", action="store_true", help="run the host-volume encode first (a run cut short still has its row)")
    ap.add_argument("--progress", action="store_true", help="a line as each stage of an encode starts")
    ap.add_argument(
        "--draw-ahead",
        choices=("default", "off", "on", "both"),
        default="default",
        help="the host-volume encode with each draw one iteration ahead (encoding.refine.draw.DRAW_AHEAD) off, on, or both rows",
    )
    ap.add_argument(
        "--draw-threads",
        default="default",
        help="comma-separated launch sizes of the host-volume draw (encoding.refine.draw.DRAW_THREADS_HOST; 0: one "
        "thread a sample): a host row for each, with each --draw-ahead setting",
    )
    ap.add_argument("--out", required=True)
    ap.add_argument("--summary", default=None, help="a JSON whose issue #55 keys this run sets")
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    wp = warp()
    warpgauss.encode(generate("vortex", 32), ratio=10, device=dev, iterations=20, progress=False)  # compile outside the clock
    vol = generate(args.field, args.size, seed=0)
    kw: dict = dict(ratio=args.ratio, device=dev, full_eval=args.full_eval, seed=0, progress=False)
    if args.progress:
        t0 = time.perf_counter()
        kw["on_stage"] = lambda name, title: print(f"  {time.perf_counter() - t0:8.1f} s  {name}: {title}", flush=True)
    if args.iterations is not None:
        kw["iterations"] = args.iterations
    from warpgauss.encoding.refine import draw

    host_kw = {"volume_on_host": True, "max_device_memory": args.max_device_memory}
    ahead = {"default": [None], "off": [False], "on": [True], "both": [False, True]}[args.draw_ahead]
    threads = [None if t == "default" else int(t) for t in args.draw_threads.split(",")]
    hosts = [
        (
            "volume on host" + ("" if a is None else f", draw ahead {'on' if a else 'off'}") + ("" if t is None else f", draw threads {t}"),
            (a, t),
        )
        for a in ahead
        for t in threads
    ]
    runs = [("in core", (None, None)), *hosts]
    if args.host_first:
        runs = [*hosts, ("in core", (None, None))]
    res = {**result_header("one model with the volume in host memory", __file__, argv, dev), "rows": []}
    models = {}
    print(f"{'path':24s} {'s':>8s} {'PSNR':>8s} {'N':>10s}")
    default_ahead, default_threads = draw.DRAW_AHEAD, draw.DRAW_THREADS_HOST
    for name, (a, t) in runs:
        draw.DRAW_AHEAD = default_ahead if a is None else a
        draw.DRAW_THREADS_HOST = default_threads if t is None else t
        try:
            wp.synchronize()
            t = time.perf_counter()
            m = warpgauss.encode(vol, **kw, **({} if name == "in core" else host_kw))
            wall = time.perf_counter() - t
        finally:
            draw.DRAW_AHEAD, draw.DRAW_THREADS_HOST = default_ahead, default_threads
        models[name] = np.asarray(m.params)
        rep = m.report
        row = {
            "path": name,
            "seconds": wall,
            "psnr_db": rep["evaluation"]["final"]["psnr_db"],
            "n": m.n,
            "stages": {s["stage"]: round(s["seconds"], 3) for s in rep["stages"]},
            "peak_device_bytes": rep.get("peak_device_bytes"),
            "volume_memory": rep.get("volume_memory"),
            "bricks_xyz": (rep.get("bricking") or {}).get("bricks_xyz"),
            "ms_per_iteration": (rep.get("refinement") or {}).get("ms_per_iteration"),
        }
        res["rows"].append(row)
        print(f"{name:24s} {wall:8.2f} {row['psnr_db']:8.2f} {m.n:10d}  {row['stages']}", flush=True)
        Path(args.out).write_text(json.dumps(res, indent=1) + "\n")  # each row as it comes (a long run may be cut)
    base = next(r for r in res["rows"] if r["path"] == "in core")
    for r in res["rows"]:
        if r["path"] != "in core":
            r["equals_in_core"] = bool(np.array_equal(models["in core"], models[r["path"]]))
            r["time_ratio"] = r["seconds"] / base["seconds"]
            print(f"{r['path']} / in core: {r['time_ratio']:.2f}x, the same model: {r['equals_in_core']}")
    host = [r for r in res["rows"] if r["path"] != "in core"][-1]  # the summary's: the last host row
    res["host_equals_in_core"] = host["equals_in_core"]
    res["host_time_ratio"] = host["time_ratio"]
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    if args.summary:
        _summary(args, host, base)
    return res


def _summary(args, host: dict, base: dict) -> None:
    """The issue's ooc1024 keys, from the last host row against the in-core row."""
    p = Path(args.summary)
    summary = json.loads(p.read_text()) if p.is_file() else {}
    summary.update(
        ooc1024_db=host["psnr_db"],
        incore1024_db=base["psnr_db"],
        ooc1024_time_ratio=host["time_ratio"],
        ooc1024_source=f"{Path(args.out).name}: --volume-on-host ({host['path']}) against in core, {args.field} {args.size}^3, ratio {args.ratio:g}",
    )
    p.write_text(json.dumps(summary, indent=1) + "\n")


if __name__ == "__main__":
    main()
