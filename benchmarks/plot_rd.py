"""Plot bench_rd.py results: one panel per volume, PSNR against compression ratio (log x).

Also prints (or writes with ``--table``) a Markdown table per volume: each warpgauss budget with
SZ3 and ZFP at the matched ratio, and encode / decode seconds.

    python benchmarks/plot_rd.py benchmarks/results/rd_cpu_128.json -o benchmarks/results/rd_cpu_128.png
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

SERIES = (  # codec, label, style
    ("wg-full", "warpgauss full precision", dict(color="C0", marker="o", ls="-")),
    ("wg-compact", "warpgauss compact", dict(color="C0", marker="s", ls="--", mfc="none")),
    ("sz3", "SZ3 (abs error bound)", dict(color="C3", marker="^", ls="-")),
    ("sz3-matched", "SZ3 matched to warpgauss", dict(color="C3", marker="*", ls="none", ms=10)),
    ("zfp-rate", "ZFP fixed rate", dict(color="C2", marker="v", ls="-")),
    ("zfp-rate-matched", "ZFP fixed rate, matched", dict(color="C2", marker="x", ls="none", ms=8)),
    ("zfp-acc", "ZFP fixed accuracy", dict(color="C1", marker="D", ls=":")),
)


def _rows(entry, codec):
    return sorted((r for r in entry["rows"] if r["codec"] == codec), key=lambda r: r["ratio"])


def _where(res: dict) -> str:
    """The machine of a run; a resumed run names the one its reused rows came from too."""
    here = f"{res['device_name']} ({res.get('cpu_count')} cores)"
    prev = res.get("previous_run")
    return here if not prev else f"{prev['device_name']} ({prev.get('cpu_count')} cores), rows added on {here}"


def plot(results: list[dict], out: Path, max_psnr: float = 120.0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vols = [(res, label, entry) for res in results for label, entry in res["volumes"].items() if entry["rows"]]
    cols = min(4, len(vols))
    rows = math.ceil(len(vols) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for ax, (res, label, entry) in zip(axes.ravel(), vols):
        for codec, name, style in SERIES:
            pts = [(r["ratio"], r["psnr_db"]) for r in _rows(entry, codec) if r["psnr_db"] <= max_psnr]
            if pts:
                ax.plot(*zip(*pts), label=name, lw=1.2, **style)
        ax.set_xscale("log")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("compression ratio (source bytes / compressed bytes)", fontsize=7)
        ax.set_ylabel("PSNR (dB), full grid", fontsize=8)
        ax.grid(True, which="both", alpha=0.3)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(vols):]:
        ax.axis("off")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    r0 = results[0]
    s = r0["settings"]
    fig.legend(handles, labels, loc="lower center", ncol=4, fontsize=8, frameon=False)
    fig.suptitle(
        f"Rate-distortion, {_where(r0)}, warpgauss {s['iterations']} iterations x "
        f"{s['samples']} samples, Warp {r0['warp_version']}, pysz {r0['codec_versions']['pysz']}, zfpy {r0['codec_versions']['zfpy']}",
        fontsize=9,
    )
    fig.tight_layout(rect=(0, 0.08 if rows == 1 else 0.05, 1, 0.95))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"-> {out}")


def table(results: list[dict]) -> str:
    """Markdown: per volume and budget, PSNR of each codec at (about) the warpgauss ratio."""
    lines = [
        "| volume | N | ratio full | wg full dB | SZ3 dB (ratio) | ZFP-rate dB | wg enc s | wg dec s | SZ3 enc/dec s | "
        "ratio compact | wg compact dB | ZFP-rate dB (compact ratio) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for res in results:
        for label, entry in res["volumes"].items():
            full = {r["n"]: r for r in _rows(entry, "wg-full")}
            comp = {r["n"]: r for r in _rows(entry, "wg-compact")}
            sz = {r["matched_to"]["n"]: r for r in _rows(entry, "sz3-matched") if r["matched_to"]["format"] == "full"}
            zf = {(r["matched_to"]["n"], r["matched_to"]["format"]): r for r in _rows(entry, "zfp-rate-matched")}
            for n in sorted(full):
                f, c, s = full[n], comp.get(n), sz.get(n)
                zff, zfc = zf.get((n, "full")), zf.get((n, "compact"))
                cell = lambda r, k="psnr_db": "-" if r is None else f"{r[k]:.2f}"  # noqa: E731
                lines.append(
                    f"| {label} | {n:,} | {f['ratio']:.1f} | {f['psnr_db']:.2f} | "
                    + ("-" if s is None else f"{s['psnr_db']:.2f} ({s['ratio']:.1f})")
                    + f" | {cell(zff)} | {f['encode_s']:.1f} | {f['decode_s']:.1f} | "
                    + ("-" if s is None else f"{s['encode_s']:.3f}/{s['decode_s']:.3f}")
                    + f" | {'-' if c is None else format(c['ratio'], '.1f')} | {cell(c)} | {cell(zfc)} |"
                )
    return "\n".join(lines)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("json", nargs="+", help="bench_rd.py outputs")
    ap.add_argument("-o", "--out", default="benchmarks/results/rd_cpu.png")
    ap.add_argument("--table", default=None, help="also write the Markdown table here")
    args = ap.parse_args(argv)
    results = [json.loads(Path(p).read_text()) for p in args.json]
    plot(results, Path(args.out))
    t = table(results)
    print(t)
    if args.table:
        Path(args.table).write_text(t + "\n")


if __name__ == "__main__":
    main()
