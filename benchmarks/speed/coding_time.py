"""What the rate control's codings cost on the host (issue #52 part 3: the codings are part of
every encode; at CR 10 a fit's 5-14 codings of 110,000-330,000 Gaussians took 1.3-3.3 s of an
H200 encode's S2 stage beyond its iterations).

For each stored model: one coding of its parameters (``encode_coded``, the least of ``--repeat``),
then the fit of a budget ``--share`` of its file size (``Model.fit_bytes``: quantisation depths
and pruning, every trial a coding; the least of ``--repeat``), with the bytes of both so that two builds can be checked to
write the same files. Host only: no device.

    python benchmarks/speed/coding_time.py --models a.wgs,b.wgs --out OUT.json
    python benchmarks/speed/coding_time.py --models a.wgs --extra-bits 2 --share 0.8 --scored --repeat 2 --out OUT.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np

from warpgauss import Model
from warpgauss.encoding.bench import result_header
from warpgauss.format.coded import encode_coded


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--models", required=True, help="stored models (.wgs), comma-separated")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--share", type=float, default=0.97, help="the fit's budget as a share of the model's file size")
    ap.add_argument(
        "--extra-bits", type=int, default=0, help="start the fit this many bits above the model's depths (and its budget from that size)"
    )
    ap.add_argument(
        "--scored", action="store_true", help="a scored fit (the choice of prune shares, as the encode runs it; score: the weights' sum)"
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = {**result_header("the rate control's codings on the host", __file__, argv, "cpu"), "rows": []}
    print(f"{'model':28s} {'N':>8s} {'coding s':>9s} {'fit s':>7s} {'codings':>7s} {'B/G':>6s}")
    for path in args.models.split(","):
        m = Model.load(path)
        p = np.asarray(m.params)
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            payload, _, _ = encode_coded(p)
            times.append(time.perf_counter() - t)
        budget = int(args.share * Path(path).stat().st_size)
        if args.extra_bits:
            m.coded_bits = {k: v + args.extra_bits for k, v in m.coded_bits.items()}
            budget = int(args.share * m.fit_bytes(10**12)[1]["first_bytes"])
        score = (lambda fitted: float(np.asarray(fitted.params)[:, 11].sum())) if args.scored else None
        fits = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            fitted, info = m.fit_bytes(budget, score=score)
            fits.append(time.perf_counter() - t)
        stored, bits = np.asarray(fitted.params), info["bits"]
        fit_s = min(fits)
        row = {
            "model": Path(path).name,
            "n": m.n,
            "coding_s": min(times),
            "payload_bytes": len(payload),
            "payload_sha256": hashlib.sha256(payload).hexdigest(),
            "fit_budget": budget,
            "fit_s": fit_s,
            "fit_codings": info.get("codings"),
            "fit_chosen": info.get("chosen"),
            "fit_bits": bits,
            "fit_n": int(len(stored)),
            "fit_sha256": hashlib.sha256(np.ascontiguousarray(stored).tobytes()).hexdigest(),
        }
        print(f"{row['model']:28s} {m.n:8d} {row['coding_s']:9.3f} {fit_s:7.2f} {row['fit_codings']!s:>7s} {len(payload) / m.n:6.2f}")
        res["rows"].append(row)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
