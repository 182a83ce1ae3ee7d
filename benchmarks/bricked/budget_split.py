"""The budget split over the bricks (stage Sb of a bricked encode): every brick's statistics (occupied
and detail-eligible voxels, the sum of |grad V|, its seed limit) on this process's cores, then N
split over them. It runs on the host before any brick starts, whatever the GPUs, so it bounds what
more GPUs can gain (issue #35 part 2: 12-15 s of a 1024^3 encode on 32 cores). ``--device cuda:0``
also takes them on that device as the encode now does where the volume fits there (the volume put
there once, stage Su, then each brick's statistics from views of it): rows ``where`` "host" and
"device", the same counts required.

    python benchmarks/bricked/budget_split.py --size 512 --bricks 2x2x2,4x4x4 --out benchmarks/results/bricked/budget_split_512_cpu.json
    python benchmarks/bricked/budget_split.py --size 1024 --bricks 2x2x2,4x4x4 --budget 1000000 --device cuda:0 --out $OUT/budget_split_1024_h200.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

from warpgauss.encoding.bench import result_header, warmed_device
from warpgauss.encoding.scale.plan import default_halo, plan_bricks, split_bricks
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.readers.synthetic import generate


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--bricks", default="2x2x2,4x4x4")
    ap.add_argument("--budget", type=int, default=400_000)
    ap.add_argument("--halo", type=int, default=default_halo(4.0))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--device", default=None, help="also the statistics on this device (the volume put there once)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    result = {
        **result_header("budget split over the bricks (stage Sb), host cores and a device", __file__, argv, args.device or "cpu"),
        "cores": os.cpu_count(),
        "rows": [],
    }
    t0 = time.perf_counter()
    f = normalise(generate(args.field, args.size))
    print(f"{args.field} {args.size}^3 generated and analysed in {time.perf_counter() - t0:.1f} s")
    dv = None
    if args.device:
        from warpgauss.core.warp import warp

        warmed_device(args.device)
        t = time.perf_counter()
        dv = DeviceVolume(f, args.device)
        warp().synchronize_device(args.device)
        result["upload_seconds"] = time.perf_counter() - t
        print(f"the volume to {args.device} in {result['upload_seconds']:.2f} s")
    for spec in args.bricks.split(","):
        counts = tuple(int(x) for x in spec.split("x"))
        plan = plan_bricks(f.shape_xyz, counts, args.halo)
        host = None
        for where, on in [("host", None)] + ([("device", dv)] if dv is not None else []):
            times, split = [], None
            for _ in range(args.repeats):
                t = time.perf_counter()
                split, _ = split_bricks(f, plan, args.budget, dv=on)
                times.append(time.perf_counter() - t)
            host = split if host is None else host
            row = {
                "field": args.field,
                "size": args.size,
                "bricks": spec,
                "halo": args.halo,
                "where": where,
                "seconds": min(times),
                "all_seconds": times,
                "counts": split,
                "same_counts_as_host": split == host,
            }
            result["rows"].append(row)
            print(f"{spec} on the {where}: {min(times):.2f} s (best of {args.repeats}), {len(plan)} bricks, same counts: {split == host}")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
