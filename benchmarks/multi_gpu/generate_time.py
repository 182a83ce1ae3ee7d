"""Time to generate an example field at the sizes of issue #23 (1024^3, 2048^3), slabs on one
thread against slabs on threads (warpgauss.readers.synthetic.SLAB_THREADS), in one run; checks the two
fields are the same bit for bit where both are made.

    python benchmarks/multi_gpu/generate_time.py --field vortex --sizes 1024,2048 --serial 1024 --out $OUT/generate.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import warpgauss.readers.synthetic as sy
from warpgauss.encoding.bench import result_header


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--sizes", default="1024,2048")
    ap.add_argument("--serial", default="1024", help="sizes also made on one thread (the baseline)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = []
    threads = sy.SLAB_THREADS
    for size in (int(s) for s in args.sizes.split(",")):
        ref = None
        if str(size) in args.serial.split(","):
            sy.SLAB_THREADS = 1
            t0 = time.perf_counter()
            ref = sy.generate(args.field, size)
            rows.append({"size": size, "threads": 1, "seconds": time.perf_counter() - t0})
            print(f"{args.field} {size}^3 on 1 thread: {rows[-1]['seconds']:.1f} s", flush=True)
        sy.SLAB_THREADS = threads
        t0 = time.perf_counter()
        v = sy.generate(args.field, size)
        row = {"size": size, "threads": min(threads, os.cpu_count() or 1), "seconds": time.perf_counter() - t0}
        if ref is not None:
            row["identical_to_one_thread"] = bool(np.array_equal(v, ref))
            row["speedup"] = rows[-1]["seconds"] / row["seconds"]
        rows.append(row)
        print(f"{args.field} {size}^3 on {row['threads']} threads: {row['seconds']:.1f} s {row.get('speedup', '')}", flush=True)
        del v, ref
    result = {
        **result_header("example field generation time", __file__, argv, "cpu"),
        "cpu_count": os.cpu_count(),
        "field": args.field,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
