"""What the pair passes of one iteration would visit, counted on any device (issue #52).

For each saved model (an ``.npz`` with ``params``, as ``benchmarks/accuracy/sweep.py`` keeps them)
and its volume: a refiner on the model, one draw of an iteration's points, and for each setting
of module constants (the point grids' ``ROW_COST``, the cell lists' padding, ...): the list
entries, the candidates the forward pass tests (a point reads its cell's list on every level),
the pairs that contribute, and the candidates and point-cell rows the backward pass walks. The
counts decide the passes' work; they do not time it, so they run on the CPU as well as on a GPU.

    python benchmarks/speed/pair_counts.py --case mni_icbm152.npy=/work/models/mni_icbm152_cr10.npz \\
        --samples 131072 --set warpgauss.field.gaussians.ROW_COST:64,16 --out OUT.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header

try:
    from iteration_floor import settings_of  # run as a script: benchmarks/speed is on the path
    from profile_encode import _apply
except ImportError:  # imported as a module
    from .iteration_floor import settings_of
    from .profile_encode import _apply


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--case", action="append", required=True, help="VOLUME.npy=MODEL.npz[@SAMPLES]; repeat for more")
    ap.add_argument("--samples", type=int, default=131_072, help="points an iteration where a case names none")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        help="module.CONST:v1,v2: count at each value (the others as they are); "
        "set:module.A=v;module.B=w: several at once; repeat for more",
    )
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    dev = resolve_device(args.device)
    res = {**result_header("pair pass counts of one iteration", __file__, argv, dev), "rows": []}
    for case in args.case:
        vol, _, rest = case.partition("=")
        model, _, samples = rest.partition("@")
        r = _refiner(vol, model, int(samples or args.samples), args.seed, dev)
        row = {"volume": Path(vol).name, "model": Path(model).name, "n": r.n, "points": r.passes.n_points, "settings": {}}
        row["settings"]["default"] = _counts(r)
        for spec in args.set:
            name = "" if spec.startswith("set:") else spec.partition(":")[0].rsplit(".", 1)[-1] + "="
            for value, setting in settings_of(spec).items():
                label = name + value
                saved = _apply(setting)
                try:
                    row["settings"][label] = _counts(r)
                finally:
                    _apply(saved)
        for label, c in row["settings"].items():
            print(row["volume"], row["model"], label, json.dumps(c))
        res["rows"].append(row)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


def _refiner(vol: str, model: str, samples: int, seed: int, dev: str):
    """A refiner on a saved model and its volume, the default configuration at ``samples`` points."""
    from warpgauss.encoding.allocate import AllocationConfig
    from warpgauss.encoding.refine import RefineConfig, Refiner
    from warpgauss.field.analysis import DeviceVolume, normalise

    f = normalise(np.load(vol))
    params = np.load(model)["params"].astype(np.float32)
    ac = AllocationConfig()
    dv = DeviceVolume(f, dev)
    cfg = RefineConfig(samples=samples, auto_samples=False)
    return Refiner(dv, params, cfg, seed, ac.scale_min, ac.resolved_cap(f.shape_xyz))


def _counts(r) -> dict:
    """One draw's counts on the current constants (the point grids re-planned, the lists re-indexed)."""
    from warpgauss.kernels import chunked as kc

    wp, p = warp(), r.passes
    t = time.perf_counter()
    p.list_inputs_from_state()
    p.invalidate()
    r._graph = None
    r.sample()
    b = p.buffers()
    m2 = p.n_points
    r.forward()  # sorts the points on the point grids (the lists' forward pass where lists fit)
    pts = np.diff(b["grid"].start.numpy().astype(np.int64))
    out = {
        "point_cells": [round(float(s), 3) for s in b["grid_plan"].sizes[:-1]],
        "cells": int(b["grid_plan"].total_cells),
        "listed": bool(p.listed),
        "list_entries": int(p.list_entries),
        "pairs": int(r.pairs.numpy()[:m2].astype(np.int64).sum()),
    }
    if p.listed:
        lens = np.diff(b["lists"].start.numpy().astype(np.int64))
        out["forward_candidates"] = int((pts * lens[: pts.size]).sum())
    n, st = r.n, r.state
    wp.launch(kc.pair_work, dim=n, inputs=[st.slot_cell, st.prims, b["grid"], 1], outputs=[b["work"], b["rows"]], device=r.device)
    out["backward_candidates"] = int(b["work"].numpy().astype(np.int64).sum())
    out["backward_rows"] = int(b["rows"].numpy().astype(np.int64).sum())
    out["count_s"] = round(time.perf_counter() - t, 2)
    return out


if __name__ == "__main__":
    main()
