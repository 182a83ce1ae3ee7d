"""Seconds of a bounded encode's residual (issue #52 part 5): its interpolation passes on the
device against the numpy passes, the same run and the same bytes.

For each volume and bound: a default bounded encode (``warpgauss.encode(..., max_error_rel=B)``,
the Gaussians at its default ratio), its report's residual seconds; then the residual coded again
from the same prediction with the passes in numpy (``device=None``) and on the device, timed, and
their payloads compared; SZ3 (pysz, where installed) at the same absolute bound on the source as
float32, in the same run (the fastest of three), and the residual's seconds over SZ3's. Each
coding's breakdown (``seconds``: the axis choice, each predictor's passes and coding, the final
symbols) as the report gives it. Prints a table, writes JSON.

    python benchmarks/bounded/bounded_time.py --volumes /tmp/vol/mni_icbm152.npy --bounds 1e-2 --out results/bounded/time_h200.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header
from warpgauss.format import interpolation as I
from warpgauss.format import residual as R


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volumes", required=True, help="comma list of .npy volumes")
    ap.add_argument("--bounds", default="1e-2,1e-3")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    res = {**result_header("bounded residual seconds", __file__, argv, dev), "rows": []}
    print("| volume | bound | encode s | residual s (report) | numpy passes s | device passes s | same bytes | ratio | SZ3 s | SZ3 ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for path in args.volumes.split(","):
        src = np.load(path)
        for rel in (float(b) for b in args.bounds.split(",")):
            t0 = time.perf_counter()
            m = warpgauss.encode(src, max_error_rel=rel, device=dev)
            wall = time.perf_counter() - t0
            rep = m.run_report["residual"]
            pred, fragile = R.prediction(m, dev)
            lo, hi = m.value_range
            bound = float(rep["bound"])
            t1 = time.perf_counter()
            a, _ = R.code_residual(src, None, pred, fragile, bound, (lo, hi))
            t2 = time.perf_counter()
            b, _ = R.code_residual(src, None, pred, fragile, bound, (lo, hi), device=I.residual_device(dev, src.size))
            t3 = time.perf_counter()
            sz3 = sz3_seconds(src, bound)
            row = {
                "volume": Path(path).name,
                "bound_rel": rel,
                "encode_s": wall,
                "residual_code_s": rep["code_seconds"],
                "numpy_code_s": t2 - t1,
                "device_code_s": t3 - t2,
                "same_bytes": a.payload() == b.payload(),
                "compression_ratio": rep["compression_ratio"],
                "predictor": rep["predictor"],
                "report_seconds": rep.get("seconds"),
                "sz3_s": None if sz3 is None else sz3[0],
                "sz3_ratio": None if sz3 is None else src.nbytes / sz3[1],
                "residual_over_sz3": None if sz3 is None else rep["code_seconds"] / sz3[0],
            }
            res["rows"].append(row)
            print(
                f"| {row['volume']} | {rel:g} | {wall:.2f} | {row['residual_code_s']:.2f} | {row['numpy_code_s']:.2f} | "
                f"{row['device_code_s']:.2f} | {row['same_bytes']} | {row['compression_ratio']:.2f} | {row['sz3_s'] or 0:.3f} | {row['sz3_ratio'] or 0:.2f} |",
                flush=True,
            )
            print("   seconds:", json.dumps(row["report_seconds"]), flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


def sz3_seconds(src: np.ndarray, bound: float) -> tuple[float, int] | None:
    """SZ3 at the absolute ``bound`` on the source as float32: (the fastest of three encodes' seconds,
    bytes), or None where pysz is not installed."""
    try:
        from pysz import sz, szConfig, szErrorBoundMode
    except ImportError:
        return None
    data = np.ascontiguousarray(src, np.float32)
    conf = szConfig()
    conf.errorBoundMode = szErrorBoundMode.ABS
    conf.absErrorBound = float(bound)
    best, size = float("inf"), 0
    for _ in range(3):
        t0 = time.perf_counter()
        comp, _ = sz.compress(data, conf)
        best, size = min(best, time.perf_counter() - t0), int(comp.nbytes)
    return best, size


if __name__ == "__main__":
    main()
