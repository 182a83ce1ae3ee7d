"""Benchmark run time against error: final PSNR versus refinement seconds, per preset and time budget.

For each size and example field the volume is generated once (``generate(name, size, seed=0)``,
timed as ``generate_seconds``) and encoded with N Gaussians by each preset (``paper``, ``fast``,
``quality``) and by the ``--time-budget-preset`` (default ``paper``) under each time budget
(``encode(..., time_budget=T)``; the encoder then chooses the iterations and the samples per
iteration, 1-64x the preset's, from timed probe iterations: ``samples`` is its choice and
``budget_plan`` the report's ``refinement.time_budget``). The paper preset always runs
first for every field / size / N: it is the baseline that ``delta_final_db_vs_paper`` and
``refine_time_ratio_vs_paper`` refer to, measured in the same process and run.

A warm-up encode compiles every kernel module before anything is timed. One line is printed per
row as it finishes, and the JSON (``--out``) is rewritten atomically after every row, so a run that
is killed (or stopped by ``--max-seconds``, or by Ctrl-C, which ends the current refinement
early and starts nothing more) leaves every finished row; ``complete`` is true only when every
planned run was made, and ``skipped`` lists the others. ``python3
benchmarks/refine/plot_tradeoff.py OUT.json`` draws the figure and prints a markdown table.

Times per row (seconds):

- ``refine_seconds``: stage S2 as the report's stage table has it: refiner set-up (upload,
  first binning), the binned-vs-dense self-test and the iterations.
- ``refine_loop_seconds``: the iterations alone (``report["refinement"]["seconds"]``; what
  ``bench_refine.py`` calls ``refine_seconds``).
- ``self_test_seconds``: the self-test (0 where the encoder reused the warm-up's: it runs once
  per process and device). A time budget covers self-test + iterations (the budget
  starts once the kernels are compiled), not the set-up before them, so ``within_budget`` checks
  ``self_test_seconds + refine_loop_seconds <= time_budget``.
- ``encode_seconds``: every stage except P (the volume is already in memory), i.e. S1a-S1e, S1x,
  S2 and EV; ``wall_seconds`` is the whole ``encode`` call.

``peak_device_bytes`` is Warp's CUDA pool high-water mark since the process started (the pool has
no reset), so within one run of this script it never decreases from row to row.

Generating the example volumes is numpy on the host and, at 1024^3, takes longer than encoding
them. ``generate(name, 256)`` measured on a 2-core CPU (Python 3.11, numpy, one process):
vortex 1.19 s, bubbles 0.05 s, turbulence 1.21 s, interface 0.23 s; at 128^3: 0.26, 0.02, 0.10,
0.04 s. The work grows with the voxel count (turbulence, an FFT, somewhat faster), so 1024^3
(64x the voxels of 256^3) takes roughly vortex 75 s, bubbles 3 s, turbulence 80-100 s,
interface 15 s, and 512^3 about an eighth of that (the H100 host measured 11.2, 0.4, 9.4, 1.8 s
at 512^3, ``refine/bench_encode_h100.json``). A 1024^3 float32 volume is 4 GiB; each is freed before the next
one is generated (turbulence holds a complex64 half-spectrum, another 4 GiB, while it is made).

    python3 benchmarks/refine/bench_tradeoff.py --sizes 512 --budget 1400000 --out benchmarks/results/refine/bench_tradeoff_512.json
    python3 benchmarks/refine/bench_tradeoff.py --sizes 1024 --fields vortex,bubbles --max-seconds 480 \\
        --out benchmarks/results/refine/bench_tradeoff_1024_a.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import gc
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BASELINE = "paper"
FIELD_DOCS = {
    "refine_seconds": "stage S2: refiner set-up + self-test + iterations",
    "refine_loop_seconds": "iterations only (report['refinement']['seconds'])",
    "self_test_seconds": "binned-vs-dense self-test (inside the time budget)",
    "encode_seconds": "sum of all stages except P (volume already in memory)",
    "wall_seconds": "the whole encode() call",
    "delta_final_db_vs_paper": "psnr_final_db minus the paper preset's, same field / size / n, same run",
    "refine_time_ratio_vs_paper": "refine_seconds / the paper preset's refine_seconds",
    "peak_device_bytes": "Warp CUDA pool high-water mark since the process started (never reset)",
}


def _floats(text: str) -> list[float]:
    return [float(x) for x in str(text).split(",") if x.strip()]


def _ints(text: str) -> list[int]:
    return [int(x) for x in str(text).split(",") if x.strip()]


def _names(text: str) -> list[str]:
    return [x.strip() for x in str(text).split(",") if x.strip()]


def _label(t: float) -> str:
    return f"T={t:g}s"


def write_json(path: Path, data: dict) -> None:
    """Write ``data`` to ``path`` atomically (a temporary file in the same folder, then os.replace)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(data, indent=2, default=str) + "\n")
        os.chmod(tmp, 0o644)  # mkstemp makes it 0600
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def make_row(field: str, size: int, n: int, gen_s: float, run: dict, m, wall: float) -> dict:
    """One result row from an encoded model's report."""
    r = m.report
    ev = r["evaluation"]
    ref = r["refinement"]
    if "final" not in ev:  # refinement interrupted (Ctrl-C): no evaluation
        return {"field": field, "size": size, "n": n, "run": run["label"], "kind": run["kind"], "psnr_final_db": None,
                "interrupted": f"at iteration {ref.get('iterations_done')}"}  # fmt: skip
    stages = {s["stage"]: s["seconds"] for s in r["stages"]}
    tb = ref.get("time_budget") or {}
    loop = ref.get("seconds")
    test = ref.get("self_test") or {}
    st = 0.0 if test.get("reused") else test.get("seconds", 0.0)  # reused: passed earlier in this process
    row = {
        "field": field,
        "size": size,
        "n": n,
        "run": run["label"],
        "kind": run["kind"],
        "preset": run["preset"],
        "time_budget": run.get("time_budget"),
        "iterations_override": run.get("iterations"),
        "iterations": ref.get("iterations_done", ref.get("iterations", 0)),
        "planned_iterations": ref.get("iterations", 0),
        "samples": ref.get("samples"),
        "psnr_analytic_db": ev["analytic"]["psnr_db"],
        "psnr_final_db": ev["final"]["psnr_db"],
        "gain_db": ev["gain_db"],
        "eval_mode": ev["final"].get("mode"),
        "refine_seconds": stages.get("S2", 0.0),
        "refine_loop_seconds": loop,
        "self_test_seconds": st,
        "ms_per_iteration": ref.get("ms_per_iteration"),
        "encode_seconds": sum(v for k, v in stages.items() if k != "P"),
        "wall_seconds": wall,
        "load_seconds": stages.get("P", 0.0),
        "stages": stages,
        "total_seconds": r["total_seconds"],
        "peak_device_bytes": r["peak_device_bytes"],
        "peak_host_bytes": r["peak_host_bytes"],
        "lr_touch_scale": ref.get("lr_touch_scale"),
        "contacts_per_primitive": ref.get("contacts_per_primitive"),
        "rebins": ref.get("rebins"),
        "cuda_graph": ref.get("cuda_graph"),
        "generate_seconds": gen_s,
        "delta_final_db_vs_paper": None,
        "refine_time_ratio_vs_paper": None,
    }
    if run.get("time_budget") is not None:
        row["budget_stopped_early"] = tb.get("stopped_early")
        row["budget_plan"] = tb  # probes, cost model, the samples and iterations chosen
        row["within_budget"] = (st or 0.0) + (loop or 0.0) <= run["time_budget"]
    return row


def _print(row: dict) -> None:
    for what in ("refused", "interrupted"):
        if what in row:
            print(f"{row['field']:11s} {row['size']:5d} {row['n']:8d} {row['run']:>9s}  {what}: {row[what]}", flush=True)
            return
    d = row["delta_final_db_vs_paper"]
    delta = "" if d is None or row["run"] == BASELINE else f" ({d:+6.2f} vs paper)"
    print(
        f"{row['field']:11s} {row['size']:5d} {row['n']:8d} {row['run']:>9s}  it {row['iterations']:5d} x {row['samples'] or 0:6d}"
        f"  S2 {row['refine_seconds']:8.3f} s (loop {row['refine_loop_seconds'] or 0:8.3f}, {row['ms_per_iteration'] or 0:7.3f} ms/it)"
        f"  encode {row['encode_seconds']:8.3f} s  PSNR {row['psnr_analytic_db']:6.2f} -> {row['psnr_final_db']:6.2f} dB{delta}",
        flush=True,
    )


def plan_runs(presets: list[str], time_budgets: list[float], budget_preset: str, iterations: int | None) -> list[dict]:
    """The runs per field / size / N: the paper baseline first, the other presets, then the time budgets."""
    runs = [{"label": BASELINE, "kind": "preset", "preset": BASELINE, "iterations": iterations}]
    runs += [{"label": p, "kind": "preset", "preset": p, "iterations": iterations} for p in presets if p != BASELINE]
    runs += [
        {"label": _label(t), "kind": "time_budget", "preset": budget_preset, "time_budget": t, "iterations": None}
        for t in sorted(time_budgets)
    ]
    return runs


def _result(args, argv, dev: str, wp, fields, sizes, budgets, runs, warm: float) -> dict:
    """The result file's head: the device, the versions, the command and the configuration."""
    from warpgauss.core.warp import device_name

    return {
        "benchmark": "run time against error: PSNR vs refinement seconds per preset and time budget",
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "numpy_version": np.__version__,
        "host": platform.node(),
        "cpu_count": os.cpu_count(),
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "command": list(sys.argv if argv is None else ["benchmarks/refine/bench_tradeoff.py", *argv]),
        "config": {
            "fields": fields,
            "sizes": sizes,
            "budgets": budgets,
            "runs": runs,
            "seed": args.seed,
            "self_test": not args.no_self_test,
            "max_seconds": args.max_seconds,
        },
        "baseline": BASELINE,
        "field_docs": FIELD_DOCS,
        "warmup_seconds": warm,
        "volumes": [],
        "rows": [],
        "skipped": [],
        "complete": False,
    }


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fields", default="vortex,bubbles,turbulence,interface")
    ap.add_argument("--sizes", default="512,1024", help="voxels per axis, comma list")
    ap.add_argument("--budget", "--budgets", dest="budgets", default="1400000", help="N Gaussians, comma list")
    ap.add_argument("--presets", default="paper,fast,quality", help="paper (the baseline) always runs first")
    ap.add_argument("--time-budgets", default="0.25,0.5,1,2,4", help="seconds, comma list ('' for none)")
    ap.add_argument("--time-budget-preset", default=BASELINE, help="preset (samples per iteration) of the time-budget runs")
    ap.add_argument("--iterations-override", type=int, default=None, help="iterations of every preset run (quick checks)")
    ap.add_argument("--no-self-test", action="store_true", help="skip the refiner's self-test (it counts against a time budget)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--seed", type=int, default=0, help="encoding seed (the fields use seed 0)")
    ap.add_argument(
        "--max-seconds",
        type=float,
        default=None,
        help="start no field or run after this much wall time, nor one expected (from the same run's earlier rows) to end past it",
    )
    ap.add_argument("--out", default="benchmarks/results/refine/bench_tradeoff.json")
    return ap


def main(argv=None) -> dict:
    ap = _parser()
    args = ap.parse_args(argv)
    t_start = time.perf_counter()

    import warpgauss
    from warpgauss.core.warp import resolve_device, warp
    from warpgauss.encoding.refine import PRESETS
    from warpgauss.readers.synthetic import EXAMPLES, generate

    wp = warp()
    dev = resolve_device(args.device)
    fields, sizes, budgets = _names(args.fields), _ints(args.sizes), _ints(args.budgets)
    runs = plan_runs(_names(args.presets), _floats(args.time_budgets), args.time_budget_preset, args.iterations_override)
    out = Path(args.out)
    for p in {r["preset"] for r in runs}:
        if p not in PRESETS:
            ap.error(f"unknown preset {p!r}; use {', '.join(PRESETS)}")
    for f in fields:
        if f not in EXAMPLES:
            ap.error(f"unknown field {f!r}; use {', '.join(EXAMPLES)}")

    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64)  # compiles every module
    warm = time.perf_counter() - t0

    result = _result(args, argv, dev, wp, fields, sizes, budgets, runs, warm)
    rows, skipped = result["rows"], result["skipped"]
    write_json(out, result)

    seen: dict[tuple, float] = {}  # (size, n, label) / (size, "generate") -> longest measured seconds
    stopped = None

    def elapsed() -> float:
        return time.perf_counter() - t_start

    def fits(estimate: float | None) -> bool:
        return args.max_seconds is None or elapsed() + (estimate or 0.0) <= args.max_seconds

    def run_estimate(size: int, n: int, label: str) -> float | None:
        if (size, n, label) in seen:
            return seen[(size, n, label)]
        other = [v for k, v in seen.items() if len(k) == 3 and k[2] == label]  # another size or N
        return max(other) if other else None

    def gen_estimate(size: int) -> float | None:
        if (size, "generate") in seen:
            return seen[(size, "generate")]
        smaller = [(s, v) for (s, k), v in seen.items() if k == "generate" and s < size]
        return max(v * (size / s) ** 3 for s, v in smaller) if smaller else None

    for size in sizes:
        for name in fields:
            if stopped is None and not fits(gen_estimate(size)):
                stopped = f"--max-seconds {args.max_seconds:g} reached after {elapsed():.0f} s"
            if stopped:
                skipped.extend({"field": name, "size": size, "n": n, "run": r["label"], "why": stopped} for n in budgets for r in runs)
                continue
            t = time.perf_counter()
            vol = generate(name, size, seed=0)
            gen_s = time.perf_counter() - t
            seen[(size, "generate")] = max(seen.get((size, "generate"), 0.0), gen_s)
            result["volumes"].append({"field": name, "size": size, "generate_seconds": gen_s})
            print(f"{name:11s} {size:5d}  generated in {gen_s:.2f} s", flush=True)
            write_json(out, result)
            for n in budgets:
                base = None
                for run in runs:
                    if stopped is None and not fits(run_estimate(size, n, run["label"])):
                        stopped = f"--max-seconds {args.max_seconds:g} reached after {elapsed():.0f} s"
                    if stopped:
                        skipped.append({"field": name, "size": size, "n": n, "run": run["label"], "why": stopped})
                        continue
                    kw = {"preset": run["preset"], "iterations": run["iterations"]}
                    if run.get("time_budget") is not None:
                        kw["time_budget"] = run["time_budget"]
                    t = time.perf_counter()
                    try:
                        m = warpgauss.encode(vol, budget=n, seed=args.seed, device=dev, self_test=not args.no_self_test, **kw)
                    except warpgauss.WarpgaussError as e:
                        row = {"field": name, "size": size, "n": n, "run": run["label"], "kind": run["kind"], "refused": str(e)}
                        rows.append(row)
                        _print(row)
                        write_json(out, result)
                        if "seed limit" in str(e):  # every run of this N is refused alike
                            skipped.extend(
                                {"field": name, "size": size, "n": n, "run": r["label"], "why": "budget refused"}
                                for r in runs[runs.index(run) + 1 :]
                            )
                            break
                        continue
                    wall = time.perf_counter() - t
                    seen[(size, n, run["label"])] = max(seen.get((size, n, run["label"]), 0.0), wall)
                    row = make_row(name, size, n, gen_s, run, m, wall)
                    del m
                    if row.get("interrupted"):  # Ctrl-C stops the refiner, not the process: stop here
                        rows.append(row)
                        _print(row)
                        stopped = "interrupted"
                        continue
                    if run["label"] == BASELINE:
                        base = row
                    if base is not None:
                        row["delta_final_db_vs_paper"] = row["psnr_final_db"] - base["psnr_final_db"]
                        if base["refine_seconds"]:
                            row["refine_time_ratio_vs_paper"] = row["refine_seconds"] / base["refine_seconds"]
                    rows.append(row)
                    _print(row)
                    write_json(out, result)
            del vol
            gc.collect()

    result["complete"] = not skipped
    result["elapsed_seconds"] = elapsed()
    write_json(out, result)
    done = sum(1 for r in rows if r.get("psnr_final_db") is not None)
    extra = f", {len(skipped)} runs skipped ({skipped[0]['why']})" if skipped else ""
    print(f"\n{result['device_name']}, Warp {result['warp_version']}: {done} rows in {elapsed():.0f} s{extra} -> {out}")
    return result


if __name__ == "__main__":
    main()
