"""Benchmark both render paths (ray marching, EWA splatting): frames per second at a given image size.

For each budget an analytic model of an example field is encoded (iterations 0: refinement does
not change the cost much), both renderers are built, one frame is rendered to warm up (kernel
compilation is reported separately), and then ``--frames`` frames are timed, orbiting the camera a
few degrees per frame so that no frame repeats the last. Two rates per path: ``kernel_fps`` from
the synchronised device time of the launches, and ``wall_fps`` including the frame's read-back
to the host. Writes JSON with the device name, Warp version and date.

    python benchmarks/bench_render.py --budgets 200000,1400000 --size 256 --resolution 1024   # GPU
    python benchmarks/bench_render.py --budgets 300 --size 24 --resolution 32 --frames 2 --device cpu
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss._warp import device_name, resolve_device, warp
from warpgauss.render import Camera, ModelRenderer, RenderSettings
from warpgauss.splat import SplatRenderer
from warpgauss.transfer import make_transfer_function


def _ints(text: str) -> list[int]:
    return [int(x) for x in text.split(",") if x]


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex", help="example field the models encode")
    ap.add_argument("--size", type=int, default=256, help="edge of the example volume")
    ap.add_argument("--budgets", default="200000,1400000", help="primitive counts, comma-separated")
    ap.add_argument("--resolution", default="1024", help="image N or WxH")
    ap.add_argument("--methods", default="march,splat")
    ap.add_argument("--frames", type=int, default=20, help="timed frames per path")
    ap.add_argument("--step", type=float, default=0.5, help="ray-marching step in voxels")
    ap.add_argument("--ert", type=float, default=1e-3, help="early ray termination threshold")
    ap.add_argument("--colormap", default="viridis")
    ap.add_argument("--opacity", default="0:0,0.3:0,1:1")
    ap.add_argument("--no-shading", action="store_true")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default="benchmarks/results/render.json")
    args = ap.parse_args(argv)

    wp = warp()
    dev = resolve_device(args.device)
    res = [int(x) for x in args.resolution.lower().split("x")]
    width, height = (res[0], res[0]) if len(res) == 1 else (res[0], res[1])
    methods = [m for m in args.methods.split(",") if m]
    tf = make_transfer_function(args.colormap, args.opacity)
    settings = RenderSettings(width=width, height=height, step=args.step, ert=args.ert, shading=not args.no_shading)

    from warpgauss.synthetic import generate

    t = time.perf_counter()
    vol = generate(args.field, args.size, seed=0)
    gen_s = time.perf_counter() - t
    rows = []
    compile_s = None
    for n in _ints(args.budgets):
        t = time.perf_counter()
        model = warpgauss.encode(vol, budget=n, iterations=0, device=dev, evaluate=False)
        encode_s = time.perf_counter() - t
        for method in methods:
            t = time.perf_counter()
            r = SplatRenderer(model, dev) if method == "splat" else ModelRenderer(model, dev)
            init_s = time.perf_counter() - t
            t = time.perf_counter()
            first = r.render(Camera(), tf, settings)
            first_s = time.perf_counter() - t
            if compile_s is None:
                compile_s = init_s + first_s
            kernel, wall = [], []
            for k in range(args.frames):
                cam = Camera(azimuth=-55.0 + 3.0 * (k + 1), elevation=25.0)
                t = time.perf_counter()
                img = r.render(cam, tf, settings)
                wall.append(time.perf_counter() - t)
                kernel.append(img.seconds)
            row = {
                "n": n,
                "method": method,
                "width": width,
                "height": height,
                "frames": args.frames,
                "kernel_fps": float(1.0 / np.median(kernel)) if kernel else None,
                "wall_fps": float(1.0 / np.median(wall)) if wall else None,
                "kernel_ms_median": float(1000 * np.median(kernel)) if kernel else None,
                "kernel_ms_min": float(1000 * np.min(kernel)) if kernel else None,
                "wall_ms_median": float(1000 * np.median(wall)) if wall else None,
                "renderer_init_seconds": init_s,
                "first_frame_seconds": first_s,
                "encode_seconds": encode_s,
                "coverage": float((first.rgba[..., 3] > 0.01).mean()),
                "stats": first.stats,
            }
            rows.append(row)
            print(
                f"N {n:9d}  {method:6s} {width}x{height}: {row['kernel_fps'] or 0:8.2f} fps kernel "
                f"({row['kernel_ms_median'] or 0:9.2f} ms), {row['wall_fps'] or 0:8.2f} fps wall; init {init_s:.2f} s",
                flush=True,
            )
            del r
    result = {
        "benchmark": "render (ray marching and EWA splatting)",
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "numpy_version": np.__version__,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([Path(__file__).name, *(argv if argv is not None else sys.argv[1:])]),
        "field": args.field,
        "size": args.size,
        "generate_seconds": gen_s,
        "transfer_function": tf.describe(),
        "settings": {"step": args.step, "ert": args.ert, "shading": not args.no_shading},
        "cold_compile_and_first_frame_seconds": compile_s,
        "rows": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2, default=str) + "\n")
    print(f"\n{result['device_name']}, Warp {result['warp_version']} -> {out}")
    return result


if __name__ == "__main__":
    main()
