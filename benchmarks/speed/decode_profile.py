"""Where a decode's time goes (issue #52's decode_1024_s): the whole grid evaluated slab by slab
into one device buffer, as ``warpgauss bench kernels`` times it, for the bench's model at each N
and each slab size (``field.gaussians.DECODE_SLAB_VOXELS``): the wall time (median of --repeat),
the GPU time of each kernel under Warp's activity timing, and the brick lists' entries.

    python benchmarks/speed/decode_profile.py --size 1024 --n 20000,1400000 --slab-voxels 16777216,134217728 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding import bench
from warpgauss.encoding.bench import result_header
from warpgauss.field import gaussians
from warpgauss.field.gaussians import GaussianField


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--n", default="20000,1400000", help="comma-separated primitive counts")
    ap.add_argument("--slab-voxels", default=str(gaussians.DECODE_SLAB_VOXELS), help="comma-separated output voxels a slab")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    shape = (args.size,) * 3
    res = {**result_header("decode by kernel and slab size", __file__, argv, dev), "rows": []}
    default_slab = gaussians.DECODE_SLAB_VOXELS
    for n in (int(x) for x in args.n.split(",")):
        gf = GaussianField(bench.bench_primitives(n, shape, 0.7, 0), shape, device=dev)
        for slab in (int(x) for x in args.slab_voxels.split(",")):
            gaussians.DECODE_SLAB_VOXELS = slab
            try:
                row = _profile(wp, gf, n, slab, args.repeat)
            finally:
                gaussians.DECODE_SLAB_VOXELS = default_slab
            res["rows"].append(row)
            top = ", ".join(f"{k} {v[0] * 1e3:.1f} ms x{v[1]}" for k, v in list(row["kernel_s"].items())[:5])
            print(f"N {n:>9,} slab {slab:>11,}: {row['wall_ms']:8.1f} ms wall, kernels {row['kernel_ms']:8.1f} ms; {top}", flush=True)
            Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    return res


def _profile(wp, gf, n: int, slab: int, repeat: int) -> dict:
    entries: list[int] = []
    plain = gf._decode_lists

    def counted(out, z0, scale, offset, common, ends, counts, nb, bricks, total):
        entries.append(total)
        plain(out, z0, scale, offset, common, ends, counts, nb, bricks, total)

    bench._decode_on_device(gf)  # compile and warm up
    walls = []
    for _ in range(repeat):
        wp.synchronize()
        t = time.perf_counter()
        bench._decode_on_device(gf)
        wp.synchronize()
        walls.append(time.perf_counter() - t)
    gf._decode_lists = counted
    try:
        wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
        bench._decode_on_device(gf)
        records = wp.timing_end()
    finally:
        del gf._decode_lists
    per = defaultdict(lambda: [0.0, 0])
    for r in records:
        name = r.name.rsplit("_", 1)[0] if r.name.startswith("forward kernel") else r.name
        per[name][0] += r.elapsed / 1000.0
        per[name][1] += 1
    top = dict(sorted(per.items(), key=lambda kv: -kv[1][0]))
    return {
        "n": n,
        "slab_voxels": slab,
        "wall_ms": float(np.median(walls)) * 1e3,
        "walls_ms": [w * 1e3 for w in walls],
        "kernel_ms": sum(v[0] for v in per.values()) * 1e3,
        "kernel_s": {k: [round(v[0], 6), v[1]] for k, v in top.items()},
        "slabs": len(entries),
        "list_entries": int(sum(entries)),
        "list_entries_max_slab": int(max(entries, default=0)),
    }


if __name__ == "__main__":
    main()
