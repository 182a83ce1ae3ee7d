"""Region decode against the whole decode (issue #56 part 1): a BOX^3 box of a SIZE^3 model decoded
at ZOOM x its resolution ((BOX * ZOOM)^3 output voxels) against the whole SIZE^3 decode.

The model is the kernel benchmarks' uniform one (``warpgauss.encoding.bench.bench_primitives``: N
Gaussians spread over the grid, sigma 0.7 of their spacing, anisotropic up to 2:1), so every
brick holds work. Both decodes run once to warm up (kernels compiled and loaded), then are timed
``--repeat`` times each, on the device and with the result read back to the host:

- ``device_ms``: the slabs evaluated into device memory (``GaussianField.decode_slab``), no copy;
- ``host_ms``: ``GaussianField.decode`` (the normalised float32 array on the host), what
  ``Model.decode`` costs before the conversion to source units;
- ``field_build_ms``: preparing and binning the N Gaussians (``GaussianField``), paid once by both.

``ratio`` is box / whole; the issue's target is a 64^3 box at 256^3 of a 1024^3 1.4M model in at
most 5 % of the whole decode's time (H200). ``crop_equal``: the box at ZOOM 1 decodes to the crop
of the whole decode, bit for bit (checked at every size). The JSON (device name, Warp version,
date, commit) goes to ``benchmarks/results/decode/region_<SIZE>_n<N>_<device>.json`` or ``--out``.

    python benchmarks/decode/region.py                                                   # GPU: 1024^3, 1.4M, 64^3 box at 4x
    python benchmarks/decode/region.py --size 32 --n 2000 --box 8 --zoom 4 --device cpu --out /tmp/region.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from warpgauss.core.files import atomic_write_bytes
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import Timer, bench_primitives, result_header
from warpgauss.field.gaussians import DECODE_SLAB_VOXELS, GaussianField
from warpgauss.field.region import sampling

RESULTS = Path(__file__).resolve().parents[1] / "results" / "decode"


def centred_box(size: int, box: int) -> tuple[tuple[int, int], ...]:
    """The BOX^3 box in the middle of a SIZE^3 grid (voxel bounds, x0 <= x < x1)."""
    lo = (size - box) // 2
    return ((lo, lo + box),) * 3


def decode_on_device(gf: GaussianField, shape_xyz, box) -> None:
    """Every slab of a decode of ``box`` (None: the whole extent) at ``shape_xyz`` evaluated into
    one device buffer, no host copy (as ``GaussianField.iter_slabs`` slices it)."""
    wp = warp()
    nx, ny, nz = shape_xyz
    scale, offset = sampling(box, shape_xyz, gf.shape_xyz)
    slab = max(1, min(nz, DECODE_SLAB_VOXELS // (nx * ny)))
    buf = wp.empty((slab, ny, nx), dtype=float, device=gf.device)
    for z0 in range(0, nz, slab):
        h = min(slab, nz - z0)
        view = buf if h == slab else wp.empty((h, ny, nx), dtype=float, device=gf.device)
        gf.decode_slab(view, z0, wp.vec3(*scale), wp.vec3(*offset))


def run(size: int, n: int, box_edge: int, zoom: int, repeat: int, device: str, argv=None) -> dict:
    wp = warp()
    timer = Timer(device)
    params = bench_primitives(n, (size, size, size), 0.7, 0)
    build_ms = timer.wall_ms(lambda: GaussianField(params, (size,) * 3, device=device), repeat=1, warmup=1)
    gf = GaussianField(params, (size,) * 3, device=device)
    whole_shape = (size,) * 3
    box = centred_box(size, box_edge)
    box_shape = (box_edge * zoom,) * 3
    rows = []
    for name, shape, b in (("whole", whole_shape, None), ("box", box_shape, box)):
        dev_ms = timer.wall_ms(lambda s=shape, bb=b: decode_on_device(gf, s, bb), repeat=repeat, warmup=1)
        host_ms = timer.wall_ms(lambda s=shape, bb=b: gf.decode(s, box=bb), repeat=repeat, warmup=1)
        rows.append({"decode": name, "output_shape": list(shape), "box": None if b is None else [list(p) for p in b],
                     "output_voxels": int(np.prod(shape)), "device_ms": dev_ms, "host_ms": host_ms})  # fmt: skip
    whole = gf.decode(whole_shape)
    (x0, x1), (y0, y1), (z0, z1) = box
    crop_equal = bool(np.array_equal(gf.decode((box_edge,) * 3, box=box), whole[z0:z1, y0:y1, x0:x1]))
    wp.synchronize_device(device)
    w, b = rows
    return {
        **result_header("region decode against the whole decode", __file__, argv, device),
        "size": size,
        "n": n,
        "box_edge": box_edge,
        "zoom": zoom,
        "repeat": repeat,
        "field_build_ms": build_ms,
        "rows": rows,
        "ratio_device": b["device_ms"] / w["device_ms"],
        "ratio_host": b["host_ms"] / w["host_ms"],
        "crop_equal": crop_equal,
        "notes": [
            "device_ms: slabs evaluated into device memory; host_ms: GaussianField.decode, the float32 array on the host",
            "field_build_ms (preparing and binning the N Gaussians) is paid once by either decode and excluded from both",
            "crop_equal: the box at zoom 1 equals the crop of the whole decode bit for bit",
        ],
    }


def format_table(res: dict) -> str:
    lines = [
        f"{res['device_name']} ({res['device']}), Warp {res['warp_version']}: {res['size']}^3 model, N = {res['n']:,}, "
        f"field build {res['field_build_ms']:.1f} ms",
        f"{'decode':<7} {'output':>16} {'voxels':>14} {'device ms':>11} {'host ms':>11}",
    ]
    for r in res["rows"]:
        shape = "x".join(map(str, r["output_shape"]))
        lines.append(f"{r['decode']:<7} {shape:>16} {r['output_voxels']:>14,} {r['device_ms']:>11.2f} {r['host_ms']:>11.2f}")
    lines.append(
        f"box / whole: {100 * res['ratio_device']:.2f} % on the device, {100 * res['ratio_host']:.2f} % with the host copy; "
        f"crop equal: {res['crop_equal']}"
    )
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=1024, help="edge of the model grid (voxels)")
    ap.add_argument("--n", type=int, default=1_400_000, help="Gaussians")
    ap.add_argument("--box", type=int, default=64, help="edge of the box in model voxels")
    ap.add_argument("--zoom", type=int, default=4, help="output voxels per model voxel inside the box")
    ap.add_argument("--repeat", type=int, default=3, help="timed decodes of each")
    ap.add_argument("--device", default=None, help="Warp device (default: CUDA when present)")
    ap.add_argument("--out", default=None, help="JSON path (default: benchmarks/results/decode/region_<size>_n<n>_<device>.json)")
    args = ap.parse_args(argv)
    if not (args.size >= 1 and 1 <= args.box <= args.size and args.zoom >= 1 and args.n >= 1 and args.repeat >= 1):
        ap.error("need size >= 1, 1 <= box <= size, zoom >= 1, n >= 1, repeat >= 1")
    device = resolve_device(args.device)
    res = run(args.size, args.n, args.box, args.zoom, args.repeat, device, argv)
    print(format_table(res))
    out = Path(args.out) if args.out else RESULTS / f"region_{args.size}_n{args.n}_{device.replace(':', '')}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, (json.dumps(res, indent=1) + "\n").encode())
    print(f"wrote {out}")
    return res


if __name__ == "__main__":
    main()
