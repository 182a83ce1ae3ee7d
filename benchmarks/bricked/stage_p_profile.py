"""Where stage P's time goes with the volume in host memory (issue #55): the float32 raw file of
``out_of_core.py`` (written first when absent), then ``load_field(path, pinned=True)`` as the host
path runs it, with each part timed: the pinned buffers' allocation, the min/max scan, the fill
(normalised into the buffers), their registration page-locked where the driver takes it
(``registered``: one flag an array) and the seed-candidate count. Prints a table, writes JSON.

    python benchmarks/bricked/stage_p_profile.py --size 2048 --out $OUT/stage_p2048_h200.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--dir", type=Path, default=Path("/tmp"))
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    from out_of_core import write_volume

    from warpgauss.core.warp import resolve_device
    from warpgauss.encoding.bench import result_header
    from warpgauss.encoding.driver.load import load_field
    from warpgauss.field import analysis, slabs
    from warpgauss.field.limits import MAX_HOST_VOXELS

    path = args.dir / f"ooc_{args.size}x{args.size}x{args.size}_float32.raw"
    t0 = time.perf_counter()
    if not path.exists() or path.stat().st_size != 4 * args.size**3:
        write_volume(path, args.size)
    gen_s = time.perf_counter() - t0
    parts: dict[str, float] = {}

    def timed(name, fn):
        def run(*a, **k):
            t = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                parts[name] = parts.get(name, 0.0) + time.perf_counter() - t

        return run

    calls = {"map_slabs": 0}
    plain_map = analysis.map_slabs

    def map_slabs(fn, nz, slab=analysis.SLAB, threads=None):  # the first call is the scan, the second the fill
        calls["map_slabs"] += 1
        return timed(("scan", "fill", "count_slabs")[min(calls["map_slabs"], 3) - 1], plain_map)(
            fn, nz, slab, threads
        )  # count's within count

    analysis.map_slabs = map_slabs
    slabs.host_buffers = timed("pinned_alloc", slabs.host_buffers)
    registered: list[bool] = []
    plain_lock = slabs.page_locked

    def page_locked(arr, dtype):
        out = timed("register", plain_lock)(arr, dtype)
        registered.append(out is not None)
        return out

    slabs.page_locked = page_locked
    analysis.count_seed_candidates = timed("count", analysis.count_seed_candidates)
    dev = resolve_device(None)
    t0 = time.perf_counter()
    f, _ = load_field(str(path), max_voxels=MAX_HOST_VOXELS, pinned=True)
    total = time.perf_counter() - t0
    res = {**result_header("stage P with the volume in host memory", __file__, argv, dev)}
    res.update(
        size=args.size,
        generate_s=gen_s,
        stage_p_s=total,
        parts_s=parts,
        other_s=total - sum(parts.get(k, 0.0) for k in ("scan", "fill", "pinned_alloc", "count", "register")),
        occupied=int(f.occupied),
        registered=registered,
    )
    print("| part | s |\n|---|---|")
    for k, v in {**parts, "other (read, open)": res["other_s"], "total": total}.items():
        print(f"| {k} | {v:.2f} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
