"""Plot bounded_rd.py results: one panel per volume, compression ratio against the bound (log-log):
the bounded file (Gaussians at each ratio + residual), the residual alone and SZ3 at the same bound.

    python benchmarks/bounded/plot_bounded.py benchmarks/results/bounded/bounded_rd256_h200.json \
        --codecs benchmarks/results/bounded/codecs_bounded256_cpu.json -o benchmarks/results/bounded/bounded_rd256_h200.png

``--codecs``: SZ3, SPERR and ZFP at the same bounds (``codecs_bounded.py``) instead of the SZ3 rows
``bounded_rd.py`` copied from the older sweep.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("result")
    ap.add_argument("-o", "--out", required=True)
    ap.add_argument("--codecs", default=None, help="codecs_bounded.py's JSON")
    a = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = json.loads(Path(a.result).read_text())["rows"]
    others = json.loads(Path(a.codecs).read_text())["rows"] if a.codecs else []
    styles = {"sz3": ("SZ3", "C3", "^"), "sperr-pwe": ("SPERR (pwe)", "C4", "v"), "zfp-acc": ("ZFP (accuracy)", "C2", "x")}
    vols = list(dict.fromkeys(r["volume"] for r in rows))
    fig, axes = plt.subplots(1, len(vols), figsize=(4.2 * len(vols), 3.8), squeeze=False)
    for ax, v in zip(axes[0], vols):
        mine = [r for r in rows if r["volume"] == v]
        for g, style in (
            (None, dict(color="C7", marker="s", ls="--")),
            *((g, dict(marker="o", ls="-")) for g in sorted({r["gaussian_ratio"] for r in mine if r["gaussian_ratio"]})),
        ):
            pts = sorted((r["bound_rel"], r["ratio"]) for r in mine if r["gaussian_ratio"] == g)
            label = "residual alone" if g is None else f"Gaussians 1/{g:g} + residual"
            ax.plot(*zip(*pts), label=label, **style)
        if others:
            for codec, (label, colour, marker) in styles.items():
                pts = sorted((r["bound_rel"], r["ratio"]) for r in others if r["volume"] == v and r["codec"] == codec)
                if pts:
                    ax.plot(*zip(*pts), label=label, color=colour, marker=marker, ls="-")
        else:
            sz = sorted((r["bound_rel"], r["sz3"]["ratio"]) for r in mine if r["sz3"] and r["gaussian_ratio"] is None)
            if sz:
                ax.plot(*zip(*sz), label="SZ3 (same bound)", color="C3", marker="^", ls="-")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("bound / value range")
        ax.set_title(v.split(".")[0], fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("compression ratio (whole file)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
