"""Out-of-core encode (issue #20 part 3): a float32 raw volume larger than the device limit is
written slab by slab (by child processes, one z-range each), then encoded with ``--max-device-memory``: the bricking
is chosen from the limit, each brick reads its own box from the file. Reports the peak device
memory (Warp's pool high-water mark), this process's peak host RSS against the file's size, PSNR
on 500,000 sampled voxels, and the time of each stage.

    python benchmarks/bricked/out_of_core.py --size 2048 --budget 4000000 --max-device-memory 24GiB --dir /tmp --out $OUT/out_of_core_h100.json
    python benchmarks/bricked/out_of_core.py --size 2048 --gpus 2 --max-device-memory 24GiB --max-host-memory 16GiB --out $OUT/out_of_core2048_gpus2.json

With ``--gpus K`` the bricks run on a local Dask cluster of one worker process per GPU; the
report's ``workers`` gives each one's peak device memory (Warp's pool) and peak host RSS. With a
list (``--gpus 1,2``: issue #35 part 2 at sizes no in-memory array reaches) the same file is
encoded once per worker count, each on a cluster of that many GPU workers, in this run: rows with
``size``, ``gpus``, ``speedup`` against the first and whether the model equals the first's bit
for bit (this process's peak RSS is a lifetime peak: from the second row on it includes the
rows before).

    python benchmarks/bricked/out_of_core.py --size 2048 --gpus 1,2 --max-device-memory 24GiB --out $OUT/out_of_core2048_gpus12.json

With ``--volume-on-host`` the same file is encoded as one model with the volume in pinned host
memory (no bricks, no seams) under the same limits; ``--replicas 1,2`` encodes it once on one GPU
and once refined on two (``--devices cuda:0,cuda:1``, issue #55 part 3), rows with ``speedup``
against the first.

    python benchmarks/bricked/out_of_core.py --size 2048 --volume-on-host --max-device-memory 24GiB --out $OUT/out_of_core2048_host.json
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

GEN = r"""
import sys, numpy as np
path, n, start, stop = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
m = np.memmap(path, dtype=np.float32, mode="r+", shape=(n, n, n))
ax = (np.arange(n, dtype=np.float32) + 0.5) / n
y, x = np.meshgrid(ax, ax, indexing="ij")
for z0 in range(start, stop, 16):
    z = ax[z0 : z0 + 16, None, None]
    r2 = (x - 0.5) ** 2 + (y - 0.5) ** 2 + (z - 0.5) ** 2
    v = np.exp(-r2 / 0.08) + 0.3 * np.sin(6 * np.pi * x) * np.sin(4 * np.pi * y) * np.cos(5 * np.pi * z)
    v += 0.1 * np.sin(23 * np.pi * x + 9 * np.pi * z) * np.cos(17 * np.pi * y)
    m[z0 : z0 + 16] = v.astype(np.float32)
m.flush()
"""


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--budget", type=int, default=4_000_000)
    ap.add_argument("--max-device-memory", default="24GiB")
    ap.add_argument("--max-host-memory", default=None)
    ap.add_argument("--halo", type=int, default=None)
    ap.add_argument("--bricks", default=None, help="bricks per axis, e.g. 2x2x2 (default: chosen from the limits)")
    ap.add_argument("--iterations", type=int, default=None, help="refinement iterations (default: the encode's)")
    ap.add_argument("--dir", type=Path, default=Path("/tmp"))
    ap.add_argument(
        "--gpus",
        default="1",
        help="GPU workers (a local Dask cluster, one process per GPU) beyond 1; 1: this process; a comma list: one row per count, each on a cluster",
    )
    ap.add_argument("--error-share", type=float, default=None, help="share of the samples drawn where the error is (default: the encode's)")
    ap.add_argument(
        "--error-pool",
        action="store_true",
        help="draw.ERROR_POOL on: sparse error-map cells scored by blocks of them (this process only: --gpus 1)",
    )
    ap.add_argument(
        "--volume-on-host",
        action="store_true",
        help="one model, the volume in pinned host memory (issue #55 part 1) instead of bricks (this process only: --gpus 1)",
    )
    ap.add_argument(
        "--huge-pages",
        action="store_true",
        help="with --volume-on-host: the volume's host memory in transparent huge pages (field.slabs.HUGE_PAGES, this process)",
    )
    ap.add_argument(
        "--replicas",
        default="1",
        help="with --volume-on-host: GPUs of this machine refining the one model (--devices cuda:0,...); a comma list: one row per count",
    )
    ap.add_argument(
        "--kernels", action="store_true", help="time every kernel and copy by stage (CUDA activity, the graph off): the row's kernel_s"
    )
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    import warpgauss
    from warpgauss.core.warp import resolve_device
    from warpgauss.encoding.bench import result_header
    from warpgauss.readers.synthetic import generate

    dev = resolve_device(args.device)
    if args.error_pool:
        if str(args.gpus) != "1":
            raise SystemExit("--error-pool sets a module constant of this process: use it with --gpus 1")
        from warpgauss.encoding.refine import draw

        draw.ERROR_POOL = True
    if args.huge_pages:
        from warpgauss.field import slabs

        slabs.HUGE_PAGES = True
    if args.volume_on_host and (str(args.gpus) != "1" or args.bricks):
        raise SystemExit("--volume-on-host encodes one model in this process: use it with --gpus 1 and no --bricks")
    path = args.dir / f"ooc_{args.size}x{args.size}x{args.size}_float32.raw"
    t0 = time.perf_counter()
    if not path.exists() or path.stat().st_size != 4 * args.size**3:
        write_volume(path, args.size)
    gen_s = time.perf_counter() - t0
    print(f"wrote {path} ({path.stat().st_size / 2**30:.1f} GiB) in {gen_s:.1f} s", flush=True)
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64, format="full")  # compile
    counts = [int(g) for g in str(args.gpus).split(",")]
    replicas = [int(g) for g in str(args.replicas).split(",")]
    if replicas != [1] and not args.volume_on_host:
        raise SystemExit("--replicas refines one model: use it with --volume-on-host")
    if args.volume_on_host:
        counts = replicas
    for k in sorted(set(counts)) if args.volume_on_host else []:
        if k > 1:  # each device's kernels loaded before the clock
            warpgauss.encode(generate("vortex", 16), budget=50, devices=_devices(k, dev), iterations=2, samples=64, format="full")
    result = result_header("out-of-core bricked encode of a raw float32 volume under a device-memory limit", __file__, argv, dev)
    result["rows"] = []
    first = None
    for k in counts:
        client = None
        if not args.volume_on_host and (k > 1 or len(counts) > 1):
            from warpgauss.encoding.scale.cluster import gpu_client

            client = gpu_client(k)
            client.wait_for_workers(k, timeout=300)
            warpgauss.encode(
                generate("vortex", 48), budget=400, bricks="2x1x1", client=client, iterations=20, format="full", self_test=False
            )
        try:
            row, params = encode_once(args, path, dev, client, k, gen_s)
        finally:
            if client is not None:
                client.close()
                client.cluster.close()
        if first is None:
            first = (row["encode_s"], params)
        row["speedup"] = first[0] / row["encode_s"]
        row["identical_to_first"] = bool(np.array_equal(params, first[1]))
        result["rows"].append(row)
        args.out.write_text(json.dumps(result, indent=1))  # after every row: a run cut short keeps what it measured
        print({k_: v for k_, v in row.items() if k_ not in ("stages", "bricks", "waves")}, flush=True)
    args.out.write_text(json.dumps(result, indent=1))
    return result


class _KernelTimes:
    """Seconds and calls of each kernel, copy and set (CUDA activity) by the encode's stage: the
    timing restarts as each stage starts (``on_stage``), so every record lands in its stage."""

    FILTER = 0

    def __init__(self):
        import warp as wp

        self.wp, self.stage, self.per = wp, "before", {}
        self.FILTER = wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET
        wp.synchronize()
        wp.timing_begin(cuda_filter=self.FILTER)

    def _collect(self) -> None:
        from collections import defaultdict

        self.wp.synchronize()
        per = self.per.setdefault(self.stage, defaultdict(lambda: [0.0, 0]))
        for r in self.wp.timing_end():
            name = r.name.rsplit("_", 1)[0] if r.name.startswith("forward kernel") else r.name
            per[name][0] += r.elapsed / 1000.0
            per[name][1] += 1

    def on_stage(self, name: str, title: str) -> None:
        self._collect()
        self.stage = name
        self.wp.timing_begin(cuda_filter=self.FILTER)

    def finish(self) -> dict:
        """{stage: {name: [seconds, calls]}}, the largest first; the top of each printed."""
        self._collect()
        out = {}
        for stage, per in self.per.items():
            top = sorted(per.items(), key=lambda kv: -kv[1][0])
            out[stage] = {k: [round(v[0], 4), v[1]] for k, v in top}
            print(f"  {stage}: {sum(v[0] for v in per.values()):.3f} s in kernels and copies", flush=True)
            for k, v in top[:8]:
                print(f"    {v[0]:8.3f} s {v[1]:7d}x  {k}", flush=True)
        return out


def _devices(k: int, dev: str = "cuda:0") -> list[str]:
    """k devices: cuda:0 .. cuda:k-1 (the CPU k times, a test of the path)."""
    return [dev] * k if dev == "cpu" else [f"cuda:{i}" for i in range(k)]


def write_volume(path: Path, n: int) -> None:
    """The field written by child processes, one z-range each (one per core, at most 16; slabs of 16
    planes: the same values however many), into a file of its final size."""
    import os

    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as fh:
        fh.truncate(4 * n**3)
    k = max(1, min(16, os.cpu_count() or 1, -(-n // 16)))
    edges = [16 * (i * (-(-n // 16)) // k) for i in range(k)] + [n]
    procs = [subprocess.Popen([sys.executable, "-c", GEN, str(tmp), str(n), str(a), str(b)]) for a, b in zip(edges, edges[1:]) if a < b]
    if any([p.wait() != 0 for p in procs]):  # every child waited for, then any failure
        raise SystemExit("writing the volume failed")
    os.replace(tmp, path)


def encode_once(args, path, dev, client, gpus: int, gen_s: float):
    """One encode of the file (on ``client`` when given): its row and its parameters."""
    import warpgauss
    from warpgauss.encoding.refine import RefineConfig

    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    refine = {} if args.error_share is None else {"error_share": args.error_share}
    timing = None
    if args.kernels:
        refine["graph"] = False
        timing = _KernelTimes()
    t0 = time.perf_counter()
    done = []
    m = warpgauss.encode(
        str(path),
        budget=args.budget,
        refine=RefineConfig(**refine) if refine else None,
        device=dev,
        format="full",
        self_test=False,
        max_device_memory=args.max_device_memory,
        max_host_memory=args.max_host_memory,
        halo=args.halo,
        bricks=args.bricks,
        volume_on_host=bool(args.volume_on_host),  # else the bricked path (a model that fits would otherwise keep the volume on the host)
        iterations=args.iterations,
        client=client,
        devices=_devices(gpus, dev) if args.volume_on_host and gpus > 1 else None,
        on_stage=None if timing is None else timing.on_stage,
        on_bricks=lambda d, t: (done.append(d), print(f"brick {d}/{t} at {time.perf_counter() - t0:.1f} s", flush=True)),
    )
    wall = time.perf_counter() - t0
    kernels = None if timing is None else timing.finish()
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    r = m.report
    b = r.get("bricking") or {}
    row = {
        "path": "volume on host" if args.volume_on_host else "bricks",
        "size": args.size,
        "file_bytes": path.stat().st_size,
        "n": m.n,
        "max_device_memory": b.get("max_device_memory"),
        "max_host_memory": args.max_host_memory,
        "bricks_xyz": b.get("bricks_xyz"),
        "halo": b.get("halo"),
        "chosen": b.get("chosen"),
        "read_lazily": b.get("read_lazily"),
        "encode_s": wall,
        "psnr_db": r["psnr_db"],
        "psnr_on": r["evaluation"]["final"].get("on"),
        "peak_device_bytes": r.get("peak_device_bytes"),
        "peak_host_rss_bytes": rss,
        "host_rss_before_encode_bytes": rss0,
        "rss_over_file": rss / path.stat().st_size,
        "rss_growth_over_file": (rss - rss0) / path.stat().st_size,
        "gpus": gpus,
        "workers": b.get("workers"),
        "waves": b.get("waves"),
        "stages": [{k: s[k] for k in ("stage", "seconds", "device_peak_bytes", "host_peak_bytes") if k in s} for s in r.get("stages", [])],
        "bricks": [{k: x.get(k) for k in ("n", "seconds", "samples", "stand_ins", "frozen", "box_zyx")} for x in b.get("bricks", [])],
        "generate_s": gen_s,
        "error_share": args.error_share,
        "error_pool": bool(args.error_pool),
        "huge_pages": bool(args.huge_pages),
        "replicas": (r.get("refinement") or {}).get("replicas"),
        "s2_s": next((x["seconds"] for x in r.get("stages", []) if x["stage"] == "S2"), None),
        "kernel_s": kernels,
    }
    return row, m.params


if __name__ == "__main__":
    main()
