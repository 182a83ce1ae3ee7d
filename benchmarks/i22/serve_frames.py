"""Server-side frame rate of `warpgauss serve` (issue #22 targets: 1024x1024 frames of a
1.4M-primitive model at >= 30 frames per second with cached marching; a transfer-function change
to its new frame <= 100 ms).

What is timed is the page's own path without the browser: warpgauss.viewer.Viewer.frame() (render,
RGBA -> RGB8, copy to the host) for an orbit of frames, then the image encodings trame-rca would
apply (PNG lossless, JPEG quality 90), and set_opacity + frame() for transfer-function edits.
The model: N primitives placed by the analytic allocation on an example field (no refinement:
the frame cost does not depend on how well it fits).

    python benchmarks/i22/serve_frames.py --size 512 --budget 1400000 --out $OUT/i22_serve_frames.json
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss._warp import resolve_device
from warpgauss.bench import result_header
from warpgauss.synthetic import generate
from warpgauss.viewer import Viewer


def encode_seconds(img: np.ndarray, fmt: str) -> float:
    from PIL import Image

    t0 = time.perf_counter()
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format=fmt, **({"quality": 90} if fmt == "JPEG" else {"compress_level": 1}))
    return time.perf_counter() - t0


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--field", default="vortex")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--budget", type=int, default=1_400_000)
    ap.add_argument("--image", type=int, default=1024)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    model = warpgauss.encode(generate(args.field, args.size), budget=args.budget, iterations=0, device=dev, format="full")
    alloc = time.perf_counter() - t0
    rows = []
    for method in ("cached", "splat"):
        v = Viewer([model], device=dev, method=method)
        v.resize(args.image, args.image)
        t0 = time.perf_counter()
        v.frame()  # builds the renderer (the cache's decode) and compiles
        first = time.perf_counter() - t0
        v.frame()
        times = []
        for _ in range(args.frames):  # an orbit: every frame a new camera
            v.orbit(360.0 / args.frames / 0.4, 0.0)
            t0 = time.perf_counter()
            img = v.frame()
            times.append(time.perf_counter() - t0)
        tf_times = []
        for k in range(10):  # transfer-function edits: the opacity curve's knee moves
            t0 = time.perf_counter()
            v.set_opacity([(0.0, 0.0), (0.1 + 0.05 * k, 0.0), (1.0, 1.0)])
            v.frame()
            tf_times.append(time.perf_counter() - t0)
        png = float(np.median([encode_seconds(img, "PNG") for _ in range(5)]))
        jpeg = float(np.median([encode_seconds(img, "JPEG") for _ in range(5)]))
        med = float(np.median(times))
        rows.append(
            {
                "method": method,
                "image": f"{args.image}x{args.image}",
                "first_frame_seconds": first,
                "frame_ms_median": 1000 * med,
                "frame_ms_p90": 1000 * float(np.percentile(times, 90)),
                "fps": 1.0 / med,
                "tf_change_to_frame_ms_median": 1000 * float(np.median(tf_times)),
                "tf_change_to_frame_ms_max": 1000 * float(np.max(tf_times)),
                "png_encode_ms": 1000 * png,
                "jpeg_encode_ms": 1000 * jpeg,
                "fps_with_jpeg": 1.0 / (med + jpeg),
            }
        )
        r = rows[-1]
        print(
            f"{method:7s} {r['image']}: frame {r['frame_ms_median']:.1f} ms ({r['fps']:.1f} fps; p90 {r['frame_ms_p90']:.1f}), "
            f"TF change -> frame {r['tf_change_to_frame_ms_median']:.1f} ms (max {r['tf_change_to_frame_ms_max']:.1f}), "
            f"PNG {r['png_encode_ms']:.1f} ms, JPEG {r['jpeg_encode_ms']:.1f} ms, first frame {first:.2f} s",
            flush=True,
        )
    result = {
        **result_header("warpgauss serve: server-side frames (Viewer.frame) and encodings", __file__, argv, dev),
        "field": args.field,
        "size": args.size,
        "n": int(model.n),
        "allocation_seconds": alloc,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
