"""Multi-GPU scaling of the bricked encode and of a series (issue #23), against the same work on
one GPU of the same machine in the same run.

For each size: an example field generated here, encoded with the same bricking and seed on a local
Dask cluster of 1 GPU worker, then of 2 (``--gpus``), each worker a process with its own GPU
(``warpgauss.encoding.scale.cluster.gpu_client``: CUDA_VISIBLE_DEVICES per worker, Dask's own TCP transport).
Each row: gpus, seconds, speedup against gpus=1, PSNR, and whether the model equals the one-GPU
model bit for bit (same seed, same bricking: it must). The default rows run the encode's own
schedule (``rule`` in the row: the waves on a GPU cluster, then the seams refit on this process's
GPU where it holds the whole volume). ``--together 0.25`` adds each worker count
with every brick started at once (``warpgauss.encoding.scale.bricks.schedule``: no waves, stand-ins for every
neighbour) and the seams then refit together on this process's GPU for that share of the
iterations (0: none), rows with ``"schedule": "together"``. Then ``--series`` timesteps of an evolving
example encoded across the workers: timesteps per second against one GPU.

Every cluster first encodes a small field (kernels compiled in each worker, then cached on disk);
only the later encodes are timed. On the CPU (``--device cpu``) the workers are CPU processes
(``local_client``): the same encode paths, for a check on a machine without GPUs.

    python benchmarks/multi_gpu/multi_gpu.py --sizes 1024 --gpus 1,2 --series 8 --out $OUT/multi_gpu_1024.json
    python benchmarks/multi_gpu/multi_gpu.py --sizes 2048 --budget 4000000 --gpus 1,2 --series 0 --out $OUT/multi_gpu_2048.json
    python benchmarks/multi_gpu/multi_gpu.py --sizes 32 --budget 400 --bricks 2x2x1 --gpus 1,2 --series 4 --series-size 24 --device cpu --out /tmp/cpu.json
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

import numpy as np

import warpgauss
import warpgauss.encoding.scale.cluster
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.encoding.scale.cluster import gpu_client, local_client
from warpgauss.readers.synthetic import generate, generate_series
from warpgauss.series.steps import encode_series

os.environ.setdefault("NCCL_NVLS_ENABLE", "0")  # NVLink multicast stays off (nothing here uses NCCL; kept for any child)


logging.getLogger("distributed").setLevel(logging.WARNING)  # the workers' start and stop, line by line, otherwise


def cluster(k: int, device: str):
    client = gpu_client(k) if device.startswith("cuda") else local_client(k)
    client.wait_for_workers(k, timeout=300)
    return client


def _series(args, counts: list[int], clients: dict, common: dict, result: dict, save) -> None:
    """The series part: ``--series`` timesteps encoded across each cluster, timesteps per second
    against one GPU."""
    steps = list(generate_series(args.field, args.series_size, args.series))
    base_rate = None
    for k in counts:
        t0 = time.perf_counter()
        models = encode_series(steps, budget=args.series_budget, client=clients[k], **common)
        sec = time.perf_counter() - t0
        rate = len(steps) / sec
        base_rate = base_rate or rate
        result["rows"].append(
            {
                "what": "series",
                "size": args.series_size,
                "timesteps": len(steps),
                "n": int(models[0].n),
                "gpus": k,
                "seconds": sec,
                "timesteps_per_second": rate,
                "speedup": rate / base_rate,
                "psnr_db": [m.report["psnr_db"] for m in models],
                "warm": [bool(m.report["series"]["warm_start"]) for m in models],
                "encode_seconds": [m.report.get("total_seconds") for m in models],
            }
        )
        print(
            f"series of {len(steps)} at {args.series_size}^3 on {k} GPU(s): {sec:.1f} s, {rate:.3f} timesteps/s, "
            f"speed-up {rate / base_rate:.2f}x, PSNR {min(m.report['psnr_db'] for m in models):.2f}-"
            f"{max(m.report['psnr_db'] for m in models):.2f} dB",
            flush=True,
        )
        save()


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--sizes", default="1024", help='comma list of cube sizes ("": none, the series alone)')
    ap.add_argument("--budget", type=int, default=None, help="N (default: 1,000,000 at 1024^3, scaled with the voxel count)")
    ap.add_argument("--bricks", default="4x4x4")
    ap.add_argument("--gpus", default="1,2")
    ap.add_argument("--iterations", type=int, default=None, help="refinement iterations (default: the preset's)")
    ap.add_argument("--series", type=int, default=8, help="timesteps of the series part (0: none)")
    ap.add_argument("--series-size", type=int, default=512)
    ap.add_argument("--series-budget", type=int, default=400_000)
    ap.add_argument("--monolithic", action="store_true", help="also the monolithic encode on one GPU (this process), per size")
    ap.add_argument(
        "--graph-gpus",
        default="",
        help="also these worker counts with each wave's boxes sent through the Dask graph (the path before the volume was shared as a file)",
    )
    ap.add_argument("--together", default="", help="seam-refit shares for bricks started at once, comma list (0: no refit)")
    ap.add_argument("--no-waves", action="store_true", help="leave out the default schedule (the waves; with --together)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    return ap


def main(argv=None) -> dict:
    ap = _parser()
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    schedules = ([] if args.no_waves else [None]) + [float(x) for x in filter(None, args.together.split(","))]
    counts = [int(g) for g in args.gpus.split(",")]
    assert counts[0] == 1, "the first --gpus entry is the one-GPU baseline (1)"
    from warpgauss.field.analysis import MAX_VOXELS

    for size in (int(x) for x in args.sizes.split(",") if x.strip()):
        if size**3 > MAX_VOXELS:  # an in-memory array is refused past int32 voxel indices (the encode says --stride 2)
            ap.error(
                f"--sizes {size}: {size}^3 voxels exceed the {MAX_VOXELS:,} an in-memory volume may hold; encode it from a file "
                "instead: benchmarks/bricked/out_of_core.py --size SIZE --gpus 1,2"
            )
    extra = {} if args.iterations is None else {"iterations": args.iterations}
    common = dict(self_test=False, format="full", seed=0, device=dev, **extra)
    result = {
        **result_header("bricked encode and series across GPUs (Dask, one worker per GPU)", __file__, argv, dev),
        "field": args.field,
        "bricks": args.bricks,
        "environment": {k: os.environ.get(k) for k in ("CUDA_VISIBLE_DEVICES", "NCCL_NVLS_ENABLE")},
        "rows": [],
    }
    clients = {}

    def save() -> None:  # after every row: a run cut short keeps what it measured
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))

    try:
        for k in counts:
            t0 = time.perf_counter()
            clients[k] = cluster(k, dev)
            warm = warpgauss.encode(generate(args.field, 48), budget=400, bricks="2x1x1", client=clients[k], **{**common, "iterations": 20})
            print(
                f"cluster of {k}: up and compiled in {time.perf_counter() - t0:.1f} s ({warm.report['bricking']['scheduler']})", flush=True
            )
        for size in (int(s) for s in args.sizes.split(",") if s.strip()):  # --sizes "": the series alone
            budget = args.budget or int(1_000_000 * (size / 1024) ** 3)
            t0 = time.perf_counter()
            vol = generate(args.field, size)
            gen = time.perf_counter() - t0
            mono = None
            if args.monolithic:  # the whole field on one GPU in this process: what bricks on several GPUs must beat
                t0 = time.perf_counter()
                m = warpgauss.encode(vol, budget=budget, **common)
                sec = time.perf_counter() - t0
                result["rows"].append(
                    {"what": "monolithic encode", "size": size, "n": int(m.n), "gpus": 1, "seconds": sec, "psnr_db": m.report["psnr_db"]}
                )
                print(f"{size}^3 N {m.n:,} monolithic on one GPU: {sec:.1f} s, PSNR {m.report['psnr_db']:.2f} dB", flush=True)
                save()
                mono = sec
                del m
            graph = [(k, True, None) for k in counts if str(k) in args.graph_gpus.split(",")]
            runs = [(k, False, share) for share in schedules for k in counts] + graph
            bases: dict = {}
            for k, through_graph, share in runs:
                t0 = time.perf_counter()
                if through_graph:  # as before the volume was shared: every brick's box in the task graph
                    local = warpgauss.encoding.scale.cluster.is_local
                    warpgauss.encoding.scale.cluster.is_local = lambda client: False  # type: ignore[assignment]
                try:
                    # the default row: the encode's own rule (waves on a GPU cluster, then the seams
                    # refit on this process's GPU where it holds the whole volume)
                    with wsched.schedule(None if share is None else False, None if share is None else share):
                        m = warpgauss.encode(vol, budget=budget, bricks=args.bricks, client=clients[k], **common)
                finally:
                    if through_graph:
                        warpgauss.encoding.scale.cluster.is_local = local  # type: ignore[assignment]
                sec = time.perf_counter() - t0
                b = m.report["bricking"]
                devices = sorted({x["device"] for x in b["bricks"]})
                row = {
                    "what": "bricked encode" + (" (boxes through the graph)" if through_graph else ""),
                    "schedule": b["schedule"]["waves"],  # the rule's: a CPU cluster of idle workers takes "together"
                    "rule": b["schedule"],
                    "seam_refit": b.get("seam_refit"),
                    "volume_to_workers": b["volume_to_workers"],
                    "stages": [{"stage": x["stage"], "seconds": x["seconds"]} for x in m.report.get("stages", [])],
                    "waves": b["waves"],
                    "workers": b["workers"],
                    "brick_seconds": sum(x["seconds"] for x in b["bricks"]),
                    "size": size,
                    "n": int(m.n),
                    "gpus": k,
                    "seconds": sec,
                    "psnr_db": m.report["psnr_db"],
                    "worker_devices": devices,
                    "generate_seconds": gen,
                }
                base = bases.setdefault(share, (sec, m.params))  # the one-GPU row of the same schedule
                row["speedup"] = base[0] / sec
                row["identical_to_one_gpu"] = bool(np.array_equal(m.params, base[1]))
                if mono is not None:
                    row["over_monolithic_one_gpu"] = sec / mono
                result["rows"].append(row)
                save()
                print(
                    f"{size}^3 N {m.n:,} on {k} GPU(s), {row['schedule']}: {sec:.1f} s, speed-up {row['speedup']:.2f}x, PSNR {row['psnr_db']:.2f} dB, "
                    f"same model as one GPU: {row['identical_to_one_gpu']} ({row['volume_to_workers']}; waves {sum(w['seconds'] for w in b['waves']):.1f} s, "
                    f"of which on the workers {sum(w['worker_seconds'] for w in b['waves']):.1f} s; stages "
                    + ", ".join(f"{x['stage']} {x['seconds']:.1f}" for x in row["stages"])
                    + ")",
                    flush=True,
                )
            del vol, bases
        if args.series > 0:
            _series(args, counts, clients, common, result, save)
    finally:
        for c in clients.values():
            c.close()
            c.cluster.close()
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
