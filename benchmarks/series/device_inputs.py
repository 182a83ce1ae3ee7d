"""Device arrays into warpgauss.encode with no host copy (issue #21 part 3), on a GPU: a Warp array,
a PyTorch tensor (DLPack), a CuPy array (DLPack) and an object offering only
``__cuda_array_interface__``, each encoded as its numpy copy is (same model, bit for bit), and the
per-call cost an Encoder pays outside refinement, cold and warm.

    python benchmarks/series/device_inputs.py --size 256 --budget 100000 --out $OUT/device_inputs_h100.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header
from warpgauss.readers.synthetic import generate_series


class CudaArrayOnly:
    """Offers only ``__cuda_array_interface__`` (as a Numba device array does)."""

    def __init__(self, owner):
        self.owner = owner
        self.__cuda_array_interface__ = owner.__cuda_array_interface__


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--budget", type=int, default=100_000)
    ap.add_argument("--calls", type=int, default=4)
    ap.add_argument("--time-budget", type=float, default=1.0)
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    vols = list(generate_series("vortex", args.size, args.calls))
    kw = dict(budget=args.budget, iterations=100, format="full", device=dev)
    ref = warpgauss.encode(vols[0], **kw)
    inputs = {"warp": lambda v: wp.array(v, device=dev)}
    try:
        import torch

        inputs["torch (DLPack)"] = lambda v: torch.from_numpy(v).to(dev)
    except ImportError:
        pass
    try:
        import cupy

        inputs["cupy (DLPack)"] = lambda v: cupy.asarray(v)
        inputs["__cuda_array_interface__ only"] = lambda v: CudaArrayOnly(cupy.asarray(v))
    except ImportError:
        pass
    result = {
        **result_header("device arrays into encode (no host copy) and the Encoder's per-call cost", __file__, argv, dev),
        "size": args.size,
        "budget": args.budget,
        "inputs": [],
        "encoder_calls": [],
    }
    for name, make in inputs.items():
        m = warpgauss.encode(make(vols[0]), **kw)
        same = bool(np.array_equal(m.params, ref.params))
        stage_p = sum(s["seconds"] for s in m.report["stages"] if s["stage"] == "P")
        result["inputs"].append({"input": name, "same_model_as_numpy": same, "stage_p_seconds": stage_p, "psnr_db": m.report["psnr_db"]})
        print(f"{name:32s} same model as numpy: {same}  stage P {1000 * stage_p:.1f} ms")
    ref_p = sum(s["seconds"] for s in ref.report["stages"] if s["stage"] == "P")
    result["numpy_stage_p_seconds"] = ref_p
    print(f"{'numpy (host copy)':32s} stage P {1000 * ref_p:.1f} ms")
    enc = warpgauss.Encoder(budget=args.budget, format="full", device=dev, time_budget=args.time_budget)
    enc.prepare()
    for v in vols:
        m = enc.encode(wp.array(v, device=dev))
        e = m.report["encoder"]
        rec = {**e, "psnr_db": m.report["psnr_db"], "stages": enc.calls[-1].stages}
        result["encoder_calls"].append(rec)
        print(
            f"call {e['call']} ({'warm' if e['warm_start'] else 'cold'}): {e['seconds']:.3f} s of {e['time_budget']} s, "
            f"fixed {e['fixed_seconds']:.3f} s, {e['iterations']} iterations, PSNR {m.report['psnr_db']:.2f}  "
            + " ".join(f"{k} {1000 * x:.0f}ms" for k, x in enc.calls[-1].stages.items())
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
