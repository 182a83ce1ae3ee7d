"""Seam quality of the bricked encode (issue #20), CPU: full-grid PSNR on voxels within 2 voxels of
an inner brick face against the rest, 2x2x2 bricks, the default halo and 8, two example fields at 48^3.
``--together``: also every brick started at once, beside stand-ins for all its neighbours
(``warpgauss.encoding.scale.bricks.NEIGHBOURS_FIRST`` False), the rows marked ``"waves": "together"``.

    python benchmarks/bricked/seam_cpu.py --out benchmarks/results/bricked/seam_cpu.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import warp
from warpgauss.encoding.scale import schedule as wsched
from warpgauss.encoding.scale.plan import face_band, plan_bricks
from warpgauss.field.analysis import normalise
from warpgauss.readers.synthetic import generate


def psnr(e: np.ndarray) -> float:
    return float(10 * np.log10(1 / max(float(e.mean()), 1e-20)))


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=48)
    ap.add_argument("--budget", type=int, default=1500)
    ap.add_argument("--iterations", type=int, default=150)
    ap.add_argument("--together", action="store_true", help="also every brick at once (no waves)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    rows = []
    for name in ("vortex", "interface"):
        v = generate(name, args.size)
        f = normalise(v)
        kw = dict(budget=args.budget, iterations=args.iterations, device="cpu", format="full", self_test=False)
        near = face_band(f.shape_xyz, plan_bricks(f.shape_xyz, (2, 2, 2), 0))
        mm = warpgauss.encode(v, **kw)
        e0 = (mm.decode(device="cpu", normalised=True) - f.values) ** 2
        mono = {"monolithic_psnr_db": psnr(e0), "monolithic_seam_psnr_db": psnr(e0[near]), "monolithic_interior_psnr_db": psnr(e0[~near])}
        for halo, first in [(h, True) for h in (None, 8)] + ([(h, False) for h in (None, 8)] if args.together else []):
            with wsched.schedule(neighbours_first=first):
                m = warpgauss.encode(v, bricks="2x2x2", halo=halo, **kw)
            err = (m.decode(device="cpu", normalised=True) - f.values) ** 2
            row = {
                "field": name,
                "waves": "neighbours first" if first else "together",
                "halo": m.report["bricking"]["halo"],
                "scale_cap": m.report["bricking"]["scale_cap"],
                **mono,
                "psnr_db": psnr(err),
                "seam_psnr_db": psnr(err[near]),
                "interior_psnr_db": psnr(err[~near]),
            }
            rows.append(row)
            print(row, flush=True)
    result = {
        "benchmark": "bricked encode seam quality (2x2x2), CPU",
        "command": "python benchmarks/bricked/seam_cpu.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "device": "cpu",
        "warp_version": warp().config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "settings": vars(args) | {"out": str(args.out)},
        "rows": rows,
    }
    args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
