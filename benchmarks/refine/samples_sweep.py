"""Samples and iterations against accuracy and time at a fixed byte budget (issue #18 part 3).

For each volume and each (iterations, samples) pair: ``warpgauss.encode(volume, ratio=R,
iterations=I, samples=S)`` with the default (coded) format, full-grid PSNR of the stored model,
the refinement seconds (stage S2) and the encode's wall seconds (kernels compiled beforehand).
The JSON is rewritten after every row.

    python benchmarks/refine/samples_sweep.py --device cuda:0 --volumes /tmp/vol/*.npz \\
        --fields vortex:512,interface:512 --ratios 100 --grid 1500x3072,1500x32768 --out $OUT/sweep.json

Volumes: ``.npz`` files holding one array ``v`` (the real MRIs, saved from ``../shared/data`` with
numpy because the GPU host has no pyvista: ``benchmarks/rate_distortion/bench_rd.py --volume-dir`` writes them; the source dtype is kept, so ratios are the same) and
example fields ``name:size`` generated on the device.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate


def _write(result: dict, out: Path) -> None:
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=1))
    os.replace(tmp, out)


def _pairs(text: str) -> list[tuple[int, int | None]]:
    """'1500x3072,3000x32768,1500x-' -> [(1500, 3072), (3000, 32768), (1500, None)] (None: the default rule)."""
    out = []
    for item in text.split(","):
        it, s = item.split("x")
        out.append((int(it) if it != "-" else None, int(s) if s != "-" else None))
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--volumes", nargs="*", default=[], help=".npz files with one array 'v'")
    ap.add_argument("--fields", default="", help="example fields as name:size, comma separated")
    ap.add_argument("--ratios", default="100", help="compression ratios (comma list)")
    ap.add_argument("--grid", default="1500x3072", help="iterations x samples pairs; '-' keeps the default")
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64)
    result = {
        **result_header("samples x iterations at a fixed ratio, default (coded) format, full-grid PSNR", __file__, argv, dev),
        "warmup_seconds": time.perf_counter() - t0,
        "rows": [],
    }
    sources = [(Path(p).stem, lambda p=p: np.load(p)["v"]) for p in args.volumes]
    for spec in filter(None, args.fields.split(",")):
        name, size = spec.split(":")
        sources.append((f"{name}{size}", lambda n=name, s=int(size): generate(n, s)))
    ratios = [float(r) for r in args.ratios.split(",")]
    for label, make in sources:
        t0 = time.perf_counter()
        vol = make()
        gen_s = time.perf_counter() - t0
        for ratio in ratios:
            for its, samples in _pairs(args.grid):
                t0 = time.perf_counter()
                model = warpgauss.encode(vol, ratio=ratio, device=dev, iterations=its, samples=samples, full_eval=True, self_test=False)
                wall = time.perf_counter() - t0
                r = model.report
                stages = {s["stage"]: s["seconds"] for s in r["stages"]}
                ref = r.get("refinement", {})
                row = {
                    "volume": label,
                    "voxels": int(np.prod(vol.shape)),
                    "ratio_target": ratio,
                    "ratio": float(model.compression_ratio),
                    "bytes": r["budget"]["bytes"],
                    "budget_used": r["budget"]["budget_used"],
                    "coded_fit": r["budget"]["coded_fit"],
                    "n": model.n,
                    "iterations": ref.get("iterations_done"),
                    "samples": ref.get("samples"),
                    "samples_rule": ref.get("samples_rule"),
                    "psnr_db": r["evaluation"]["final"]["psnr_db"],
                    "analytic_psnr_db": r["evaluation"]["analytic"]["psnr_db"],
                    "refine_s": stages.get("S2"),
                    "encode_wall_s": wall,
                    "eval_s": stages.get("EV"),
                    "generate_s": gen_s,
                    "stages": stages,
                }
                result["rows"].append(row)
                print(
                    f"{label} CR {ratio:g} N {model.n} {row['iterations']} x {row['samples']}: {row['psnr_db']:.2f} dB, "
                    f"S2 {row['refine_s']:.2f} s, wall {wall:.2f} s",
                    flush=True,
                )
                _write(result, args.out)
                del model
        del vol
    return result


if __name__ == "__main__":
    main()
