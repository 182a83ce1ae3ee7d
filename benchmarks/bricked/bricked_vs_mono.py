"""Bricked (2x2x2, in one process on one GPU) against the monolithic encode at the same N and
settings (issue #20 target: PSNR within 0.2 dB, time within 1.3x), full-grid PSNR, and the PSNR
on voxels within 2 voxels of an inner brick face against the rest.

``--from-file`` encodes the field written as a raw float32 file, as ``warpgauss encode FILE`` does
(the path a file takes: read whole or brick by brick, see docs/guide/large.md); ``--workers K``
runs the bricks on a local Dask cluster of K CPU processes (``--workers`` of the command line);
``--repeat R`` times each encode R times (the summary takes the fastest: other processes share
the machine); ``--summary PATH`` writes issue #55's CPU keys (cpu48_*) from the first field.

    python benchmarks/bricked/bricked_vs_mono.py --size 512 --budget 400000 --fields vortex,interface --out $OUT/bricked_h100.json
    python benchmarks/bricked/bricked_vs_mono.py --device cpu --size 48 --budget 3000 --iterations 200 --seed 3 --fields bubbles \\
        --format coded --from-file --workers 2 --repeat 2 --out benchmarks/results/scale/cpu48.json --summary benchmarks/results/scale/round3.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import device_name, resolve_device, warp
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.scale.plan import face_band, parse_bricks, plan_bricks
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def psnr(sse: float, n: int) -> float:
    return float(10 * np.log10(n / max(sse, 1e-30)))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=400_000)
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--bricks", default="2x2x2")
    ap.add_argument("--halo", default="default", help="halos to try, comma separated (voxels; default: the bricked encode's rule)")
    ap.add_argument("--caps", default="none", help="sigma caps (voxels) to try, comma separated; none: the default")
    ap.add_argument("--device", default=None)
    ap.add_argument("--iterations", type=int, default=None, help="refinement iterations (default: the encode's)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--format", default="full", help="the model's format (full, coded, compact)")
    ap.add_argument("--from-file", action="store_true", help="encode the field written as a raw float32 file")
    ap.add_argument("--workers", type=int, default=0, help="a local Dask cluster of K CPU processes for the bricks (0: this process)")
    ap.add_argument("--repeat", type=int, default=1, help="encodes of each kind (the summary takes the fastest)")
    ap.add_argument("--summary", type=Path, default=None, help="write issue #55's cpu48_* summary there")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64, format="full")  # compile
    result = {
        "benchmark": "bricked vs monolithic encode, same N and settings (defaults otherwise)",
        "command": "python benchmarks/bricked/bricked_vs_mono.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "settings": {k: str(v) for k, v in vars(args).items()},
        "rows": [],
    }
    client = None
    if args.workers > 0:
        from warpgauss.encoding.scale.cluster import local_client

        client = local_client(args.workers)
    try:
        for name in filter(None, args.fields.split(",")):
            _field_rows(args, name, dev, client, result)
    finally:
        if client is not None:
            client.close()
            client.cluster.close()
    if args.summary is not None:
        _summary(result, args.summary)
    return result


def _field_rows(args, name: str, dev: str, client, result: dict) -> None:
    """Every run of one field: the monolithic encode and the bricked ones, ``--repeat`` times each."""
    import tempfile

    v = generate(name, args.size)
    f = normalise(v)
    counts = parse_bricks(args.bricks)
    near = face_band(f.shape_xyz, plan_bricks(f.shape_xyz, counts, 0))
    folder = tempfile.TemporaryDirectory()
    source = v
    if args.from_file:  # as the command line reads it: a file in a format read on demand
        source = str(Path(folder.name) / f"{name}_{v.shape[2]}x{v.shape[1]}x{v.shape[0]}_float32.raw")
        v.astype(np.float32).tofile(source)
    runs = [("monolithic", None)] + [("bricked", None if h == "default" else int(h)) for h in args.halo.split(",")]
    for _ in range(args.repeat):
        for cap, (mode, halo) in [(c, r) for c in args.caps.split(",") for r in runs]:
            kw = dict(budget=args.budget, device=dev, format=args.format, self_test=False, evaluate=False, seed=args.seed, progress=False)
            if args.iterations is not None:
                kw["iterations"] = args.iterations
            if cap != "none":
                kw["allocation"] = AllocationConfig(scale_cap=float(cap))
            if mode == "bricked":
                kw.update(bricks=args.bricks, halo=halo, client=client)
            t0 = time.perf_counter()
            m = warpgauss.encode(source, **kw)
            wall = time.perf_counter() - t0
            d = m.decode(device=dev, normalised=True)
            err = (d.astype(np.float64) - f.values) ** 2
            row = {
                "field": name,
                "size": args.size,
                "mode": mode,
                "halo": halo,
                "scale_cap": None if cap == "none" else float(cap),
                "n": m.n,
                "encode_s": wall,
                "psnr_db": psnr(float(err.sum()), err.size),
                "seam_psnr_db": psnr(float(err[near].sum()), int(near.sum())),
                "interior_psnr_db": psnr(float(err[~near].sum()), int((~near).sum())),
                "samples": m.report["refinement"].get("samples") if mode == "monolithic" else None,
            }
            if mode == "bricked":
                b = m.report["bricking"]
                row.update(halo=b["halo"], brick_scale_cap=b["scale_cap"], read_lazily=b.get("read_lazily"), workers=args.workers)
                row.update(schedule=b["schedule"], seam_refit=b["seam_refit"], bricks_wall_s=b["wall_seconds"])
                row["bricks"] = [{k: x.get(k) for k in ("n", "seconds", "samples", "stand_ins", "frozen", "worker")} for x in b["bricks"]]
            result["rows"].append(row)
            print({k: v_ for k, v_ in row.items() if k not in ("bricks", "seam_refit")}, flush=True)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(json.dumps(result, indent=1))
            del d, err, m
    folder.cleanup()


def _summary(result: dict, path: Path) -> None:
    """Issue #55's summary from the first field's rows: the bricked and monolithic PSNR (of the
    fastest run of each, every run of a kind gives the same model) and their time ratio."""
    from warpgauss.encoding.bench import source_commit

    rows = [r for r in result["rows"] if r["field"] == result["rows"][0]["field"]]
    best = {mode: min((r for r in rows if r["mode"] == mode), key=lambda r: r["encode_s"]) for mode in ("monolithic", "bricked")}
    out = {
        "cpu48_bricked_db": best["bricked"]["psnr_db"],
        "cpu48_mono_db": best["monolithic"]["psnr_db"],
        "cpu48_time_ratio": best["bricked"]["encode_s"] / best["monolithic"]["encode_s"],
        "cpu48_bricked_s": best["bricked"]["encode_s"],
        "cpu48_mono_s": best["monolithic"]["encode_s"],
        "ooc1024_db": None,
        "incore1024_db": None,
        "ooc1024_time_ratio": None,
        "ooc2048_s": None,
        "ooc2048_db": None,
        "ooc2048_two_gpu_speedup": None,
        "dask1024_db": None,
        "mono1024_db": None,
        "commit": source_commit(Path(__file__).resolve().parent),
        "command": result["command"],
        "device": result["device"],
        "warp_version": result["warp_version"],
        "date": result["date"],
        "schedule": best["bricked"].get("schedule"),
        "notes": "CPU keys only: the GPU keys (ooc1024_*, incore1024_db, ooc2048_*, dask1024_db, mono1024_db) are not measured here (null); "
        "seconds are warpgauss.encode's wall time, the Dask cluster started before, the fastest of --repeat runs",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
