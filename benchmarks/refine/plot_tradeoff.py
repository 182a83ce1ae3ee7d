"""Plot run time against error from one or more ``bench_tradeoff.py`` JSON files.

One panel per grid size (and per N when a file holds several): x = refinement seconds (stage S2 by
default, log scale), y = final PSNR; one colour per field, one marker per run kind (presets paper /
fast / quality, time budgets), the time-budget points of a field joined by a line, the paper preset
(the baseline) drawn larger with a black edge, and each field's analytic (unrefined) PSNR as a
dotted line. Also prints a markdown table of every row, with the difference to the paper preset.

    python3 benchmarks/refine/plot_tradeoff.py benchmarks/results/refine/bench_tradeoff_512.json benchmarks/results/refine/bench_tradeoff_1024_*.json \\
        --out benchmarks/results/refine/bench_tradeoff.png

Needs matplotlib (``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

FIELD_ORDER = ["vortex", "bubbles", "turbulence", "interface"]
MARKERS = {"paper": "o", "fast": "^", "quality": "s"}
BUDGET_MARKER = "D"
X_KEYS = {
    "stage": ("refine_seconds", "refinement seconds (stage S2: set-up, self-test, iterations)"),
    "loop": ("refine_loop_seconds", "refinement seconds (iterations only)"),
    "encode": ("encode_seconds", "encode seconds (all stages but loading)"),
}


def load_rows(paths: list[str]) -> tuple[list[dict], list[dict]]:
    """All measured rows (refused ones dropped) and the files' top-level facts."""
    rows, meta = [], []
    for p in paths:
        data = json.loads(Path(p).read_text())
        meta.append({k: data.get(k) for k in ("device_name", "warp_version", "date", "complete")} | {"path": str(p)})
        for r in data.get("rows", []):
            if "refused" in r or r.get("psnr_final_db") is None:
                continue
            rows.append(dict(r, device_name=data.get("device_name")))
    return rows, meta


def _fields(rows: list[dict]) -> list[str]:
    names = {r["field"] for r in rows}
    return [f for f in FIELD_ORDER if f in names] + sorted(names - set(FIELD_ORDER))


def markdown_table(rows: list[dict]) -> str:
    """Rows sorted by size, N, field; time-budget runs after the presets, by budget."""

    def key(r):
        f = _fields(rows)
        tb = r.get("time_budget")
        return (r["size"], r["n"], f.index(r["field"]), tb is not None, tb or 0.0, r["run"] != "paper", r["run"])

    head = (
        "| field | size | N | run | iterations x samples | S2 s | loop s | encode s | analytic dB | final dB | vs paper |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|"
    )
    lines = [head]
    for r in sorted(rows, key=key):
        d = r.get("delta_final_db_vs_paper")
        vs = "baseline" if r["run"] == "paper" else ("" if d is None else f"{d:+.2f} dB")
        lines.append(
            f"| {r['field']} | {r['size']}^3 | {r['n']:,} | {r['run']} | {r['iterations']:,} x {r['samples'] or 0:,} "
            f"| {r['refine_seconds']:.2f} | {r.get('refine_loop_seconds') or 0:.2f} | {r['encode_seconds']:.2f} "
            f"| {r['psnr_analytic_db']:.2f} | {r['psnr_final_db']:.2f} | {vs} |"
        )
    return "\n".join(lines)


def plot(rows: list[dict], out: Path, x: str = "stage", title: str | None = None) -> Path:
    """Write the figure to ``out`` (PNG) and return the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    xkey, xlabel = X_KEYS[x]
    panels = sorted({(r["size"], r["n"]) for r in rows})
    fields = _fields(rows)
    colours = {f: plt.get_cmap("tab10")(i % 10) for i, f in enumerate(fields)}
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(6.4 * max(len(panels), 1), 5.6), squeeze=False)
    for ax, (size, n) in zip(axes[0], panels):
        sub = [r for r in rows if r["size"] == size and r["n"] == n and (r.get(xkey) or 0) > 0]
        for f in fields:
            fr = [r for r in sub if r["field"] == f]
            if not fr:
                continue
            c = colours[f]
            tb = sorted((r for r in fr if r.get("time_budget") is not None), key=lambda r: r[xkey])
            if tb:
                ax.plot([r[xkey] for r in tb], [r["psnr_final_db"] for r in tb], "-", color=c, alpha=0.6, lw=1.2)
                ax.scatter([r[xkey] for r in tb], [r["psnr_final_db"] for r in tb], marker=BUDGET_MARKER, color=c, s=28, zorder=3)
            for r in fr:
                if r.get("time_budget") is not None:
                    continue
                base = r["run"] == "paper"
                ax.scatter(
                    r[xkey],
                    r["psnr_final_db"],
                    marker=MARKERS.get(r.get("preset") or r["run"], "P"),
                    color=c,
                    s=110 if base else 50,
                    edgecolors="black" if base else "none",
                    linewidths=1.6 if base else 0,
                    zorder=4,
                )
            analytic = fr[0]["psnr_analytic_db"]
            ax.axhline(analytic, color=c, ls=":", lw=1.0, alpha=0.7)
        ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("final PSNR (dB)")
        ax.set_title(f"{size}^3, N = {n:,}")
        ax.grid(True, which="both", alpha=0.3)
    handles = [Line2D([], [], color=colours[f], marker="o", ls="", label=f) for f in fields]
    handles += [
        Line2D(
            [], [], color="grey", marker="o", ls="", ms=10, markeredgecolor="black", markeredgewidth=1.6, label="paper preset (baseline)"
        ),
        Line2D([], [], color="grey", marker="^", ls="", label="fast preset"),
        Line2D([], [], color="grey", marker="s", ls="", label="quality preset"),
        Line2D([], [], color="grey", marker=BUDGET_MARKER, ls="-", label="time budgets"),
        Line2D([], [], color="grey", ls=":", label="analytic model (no refinement)"),
    ]
    ncol = 3 if len(panels) < 2 else 5
    legend_rows = -(-len(handles) // ncol)
    fig.legend(handles=handles, loc="lower center", ncol=ncol, frameon=False, fontsize=9)
    if title is None:
        devices = sorted({r.get("device_name") or "?" for r in rows})
        ns = sorted({r["n"] for r in rows})
        title = f"PSNR vs refinement time, {', '.join(devices)}, N = {', '.join(f'{v:,}' for v in ns)}"
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.02 + 0.045 * legend_rows, 1, 0.95))
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def main(argv=None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("inputs", nargs="+", help="bench_tradeoff.py JSON files")
    ap.add_argument("--out", default="benchmarks/results/refine/bench_tradeoff.png")
    ap.add_argument("--x", choices=sorted(X_KEYS), default="stage", help="which seconds go on the x axis")
    ap.add_argument("--title", default=None)
    args = ap.parse_args(argv)
    rows, meta = load_rows(args.inputs)
    if not rows:
        ap.error("no measured rows in " + ", ".join(args.inputs))
    for m in meta:
        flag = "" if m["complete"] else " (incomplete: stopped or killed before the end)"
        print(f"{m['path']}: {m['device_name']}, Warp {m['warp_version']}, {m['date']}{flag}")
    print()
    print(markdown_table(rows))
    out = plot(rows, Path(args.out), x=args.x, title=args.title)
    print(f"\n-> {out}")
    return out


if __name__ == "__main__":
    main()
