"""The split forward pass (one thread per point and neighbour cell) against the point-major one
(one thread per point), by samples per iteration (issues #32 and #35).

On CUDA the refiner splits the forward pass whenever the partial sums fit
(``RefineConfig.split_cells`` None; ``passes.PARTIAL_MAX_ENTRIES``), chosen when one thread per
sample left the GPU idle at the paper's 3,072 samples. Two measurements since point to the other
side: on an H200 the head MRIs encoded as fast at 65,536 samples (point-major, the partials do not
fit) as at 32,768 (split), 5.3-7.3 s against 6.0-7.0 s, while 16,384 took 2.5-4.5 s
(``results/accuracy/sweep_mri_samples_h200.json``), and a 2x2x2 brick's step at 20,089 samples
spent 2.2 of 2.9 ms in the split forward pass (``results/bricked/one_gpu_512_h200.json``). This
times both passes on the same Gaussians (allocated by the library on each volume) and samples.

For each volume, N and samples count, with ``split_cells`` True and False: a refiner stepped 20
times, then the median of the step time over ``--steps`` steps (re-bins included) and the
sample + forward time alone (CUDA events on a GPU, wall time on the CPU), and the primitives a
point visits (mean and max of the forward pass's pairs): the point-major pass's cost follows the
busiest point's visits, the split pass's all visits, so the crossover moves with them.

    python benchmarks/refine/forward_split.py --device cuda:0 --fields vortex:512,interface:512 \\
        --volumes benchmarks/build/rdvol/*.npz --budgets 20000,200000 \\
        --samples 8192,16384,32768,65536,131072 --out $OUT/forward_split_h200.json
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from warpgauss.core.profiling import StageRecorder
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.allocate import AllocationConfig, allocate
from warpgauss.encoding.bench import Timer, result_header
from warpgauss.encoding.refine import RefineConfig, Refiner, load_kernels
from warpgauss.field.analysis import DeviceVolume, normalise
from warpgauss.readers.synthetic import generate


def _volumes(args) -> list[tuple[str, object]]:
    out: list[tuple[str, object]] = [(Path(p).name.split(".")[0], lambda p=p: np.load(p)["data"]) for p in args.volumes]
    for spec in filter(None, args.fields.split(",")):
        name, size = spec.split(":")
        out.append((f"{name} {size}^3", lambda n=name, s=int(size): generate(n, s)))
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--volumes", nargs="*", default=[], help=".npz files with an array 'data' (benchmarks/build/rdvol)")
    ap.add_argument("--fields", default="vortex:64", help="example fields as name:size, comma separated")
    ap.add_argument("--budgets", default="2000", help="N, comma separated")
    ap.add_argument("--samples", default="1024,4096", help="samples per iteration, comma separated")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    load_kernels(dev)
    timer = Timer(dev)
    result = {**result_header("split against point-major forward pass, by samples per iteration", __file__, argv, dev), "rows": []}
    for label, load in _volumes(args):
        f = normalise(np.asarray(load(), np.float32))
        dv = DeviceVolume(f, dev)
        for n in (int(x) for x in args.budgets.split(",")):
            params, _ = allocate(dv, n, 0, AllocationConfig(), StageRecorder())
            cap = AllocationConfig().resolved_cap(f.shape_xyz)
            for m in (int(x) for x in args.samples.split(",")):
                row: dict = {"volume": label, "n": len(params), "samples": m}
                for split in (True, False):
                    r = Refiner(dv, params, RefineConfig(iterations=1500, samples=m, split_cells=split), 0, 0.3, cap)
                    for _ in range(20):
                        r.step()
                    warp().synchronize_device(dev)
                    t0 = time.perf_counter()
                    steps = [timer.ms(r.step, 1, warmup=0) for _ in range(args.steps)]
                    key = "split" if split else "point_major"
                    r.sample()
                    r.forward()
                    pairs = r.pairs.numpy()[: r.n_points].astype(np.float64)
                    row[key] = {
                        "partials_used": bool(r.passes.use_partials()),
                        "pairs_per_point": float(pairs.mean()),  # the primitives a point visits (same for both passes)
                        "pairs_per_point_max": int(pairs.max()),
                        "step_ms_median": float(np.median(steps)),
                        "forward_ms": timer.ms(lambda r=r: (r.sample(), r.forward()), 20),
                        "wall_s": time.perf_counter() - t0,
                    }
                    del r
                row["point_major_over_split_step"] = row["point_major"]["step_ms_median"] / row["split"]["step_ms_median"]
                result["rows"].append(row)
                print(
                    f"{label:28s} N {row['n']:8d} samples {m:7d}: step split {row['split']['step_ms_median']:7.2f} ms "
                    f"(partials {row['split']['partials_used']}, {row['split']['pairs_per_point']:.0f} pairs a point), point-major {row['point_major']['step_ms_median']:7.2f} ms; "
                    f"forward {row['split']['forward_ms']:7.2f} / {row['point_major']['forward_ms']:7.2f} ms",
                    flush=True,
                )
                args.out.parent.mkdir(parents=True, exist_ok=True)
                tmp = args.out.with_name(args.out.name + ".tmp")
                tmp.write_text(json.dumps(result, indent=1))
                os.replace(tmp, args.out)
    return result


if __name__ == "__main__":
    main()
