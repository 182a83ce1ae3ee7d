"""Server-side frame rate of `warpgauss serve` (issue #22 targets: 1024x1024 frames of a
1.4M-primitive model at >= 30 frames per second with cached marching; a transfer-function change
to its new frame <= 100 ms).

What is timed is the page's own path without the browser: warpgauss.render.viewer.Viewer.frame() (render,
RGBA -> RGB8, copy to the host) for an orbit of frames, then the image encodings trame-rca would
apply: the page's (warpgauss.render.serve.FrameEncoder: JPEG 90 while the view moves, lossless PNG at
zlib level 1 once still) and trame-rca's own PNG (PIL's default compression), and set_opacity +
frame() for transfer-function edits. Then the page's own path (warpgauss.render.serve.Area, without the
browser and the websocket): on an asyncio loop as trame-rca drives it, each change (a camera step,
an opacity edit) renders in Area's worker thread, the page is told to fetch it, and it is encoded
as a moving frame (JPEG) in a thread pool as trame-rca's scheduler does; timed from the change to
the encoded bytes, one at a time (latency) and back to back with the encodings overlapping the next
render (throughput). The worker thread's frames are checked bit for bit against frames rendered on
the main thread.
The model: N primitives placed by the analytic allocation on an example field (no refinement:
the frame cost does not depend on how well it fits).

    python benchmarks/serve/serve_frames.py --size 512 --budget 1400000 --out $OUT/serve_frames.json
"""

from __future__ import annotations

import argparse
import io
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate
from warpgauss.render.viewer import Viewer


def encode(img: np.ndarray, fmt: str) -> bytes:
    """ "moving": the page's JPEG; "still": the page's PNG; "trame-png": trame-rca's own PNG
    (Image.fromarray(...).save(buf, "png", quality=q): PIL's default compression)."""
    from PIL import Image

    from warpgauss.render.serve import FrameEncoder

    h, w = img.shape[:2]
    if fmt == "moving":
        return FrameEncoder().encode(img, w, h, 90)[0]
    if fmt == "still":
        return FrameEncoder().encode(img, w, h, FrameEncoder.STILL)[0]
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="png", quality=100)
    return buf.getvalue()


def encode_seconds(img: np.ndarray, fmt: str) -> float:
    t0 = time.perf_counter()
    encode(img, fmt)
    return time.perf_counter() - t0


async def page_path(viewer: Viewer, changes: list, pool) -> dict:
    """The page's path for a list of state changes (callables on the viewer): Area renders each in
    its worker thread; the frame is then encoded as a moving frame (JPEG) in ``pool``. Latency: one change at a time,
    change -> encoded bytes. Throughput: the same changes back to back, each encoding overlapping
    the next render (as trame-rca's scheduler pushes frames while the next renders)."""
    import asyncio

    from warpgauss.render.serve import Area

    loop = asyncio.get_running_loop()
    fetched = asyncio.Event()
    area = Area(viewer, on_frame=lambda seconds: None, request_update=fetched.set)
    area.img_cols_rows  # noqa: B018 - the first frame renders at once, on this thread

    async def one(change):
        change(viewer)
        fetched.clear()
        area.img_cols_rows  # noqa: B018 - starts the worker thread's render, shows the last frame
        await fetched.wait()
        img = area.img_cols_rows[0]
        return img, loop.run_in_executor(pool, encode, img, "moving")

    latency, frames = [], []
    for change in changes:
        t0 = time.perf_counter()
        img, enc = await one(change)
        await enc
        latency.append(time.perf_counter() - t0)
        frames.append((viewer.snapshot(), img))
    t0 = time.perf_counter()
    pending = []
    for change in changes:
        pending.append((await one(change))[1])
    await asyncio.gather(*pending)
    total = time.perf_counter() - t0
    same = all(np.array_equal(img, viewer.frame(state)) for state, img in frames)
    return {"latency": latency, "fps": len(changes) / total, "bit_identical_to_main_thread": same}


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
        opacity = [tuple(p) for p in v.state.opacity]
        times = []
        for _ in range(args.frames):  # an orbit: every frame a new camera
            v.orbit(360.0 / args.frames / 0.4, 0.0)
            t0 = time.perf_counter()
            img = v.frame()
            times.append(time.perf_counter() - t0)
        kernel = []  # the march alone (launch to synchronisation), for what Viewer.frame adds around it
        for _ in range(10):
            v.orbit(360.0 / args.frames / 0.4, 0.0)
            kernel.append(v._renderer(v.state).render(v.camera(), v.transfer_function(), v.settings()).seconds)
        tf_times = []
        for k in range(10):  # transfer-function edits: the opacity curve's knee moves
            t0 = time.perf_counter()
            v.set_opacity([(0.0, 0.0), (0.1 + 0.05 * k, 0.0), (1.0, 1.0)])
            v.frame()
            tf_times.append(time.perf_counter() - t0)
        import asyncio
        from concurrent.futures import ThreadPoolExecutor

        pool = ThreadPoolExecutor(4)  # trame-rca's encoding pool has max(4, cpu_count) threads
        step = 360.0 / args.frames / 0.4
        v.set_opacity(opacity)  # the orbit again with the same opacity as the first
        orbit = asyncio.run(page_path(v, [lambda w, s=step: w.orbit(s, 0.0)] * args.frames, pool))
        knees = [lambda w, k=k: w.set_opacity([(0.0, 0.0), (0.12 + 0.05 * k, 0.0), (1.0, 1.0)]) for k in range(10)]
        tf_page = asyncio.run(page_path(v, knees, pool))
        pool.shutdown()
        png = float(np.median([encode_seconds(img, "still") for _ in range(5)]))
        jpeg = float(np.median([encode_seconds(img, "moving") for _ in range(5)]))
        trame_png = float(np.median([encode_seconds(img, "trame-png") for _ in range(3)]))
        med = float(np.median(times))
        rows.append(
            {
                "method": method,
                "image": f"{args.image}x{args.image}",
                "first_frame_seconds": first,
                "frame_ms_median": 1000 * med,
                "frame_ms_p90": 1000 * float(np.percentile(times, 90)),
                "render_kernel_ms_median": 1000 * float(np.median(kernel)),
                "fps": 1.0 / med,
                "tf_change_to_frame_ms_median": 1000 * float(np.median(tf_times)),
                "tf_change_to_frame_ms_max": 1000 * float(np.max(tf_times)),
                "still_png_encode_ms": 1000 * png,
                "moving_jpeg_encode_ms": 1000 * jpeg,
                "trame_rca_default_png_encode_ms": 1000 * trame_png,
                "fps_with_jpeg": 1.0 / (med + jpeg),
                "page_orbit_to_jpeg_ms_median": 1000 * float(np.median(orbit["latency"])),
                "page_orbit_fps_pipelined": orbit["fps"],
                "page_tf_change_to_jpeg_ms_median": 1000 * float(np.median(tf_page["latency"])),
                "page_tf_change_to_jpeg_ms_max": 1000 * float(np.max(tf_page["latency"])),
                "page_worker_frames_bit_identical": bool(orbit["bit_identical_to_main_thread"] and tf_page["bit_identical_to_main_thread"]),
            }
        )
        r = rows[-1]
        print(
            f"{method:7s} {r['image']}: frame {r['frame_ms_median']:.1f} ms ({r['fps']:.1f} fps; p90 {r['frame_ms_p90']:.1f}; "
            f"kernels {r['render_kernel_ms_median']:.1f}), "
            f"TF change -> frame {r['tf_change_to_frame_ms_median']:.1f} ms (max {r['tf_change_to_frame_ms_max']:.1f}), "
            f"still PNG {r['still_png_encode_ms']:.1f} ms, moving JPEG {r['moving_jpeg_encode_ms']:.1f} ms "
            f"(trame-rca's PNG {r['trame_rca_default_png_encode_ms']:.1f} ms), first frame {first:.2f} s",
            flush=True,
        )
        print(
            f"        page path (worker thread + JPEG): orbit step -> JPEG {r['page_orbit_to_jpeg_ms_median']:.1f} ms, "
            f"{r['page_orbit_fps_pipelined']:.1f} fps back to back; TF change -> JPEG {r['page_tf_change_to_jpeg_ms_median']:.1f} ms "
            f"(max {r['page_tf_change_to_jpeg_ms_max']:.1f}); worker frames bit-identical: {r['page_worker_frames_bit_identical']}",
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
