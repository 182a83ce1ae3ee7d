"""Plot bench_rd.py results: one panel per volume, PSNR against compression ratio (log x).

Also prints (or writes with ``--table``) a Markdown table per volume: each warpgauss budget with
SZ3 and ZFP at the matched ratio, and encode / decode seconds.

    python benchmarks/rate_distortion/plot_rd.py benchmarks/results/rate_distortion/bench_rd_fields128_cpu.json -o benchmarks/results/rate_distortion/bench_rd_fields128_cpu.png

Fixed-ratio runs (``bench_rd.py --ratios``) are merged by volume label, so the reference codecs
measured on one machine and warpgauss on another make one figure: series wg, sz3-matched,
zfp-rate-matched and sperr, and per volume a table with a row per target ratio (PSNR of each
codec, warpgauss minus SZ3 and minus SPERR, achieved ratios, encode / decode seconds):

    python benchmarks/rate_distortion/plot_rd.py benchmarks/results/rate_distortion/bench_rd_codecs_cpu.json bench_rd_h100.json \\
        -o benchmarks/results/rate_distortion/bench_rd_mri_fields512.png --table /tmp/bench_rd.md
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


def _panel(ax, label: str, series) -> None:
    """One volume's panel: each (name, style, points) series, PSNR against ratio on a log axis."""
    for name, style, pts in series:
        if pts:
            ax.plot(*zip(*pts), label=name, lw=1.2, **style)
    ax.set_xscale("log")
    ax.set_title(label, fontsize=9)
    ax.set_xlabel("compression ratio (source bytes / compressed bytes)", fontsize=7)
    ax.set_ylabel("PSNR (dB), full grid", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax.tick_params(labelsize=7)


def plot(results: list[dict], out: Path, max_psnr: float = 120.0) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vols = [(res, label, entry) for res in results for label, entry in res["volumes"].items() if entry["rows"]]
    cols = min(4, len(vols))
    rows = math.ceil(len(vols) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False)
    for ax, (_res, label, entry) in zip(axes.ravel(), vols):
        _panel(
            ax,
            label,
            [
                (name, style, [(r["ratio"], r["psnr_db"]) for r in _rows(entry, codec) if r["psnr_db"] <= max_psnr])
                for codec, name, style in SERIES
            ],
        )
    for ax in axes.ravel()[len(vols) :]:
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


# ---------------------------------------------------------------------------- fixed ratios

FIXED_SERIES = (  # codec, label, style
    ("wg", "warpgauss (defaults, coded)", dict(color="C0", marker="o", ls="-")),
    ("sz3-matched", "SZ3 (abs bound searched to the CR)", dict(color="C3", marker="^", ls="-")),
    ("zfp-rate-matched", "ZFP fixed rate", dict(color="C2", marker="v", ls="-")),
    ("sperr", "SPERR (bpp)", dict(color="C4", marker="s", ls="-")),
)
FIXED_NAMES = {"wg": "wg", "sz3-matched": "SZ3", "zfp-rate-matched": "ZFP", "sperr": "SPERR"}


def _is_fixed(res: dict) -> bool:
    return res.get("settings", {}).get("mode") == "fixed ratios"


def _target(row: dict) -> float | None:
    if "target_ratio" in row:
        return float(row["target_ratio"])
    m = row.get("matched_to") or {}
    return float(m["target_ratio"]) if "target_ratio" in m else None


def _machine(res: dict) -> str:
    return f"{res['device_name']} ({res.get('cpu_count')} cores)"


def merge_fixed(results: list[dict], names: list[str] | None = None) -> dict:
    """Fixed-ratio runs merged by volume label: label -> {"meta", "rows": {codec: {target: row}},
    "unreachable": [...], "sources": {codec: machine}}.

    A codec measured by two runs keeps the later run's rows. Volumes whose source bytes differ
    between runs are refused: the labels would name different data.
    """
    merged: dict = {}
    names = names or [f"run {i}" for i in range(len(results))]
    for res, name in zip(results, names):
        for label, entry in res["volumes"].items():
            m = merged.setdefault(
                label,
                {
                    "meta": {k: v for k, v in entry.items() if k not in ("rows", "unreachable")},
                    "rows": {},
                    "unreachable": [],
                    "sources": {},
                },
            )
            if m["meta"].get("source_bytes") != entry.get("source_bytes") or m["meta"].get("shape_xyz") != entry.get("shape_xyz"):
                raise ValueError(f"{label}: {name} has other source bytes or shape than an earlier run")
            for row in entry["rows"]:
                t = _target(row)
                if row["codec"] in FIXED_NAMES and t is not None:
                    m["rows"].setdefault(row["codec"], {})[t] = row
                    m["sources"][row["codec"]] = _machine(res)
            m["unreachable"] += entry.get("unreachable", [])
    return merged


def _where_fixed(sources: dict) -> str:
    """'wg on A; SZ3, ZFP, SPERR on B': the machine of each codec's rows."""
    by: dict = {}
    for codec, _, _ in FIXED_SERIES:
        if codec in sources:
            by.setdefault(sources[codec], []).append(FIXED_NAMES[codec])
    return "; ".join(f"{', '.join(names)} on {machine}" for machine, names in by.items())


def plot_fixed(merged: dict, results: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vols = [(label, m) for label, m in merged.items() if m["rows"]]
    cols = min(3, len(vols))
    nrows = math.ceil(len(vols) / cols)
    fig, axes = plt.subplots(nrows, cols, figsize=(4.6 * cols, 3.8 * nrows), squeeze=False)
    for ax, (label, m) in zip(axes.ravel(), vols):
        _panel(
            ax,
            label,
            [
                (name, style, sorted((r["ratio"], r["psnr_db"]) for r in m["rows"].get(codec, {}).values()))
                for codec, name, style in FIXED_SERIES
            ],
        )
    for ax in axes.ravel()[len(vols) :]:
        ax.axis("off")
    handles = {}
    for ax in axes.ravel()[: len(vols)]:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    names = [name for _, name, _ in FIXED_SERIES if name in handles]  # the series' order, whichever panel has each
    fig.legend([handles[n] for n in names], names, loc="lower center", ncol=4, fontsize=8, frameon=False)
    where = [_where_fixed(m["sources"]) for m in merged.values()]
    where = sorted(set(where), key=where.index)
    wg = next((r for r in results if r.get("warpgauss_run")), None)
    v = next((r["codec_versions"] for r in results if r.get("codecs")), {})
    parts = ["; ".join(where)]
    if wg is not None:
        rows = [r for m in merged.values() for r in m["rows"].get("wg", {}).values()]
        its = sorted({r.get("iterations") for r in rows if r.get("iterations") is not None})
        sam = sorted({r.get("samples") for r in rows if r.get("samples") is not None})
        span = f"{'/'.join(f'{i:,}' for i in its)} iterations x {'-'.join(f'{x:,}' for x in (sam[:1] + sam[-1:] if len(sam) > 1 else sam))} samples"
        parts.append(f"warpgauss {wg['warpgauss_version']} defaults ({span}, per row in the JSON), Warp {wg['warp_version']}")
    if v:
        parts.append(f"pysz {v.get('pysz')}, zfpy {v.get('zfpy')}, numcodecs-wasm-sperr {v.get('numcodecs-wasm-sperr')}")
    fig.suptitle("Rate-distortion at fixed ratios: " + "\n".join(parts), fontsize=8)
    height = 3.8 * nrows  # inches: the title takes its lines, the legend about half an inch
    fig.tight_layout(rect=(0, 0.5 / height, 1, 1 - (0.17 * len(parts) + 0.1) / height))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    print(f"-> {out}")


def table_fixed(merged: dict) -> str:
    """Markdown, one table per volume: a row per target ratio, the PSNR of each codec, warpgauss
    minus SZ3 and minus SPERR, the ratios achieved, encode / decode seconds of each.

    ``n/r``: the codec cannot reach that ratio (ZFP below its minimum rate, warpgauss with no room
    for a Gaussian); ``-``: not measured; ``*``: the ratio achieved is outside the search tolerance.
    """
    codecs = [c for c, _, _ in FIXED_SERIES]
    out = []
    for label, m in merged.items():
        meta = m["meta"]
        unreach = {(u["codec"], float(u["target_ratio"])) for u in m["unreachable"]}
        targets = sorted({t for rows in m["rows"].values() for t in rows} | {t for _, t in unreach})
        src = _where_fixed(m["sources"])
        out += [
            f"### {label}",
            "",
            f"{meta.get('source_dtype')}, {meta.get('source_bytes', 0):,} source bytes; {src}",
            "",
            "| CR | "
            + " | ".join(f"{FIXED_NAMES[c]} dB" for c in codecs)
            + " | wg - SZ3 dB | wg - SPERR dB | achieved CR "
            + ", ".join(FIXED_NAMES[c] for c in codecs)
            + " | "
            + " | ".join(f"{FIXED_NAMES[c]} enc / dec s" for c in codecs)
            + " |",
            "|" + "---|" * (1 + 2 * len(codecs) + 3),
        ]
        for t in targets:
            rows = {c: m["rows"].get(c, {}).get(t) for c in codecs}

            def cell(c, fmt, mark=True, rows=rows, t=t, unreach=unreach):
                r = rows[c]
                if r is None:
                    return "n/r" if (c, t) in unreach else "-"
                star = "" if not mark or (r.get("matched_to") or {}).get("within_tol", True) else "*"
                return fmt(r) + star

            def diff(a, b, rows=rows):
                ra, rb = rows[a], rows[b]
                return "-" if ra is None or rb is None else f"{ra['psnr_db'] - rb['psnr_db']:+.2f}"

            out.append(
                f"| {t:g} | "
                + " | ".join(cell(c, lambda r: f"{r['psnr_db']:.2f}") for c in codecs)
                + f" | {diff('wg', 'sz3-matched')} | {diff('wg', 'sperr')} | "
                + ", ".join(cell(c, lambda r: f"{r['ratio']:.1f}") for c in codecs)
                + " | "
                + " | ".join(cell(c, lambda r: f"{r['encode_s']:.3g} / {r['decode_s']:.3g}", False) for c in codecs)
                + " |"
            )
        out.append("")
    out.append(
        "n/r: ratio not reachable by the codec; -: not measured; *: achieved ratio outside the search tolerance. "
        "PSNR: full grid, normalised by the volume's min/max. Encode / decode: one single-threaded call "
        "(SZ3: the call at the bound found); warpgauss: encode + save / load + full-grid decode."
    )
    return "\n".join(out)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("json", nargs="+", help="bench_rd.py outputs")
    ap.add_argument("-o", "--out", default="benchmarks/results/rate_distortion/bench_rd_cpu.png")
    ap.add_argument("--table", default=None, help="also write the Markdown table here")
    args = ap.parse_args(argv)
    results = [json.loads(Path(p).read_text()) for p in args.json]
    fixed = [_is_fixed(r) for r in results]
    if any(fixed):
        if not all(fixed):
            ap.error("give fixed-ratio runs (bench_rd.py --ratios) or ladder runs, not both")
        merged = merge_fixed(results, args.json)
        plot_fixed(merged, results, Path(args.out))
        t = table_fixed(merged)
        print(t)
        if args.table:
            Path(args.table).write_text(t + "\n")
        return
    plot(results, Path(args.out))
    t = table(results)
    print(t)
    if args.table:
        Path(args.table).write_text(t + "\n")


if __name__ == "__main__":
    main()
