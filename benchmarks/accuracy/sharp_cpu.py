"""What the paper's jittered samples do for sharp edges (issue #32 part 2), on the CPU: float32
models of a fixed N trained with each sampling variant, full-grid PSNR (and on occupied voxels,
and how many decoded voxels the clamp moved), on sharp-edged volumes: the bubbles example
(2-3 % occupied, step edges), mni_icbm152 (a skull-stripped brain, 78 % zeros) and the frog
tissue label map (categorical, the sharpest), strided down to CPU sizes.

    python benchmarks/accuracy/sharp_cpu.py --out benchmarks/results/accuracy/sharp_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "rate_distortion"))

import bench_rd  # noqa: E402

import warpgauss  # noqa: E402
from warpgauss.encoding.bench import result_header  # noqa: E402
from warpgauss.encoding.refine import RefineConfig  # noqa: E402
from warpgauss.field.analysis import normalise  # noqa: E402
from warpgauss.readers import read_volume  # noqa: E402
from warpgauss.readers.synthetic import generate  # noqa: E402

VARIANTS = {
    "paper": {"jitter": 0.5, "importance": False},
    "centres": {"jitter": 0.0, "importance": False},
    "default": {},
    "jitter-iw": {"jitter": 0.5, "importance": True},
    "quarter-iw": {"jitter": 0.25, "importance": True},
}


def volumes(stride: int, size: int):
    yield f"bubbles {size}^3", generate("bubbles", size, seed=0)
    for name in ("mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz", "frog_tissues.vti"):
        path = bench_rd.DATA_DIR / name
        if path.is_file():
            v = read_volume(path).data[::stride, ::stride, ::stride]
            yield f"{name.split('_t1')[0].split('.')[0]} /{stride}", v


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--stride", type=int, default=4)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--voxels-per-gaussian", type=float, default=40.0, help="N = voxels / this")
    ap.add_argument("--iterations", type=int, default=600)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--out", default="benchmarks/results/accuracy/sharp_cpu.json")
    args = ap.parse_args(argv)
    result = {**result_header("sampling variants on sharp-edged volumes, float32, fixed N (issue #32)", __file__, argv, "cpu")}
    rows = result["rows"] = []
    for label, vol in volumes(args.stride, args.size):
        n = max(50, int(vol.size / args.voxels_per_gaussian))
        f = normalise(vol)
        for v in args.variants.split(","):
            cfg = dataclasses.replace(RefineConfig(iterations=args.iterations), **VARIANTS[v])
            t0 = time.perf_counter()
            m = warpgauss.encode(vol, budget=n, refine=cfg, format="full", device="cpu", seed=0, self_test=False, full_eval=True)
            ev = m.report["evaluation"]["final"]
            hist = m.report["refinement"]["loss_history"]
            row = {
                "volume": label,
                "shape_zyx": list(vol.shape),
                "zeros_share": float((f.values <= 0.02).mean()),
                "n": n,
                "variant": v,
                "psnr_db": ev["psnr_db"],
                "psnr_occupied_db": ev["psnr_occupied_db"],
                "clamped_voxels": ev.get("clamped_voxels"),
                "sample_psnr_db": hist[-1]["sample_psnr_db"] if hist else None,
                "seconds": time.perf_counter() - t0,
            }
            rows.append(row)
            print(
                f"{label:22s} N {n:6d} {v:10s} full {row['psnr_db']:6.2f} occupied {row['psnr_occupied_db']:6.2f} "
                f"sample {row['sample_psnr_db']:6.2f} clamped {row['clamped_voxels']} {row['seconds']:5.1f} s",
                flush=True,
            )
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
