"""Benchmark the render paths (exact ray marching, ray marching of the cached grid, EWA splatting):
frames per second at a given image size.

For each budget an analytic model of an example field is encoded (iterations 0: refinement does
not change the cost much), each renderer is built (its init time reported; for ``cached`` that
includes decoding the model onto its grid, reported again as ``cache_seconds``, a one-time cost
that the frame rates exclude), one frame is rendered to warm up (kernel compilation is reported
separately), and then ``--frames`` frames are timed, orbiting the camera a few degrees per frame so
that no frame repeats the last. Two rates per path: ``kernel_fps`` from the synchronised device
time of the launches, and ``wall_fps`` including the frame's read-back to the host.

``--max-seconds`` caps the time spent on one path: a slow one (the exact march of a large model
takes seconds per frame) times as many frames as fit, at least one, and its row records
``cut_short``; when even the warm-up frame overran the cap, that frame is the one timed
(``warmup_timed``). The JSON (device name, Warp version, date, rows so far) is rewritten
atomically after every row, so an interrupted run keeps what finished.

    python benchmarks/render/bench_render.py --budgets 200000,1400000 --size 256 --resolution 1024   # GPU
    python benchmarks/render/bench_render.py --budgets 300 --size 24 --resolution 32 --frames 2 --device cpu
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
from warpgauss.core.files import atomic_write_bytes
from warpgauss.core.warp import device_name, resolve_device, warp
from warpgauss.render.renderers import METHODS, Camera, RenderSettings, make_renderer
from warpgauss.render.transfer import make_transfer_function


def _ints(text: str) -> list[int]:
    return [int(float(x)) for x in text.split(",") if x]


def time_frames(r, tf, settings, frames: int, max_seconds: float | None, first) -> dict:
    """Time up to ``frames`` frames of renderer ``r`` within ``max_seconds`` (None: no cap).

    Args:
        first: (image, wall seconds) of the warm-up frame; timed instead when it alone overran the cap.
    """
    first_img, first_s = first
    kernel: list[float] = []
    wall: list[float] = []
    warmup_timed = False
    if max_seconds is not None and first_s >= max_seconds and frames > 0:
        kernel, wall, warmup_timed = [first_img.seconds], [first_s], True
    else:
        spent = first_s  # the warm-up counts against the cap
        for k in range(frames):
            if kernel and max_seconds is not None and spent + wall[-1] > max_seconds:
                break  # the next frame would not fit (at least one is always timed)
            cam = Camera(azimuth=-55.0 + 3.0 * (k + 1), elevation=25.0)
            t = time.perf_counter()
            img = r.render(cam, tf, settings)
            wall.append(time.perf_counter() - t)
            kernel.append(img.seconds)
            spent += wall[-1]
    return {"kernel": kernel, "wall": wall, "warmup_timed": warmup_timed, "cut_short": len(kernel) < frames}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex", help="example field the models encode")
    ap.add_argument("--size", type=int, default=256, help="edge of the example volume")
    ap.add_argument("--budgets", default="200000,1400000", help="primitive counts, comma-separated")
    ap.add_argument("--resolution", default="1024", help="image N or WxH")
    ap.add_argument("--methods", default="march,splat,cached", help=f"comma-separated, of {', '.join(METHODS)}")
    ap.add_argument("--frames", type=int, default=20, help="timed frames per path")
    ap.add_argument("--max-seconds", type=float, default=60.0, help="time cap per path (warm-up and timed frames); 0: none")
    ap.add_argument("--cache-res", type=int, default=None, help="cached: voxels along the cache's longest axis (default: the model grid)")
    ap.add_argument("--step", type=float, default=0.5, help="ray-marching step in voxels")
    ap.add_argument("--ert", type=float, default=1e-3, help="early ray termination threshold")
    ap.add_argument("--colormap", default="viridis")
    ap.add_argument("--opacity", default="0:0,0.3:0,1:1")
    ap.add_argument("--no-shading", action="store_true")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default="benchmarks/results/render/bench_render.json")
    args = ap.parse_args(argv)

    methods = [m for m in args.methods.split(",") if m]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        ap.error(f"--methods takes a comma-separated list of {', '.join(METHODS)}, got {args.methods!r}")
    if args.frames < 1:
        ap.error(f"--frames must be at least 1, got {args.frames}")
    if args.max_seconds < 0:
        ap.error(f"--max-seconds must be >= 0 (0: no cap), got {args.max_seconds}")
    if args.cache_res is not None and args.cache_res < 1:
        ap.error(f"--cache-res must be a positive number of voxels, got {args.cache_res}")
    max_seconds = args.max_seconds or None

    wp = warp()
    dev = resolve_device(args.device)
    res = [int(x) for x in args.resolution.lower().split("x")]
    width, height = (res[0], res[0]) if len(res) == 1 else (res[0], res[1])
    tf = make_transfer_function(args.colormap, args.opacity)
    settings = RenderSettings(width=width, height=height, step=args.step, ert=args.ert, shading=not args.no_shading)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)

    from warpgauss.readers.synthetic import generate

    t = time.perf_counter()
    vol = generate(args.field, args.size, seed=0)
    gen_s = time.perf_counter() - t
    result = {
        "benchmark": "render (exact ray marching, ray marching of the cached grid, EWA splatting)",
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
        "max_seconds_per_path": max_seconds,
        "cold_compile_and_first_frame_seconds": None,
        "complete": False,
        "rows": [],
    }

    def save() -> None:
        atomic_write_bytes(out, (json.dumps(result, indent=2, default=str) + "\n").encode())

    save()
    rows = result["rows"]
    for n in _ints(args.budgets):
        t = time.perf_counter()
        model = warpgauss.encode(vol, budget=n, iterations=0, device=dev, evaluate=False)
        encode_s = time.perf_counter() - t
        for method in methods:
            t = time.perf_counter()
            r = make_renderer(model, method, dev, cache_res=args.cache_res if method == "cached" else None)
            init_s = time.perf_counter() - t
            t = time.perf_counter()
            first = r.render(Camera(), tf, settings)
            first_s = time.perf_counter() - t
            if result["cold_compile_and_first_frame_seconds"] is None:
                result["cold_compile_and_first_frame_seconds"] = init_s + first_s
            timed = time_frames(r, tf, settings, args.frames, max_seconds, (first, first_s))
            kernel, wall = timed["kernel"], timed["wall"]
            row = {
                "n": n,
                "method": method,
                "width": width,
                "height": height,
                "frames": len(kernel),
                "frames_requested": args.frames,
                "cut_short": timed["cut_short"],
                "warmup_timed": timed["warmup_timed"],
                "kernel_fps": float(1.0 / np.median(kernel)),
                "wall_fps": float(1.0 / np.median(wall)),
                "kernel_ms_median": float(1000 * np.median(kernel)),
                "kernel_ms_min": float(1000 * np.min(kernel)),
                "wall_ms_median": float(1000 * np.median(wall)),
                "renderer_init_seconds": init_s,
                "cache_seconds": getattr(r, "cache_seconds", None),
                "cache_shape": list(r.cache_shape) if hasattr(r, "cache_shape") else None,
                "first_frame_seconds": first_s,
                "encode_seconds": encode_s,
                "coverage": float((first.rgba[..., 3] > 0.01).mean()),
                "stats": first.stats,
            }
            rows.append(row)
            save()
            cache = f", cache {row['cache_seconds']:.2f} s" if row["cache_seconds"] is not None else ""
            cut = f" [cut short at {len(kernel)} of {args.frames} frames by --max-seconds]" if row["cut_short"] else ""
            print(
                f"N {n:9d}  {method:6s} {width}x{height}: {row['kernel_fps']:8.2f} fps kernel "
                f"({row['kernel_ms_median']:9.2f} ms), {row['wall_fps']:8.2f} fps wall; init {init_s:.2f} s{cache}{cut}",
                flush=True,
            )
            del r
    result["complete"] = True
    save()
    print(f"\n{result['device_name']}, Warp {result['warp_version']} -> {out}")
    return result


if __name__ == "__main__":
    main()
