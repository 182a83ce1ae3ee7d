"""Where an Encoder call's time goes outside refinement (issue #21 in situ overhead): one cold
call, then warm calls under cProfile at a short time budget; prints the stage table and the
functions with the largest cumulative time.

    python benchmarks/series/profile_call.py --size 256 --budget 55000 --time-budget 0.12 --out $OUT/profile_call_h100.json
"""

from __future__ import annotations

import argparse
import cProfile
import datetime as dt
import io
import json
import pstats
import sys
from pathlib import Path

import warpgauss
from warpgauss.core.warp import device_name, resolve_device, warp
from warpgauss.readers.synthetic import generate_series


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--budget", type=int, default=55_000)
    ap.add_argument("--time-budget", type=float, default=0.12)
    ap.add_argument("--calls", type=int, default=3)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    vols = [wp.array(v, device=dev) for v in generate_series("bubbles", args.size, args.calls + 1, turn_degrees=1.0)]
    enc = warpgauss.Encoder(budget=args.budget, format="full", device=dev, time_budget=args.time_budget)
    enc.prepare()
    enc.encode(vols[0])
    prof = cProfile.Profile()
    calls = []
    for v in vols[1:]:
        prof.enable()
        m = enc.encode(v)
        prof.disable()
        calls.append({**m.report["encoder"], "stages": enc.calls[-1].stages, "psnr_db": m.report["psnr_db"]})
        print(calls[-1])
    s = io.StringIO()
    pstats.Stats(prof, stream=s).sort_stats("cumulative").print_stats(45)
    print(s.getvalue())
    out = {
        "command": "python benchmarks/series/profile_call.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "calls": calls,
        "profile": s.getvalue(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
