"""The summary issue #52's check reads (``benchmarks/results/speed/summary_h200.json``), built from
the result files of this folder's runs; a target not measured is null and listed under
``not_measured``.

    python benchmarks/speed/summary.py --bench bench_kernels_1024_final_h200.json \\
        --sweep sweep_mri_lists_h200.json --baseline ../accuracy/sweep_mri_turn_h200.json \\
        --fields profile_fields512_h200.json --fast profile_fast_mri_h200.json,profile_fast_512_h200.json \\
        --out summary_h200.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RESULTS = Path(__file__).resolve().parents[1] / "results" / "speed"


def _row(bench: dict, n: int, m: int) -> dict:
    return next(r for r in bench["rows"] if r["n"] == n and r["samples"] == m)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--bench", default="bench_kernels_1024_final_h200.json")
    ap.add_argument("--sweep", default="sweep_mri_lists_h200.json")
    ap.add_argument("--baseline", default="../accuracy/sweep_mri_turn_h200.json")
    ap.add_argument("--fields", default=None, help="a profile_encode.py file whose NAME@512 rows time the 512^3 example fields")
    ap.add_argument(
        "--fast",
        default=None,
        help="profile_encode.py files, comma-separated: the share of the default's gain over the analytic model that "
        "--preset fast keeps (variant it300 against default, the default's row from any of these or --fields)",
    )
    ap.add_argument("--out", default="summary_h200.json")
    args = ap.parse_args(argv)
    bench = json.loads((RESULTS / args.bench).read_text())
    sweep = json.loads((RESULTS / args.sweep).read_text())
    base = json.loads((RESULTS / args.baseline).read_text())
    small, big = _row(bench, 20_000, 65_536), _row(bench, 1_400_000, 1_048_576)
    mri: dict[str, dict[str, float]] = {}
    key = lambda r: (r["volume"].split()[0], float(r["target_ratio"]))  # noqa: E731
    before = {key(r): r for r in base["rows"] if r["variant"] == "default"}
    losses = {}
    for r in sweep["rows"]:
        if r["variant"] != "default":
            continue
        vol, ratio = key(r)
        mri.setdefault(vol, {})[f"{ratio:g}"] = round(r["encode_s"], 2)
        if (vol, ratio) in before:
            losses[f"{vol} CR {ratio:g}"] = round(before[(vol, ratio)]["psnr_db"] - r["psnr_db"], 3)
    decode = next(e for e in bench["per_n"] if e["n"] == 1_400_000)
    fields = None
    if args.fields:
        prof = json.loads((RESULTS / args.fields).read_text())
        fields = {r["volume"]: round(r["wall_s"], 2) for r in prof["rows"] if r["volume"].endswith("@512")}
    fast = _fast_shares([args.fast or "", args.fields or ""]) if args.fast else None
    out = {
        "issue": 52,
        "device_name": bench["device_name"],
        "warp_version": bench["warp_version"],
        "date": sweep["date"],
        "commit": sweep.get("commit"),
        "sources": {"bench": args.bench, "sweep": args.sweep, "baseline": args.baseline, "fields": args.fields, "fast": args.fast},
        "gpairs_1400000x1048576": round(big["gpairs_per_s"], 3),
        "gpairs_20000x65536": round(small["gpairs_per_s"], 3),
        "iteration_ms_20000x65536": round(small["iteration_ms"], 3),
        "iteration_nograph_ms_20000x65536": round(small["iteration_nograph_ms"], 3),
        "paper_1024_refine_s": None,
        "paper_1024_total_s": None,
        "mri_encode_s": mri,
        "fields512_encode_s": fields,
        "decode_1024_s": round(decode["decode_ms"] / 1e3, 3),
        "fast_gain_share": fast,
        "bounded_code_s": None,
        "sz3_s": None,
        "max_sweep_loss_db": max(losses.values()),
        "sweep_loss_db": losses,
    }
    out["not_measured"] = [k for k, v in out.items() if v is None]
    (RESULTS / args.out).write_text(json.dumps(out, indent=1) + "\n")
    print(json.dumps(out, indent=1))
    return out


def _fast_shares(names: list[str]) -> dict[str, float]:
    """(fast - analytic) / (default - analytic) by "volume CR ratio", from profile_encode.py rows:
    variant it300 (what --preset fast runs) against the default row of the same volume and ratio."""
    rows = [r for n in ",".join(names).split(",") if n for r in json.loads((RESULTS / n).read_text())["rows"]]
    default = {(r["volume"], r["ratio"]): r["psnr_db"] for r in rows if r["variant"] == "default"}
    out = {}
    for r in rows:
        key = (r["volume"], r["ratio"])
        if r["variant"] == "it300" and key in default and r.get("analytic_psnr_db") is not None:
            a = r["analytic_psnr_db"]
            out[f"{r['volume']} CR {r['ratio']:g}"] = round((r["psnr_db"] - a) / (default[key] - a), 3)
    return out


if __name__ == "__main__":
    main()
