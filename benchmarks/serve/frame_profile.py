"""Where a `warpgauss serve` frame's time goes (issue #22): Viewer.frame's wall time against its
render kernels, the pieces around them, and how the view's settings move the kernel time
(opacity curve, cache resolution, image size). Variants ending "-cd" shade by central differences
(no gradient grid), the baseline of the gradient grid in the same run.

    python benchmarks/serve/frame_profile.py --size 512 --budget 1400000 --out $OUT/frame_profile.json

It also runs against an older warpgauss (only the public Viewer and renderer pieces are used), so
a change can be timed against its parent in the same run: put the parent's package on PYTHONPATH
(``git archive`` of warpgauss/, with kernels/ and cli/ inside it as warpgauss/kernels and
warpgauss/cli) and pass ``--label parent``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate
from warpgauss.render import raymarch
from warpgauss.render.viewer import Viewer

VARIANTS = {  # name: (opacity curve, cache_res or None, image side)
    "default": ([(0.0, 0.0), (1.0, 1.0)], None, 1024),
    "knee0.3": ([(0.0, 0.0), (0.3, 0.0), (1.0, 1.0)], None, 1024),
    "cache256": ([(0.0, 0.0), (1.0, 1.0)], 256, 1024),
    "image512": ([(0.0, 0.0), (1.0, 1.0)], None, 512),
}
# suffixes after a variant's name ("default-cd", "knee0.3-cd-t1"): -cd shade by central differences
# (no gradient grid), -tN the march launched over N x N tiles of pixels (1: row by row)


def profile(v: Viewer, frames: int, wp, dev, flags: list[str]) -> dict:
    v.frame()
    r = v._renderer(v.state)
    if "cd" in flags:  # the baseline: no gradient grid (six trilinear samples a shaded sample)
        r.volume.has_grad = 0
    for f in flags:
        if f.startswith("t"):
            r.march_tile = int(f[1:])
    v.frame()
    parts: dict[str, list[float]] = {k: [] for k in ("frame", "kernels", "tf", "render_call", "readback", "sync")}
    for _ in range(frames):
        v.orbit(360.0 / frames / 0.4, 0.0)
        t0 = time.perf_counter()
        v.frame()
        parts["frame"].append(time.perf_counter() - t0)
        s = v.state
        t0 = time.perf_counter()
        tf = v.transfer_function(s)
        cam, settings = v.camera(s), v.settings(None, s)
        t1 = time.perf_counter()
        img = v._renderer(s).render(cam, tf, settings)
        t2 = time.perf_counter()
        wp.synchronize_device(dev)
        t3 = time.perf_counter()
        img.rgb8()
        t4 = time.perf_counter()
        parts["tf"].append(t1 - t0)
        parts["render_call"].append(t2 - t1)
        parts["sync"].append(t3 - t2)
        parts["readback"].append(t4 - t3)
        parts["kernels"].append(img.seconds)  # the same view as the frame's
    return {f"{k}_ms_median": 1000 * float(np.median(x)) for k, x in parts.items()} | {
        "gradient_grid": bool(getattr(v._renderer(v.state).volume, "has_grad", 0)),
        "march_tile": int(getattr(v._renderer(v.state), "march_tile", 1)),
        "evaluations_per_pixel": img.stats["evaluations_per_pixel"],
        "frame_ms_p90": 1000 * float(np.percentile(parts["frame"], 90)),
        "kernels_ms_p90": 1000 * float(np.percentile(parts["kernels"], 90)),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=1_400_000)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="names of VARIANTS with optional suffixes (see there)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--label", default="this tree", help="what is timed (e.g. parent, when an older package is on PYTHONPATH)")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    model = warpgauss.encode(generate(args.field, args.size), budget=args.budget, iterations=0, device=dev, format="full")
    rows = []
    for name in args.variants.split(","):
        base, *flags = name.split("-")
        opacity, cache_res, side = VARIANTS[base]
        if flags and not hasattr(raymarch, "count_stats"):
            continue  # a package from before these knobs
        name = name.strip()
        v = Viewer([model], device=dev, method="cached", cache_res=cache_res)
        v.resize(side, side)
        v.set_opacity(opacity)
        r = {
            "variant": name,
            "opacity": opacity,
            "cache_res": cache_res,
            "image": side,
            **profile(v, args.frames, wp, dev, flags),
        }
        rows.append(r)
        print(
            f"{name:14s}: frame {r['frame_ms_median']:.1f} ms (p90 {r['frame_ms_p90']:.1f}), kernels {r['kernels_ms_median']:.1f} "
            f"(p90 {r['kernels_ms_p90']:.1f}); pieces: tf {r['tf_ms_median']:.2f}, render call {r['render_call_ms_median']:.1f}, "
            f"sync after {r['sync_ms_median']:.2f}, RGB8 read-back {r['readback_ms_median']:.2f}; "
            f"{r['evaluations_per_pixel']:.0f} samples a pixel, gradient grid {r['gradient_grid']}, tile {r['march_tile']}",
            flush=True,
        )
        del v
    result = {
        **result_header("warpgauss serve: where a frame's time goes", __file__, argv, dev),
        "label": args.label,
        "warpgauss_path": str(Path(warpgauss.__file__).parent),
        "field": args.field,
        "size": args.size,
        "n": int(model.n),
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
