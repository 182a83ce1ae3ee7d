"""Where a default encode's time goes, by stage and by kernel (issue #52).

For each volume and ratio: one default encode timed by the wall clock (after a warm-up encode that
compiles every module), its report's stages, then the same encode with the refiner's graph off
under Warp's activity timing (GPU time of every kernel, summed over the encode, grouped by name).

    python benchmarks/speed/profile_encode.py --volumes ../shared/data/mean_reg2mean.nii.gz --ratios 100 --out OUT.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections import defaultdict
from pathlib import Path

import warpgauss
from warpgauss.core.warp import resolve_device, warp
from warpgauss.encoding.bench import result_header
from warpgauss.encoding.refine import RefineConfig
from warpgauss.readers.synthetic import generate


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--volumes", default="../shared/data/mean_reg2mean.nii.gz")
    ap.add_argument("--ratios", default="100")
    ap.add_argument("--device", default=None)
    ap.add_argument("--kernels", type=int, default=1, help="1: also the per-kernel encode (graph off)")
    ap.add_argument(
        "--variants",
        default="default",
        help="default, nolists (RefineConfig(cell_lists=False)), fast (--preset fast), it300 (the default's "
        "sampling at 300 iterations), nograph (the refiner's CUDA graph off), comma-separated; NAME+field=value+... "
        "sets RefineConfig fields on variant NAME (e.g. it300+lr=0.016); budgetT: the defaults with --time-budget T "
        "(seconds, e.g. budget1.5: the whole encode's wall time against its promise)",
    )
    ap.add_argument(
        "--patch",
        action="append",
        default=[],
        help="NAME=module.CONST:value[+module.CONST:value]: a variant NAME (list it in --variants) that runs the "
        "default encode with module constants set (e.g. rc4=warpgauss.field.gaussians.ROW_COST:4); restored after it",
    )
    ap.add_argument("--volume-on-host", metavar="MEM", help="every encode with --volume-on-host --max-device-memory MEM")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    wp = warp()
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 32), ratio=10, device=dev, evaluate=True)
    res = {
        **result_header("a default encode by stage and by kernel", __file__, argv, dev),
        "compile_s": time.perf_counter() - t0,
        "rows": [],
    }
    patches = _patches(args.patch)
    variants, budgets = _variants(args.variants.split(","), patches)
    examples: dict[str, object] = {}

    def source(vol: str):
        """A path, or NAME@SIZE: a built-in example field (generated once)."""
        if "@" not in vol:
            return vol
        if vol not in examples:
            name, size = vol.split("@")
            examples[vol] = generate(name, int(size), seed=0)
        return examples[vol]

    for vol, ratio, variant in [
        (v, float(r), x) for v in args.volumes.split(",") for r in args.ratios.split(",") for x in args.variants.split(",")
    ]:
        if True:
            rc = variants[variant]
            saved = _apply(patches.get(variant, {}))
            src = source(vol)  # an example field is generated before the clock starts (a file is read within it)
            wp.synchronize()
            t = time.perf_counter()
            how = {"preset": variant} if rc is None else {"time_budget": budgets[variant]} if variant in budgets else {"refine": rc}
            if args.volume_on_host:
                how.update(volume_on_host=True, max_device_memory=args.volume_on_host)
            m = warpgauss.encode(src, ratio=ratio, device=dev, **how)
            wall = time.perf_counter() - t
            rep = m.report
            row = {
                "volume": Path(vol).name,
                "ratio": ratio,
                "variant": variant,
                "patch": {k: v for k, v in patches.get(variant, {}).items()},
                "wall_s": wall,
                "time_budget_s": budgets.get(variant),
                "total_s": rep.get("total_seconds"),
                "n": m.n,
                "psnr_db": rep["evaluation"]["final"]["psnr_db"],
                "analytic_psnr_db": rep["evaluation"].get("analytic", {}).get("psnr_db"),
                "stages": {s["stage"]: round(s["seconds"], 4) for s in rep["stages"]},
                "refinement": {k: v for k, v in (rep.get("refinement") or {}).items() if isinstance(v, (int, float, str))},
                **{
                    key: {
                        k: v for k, v in (rep.get(key) or rep.get("budget", {}).get(key) or {}).items() if isinstance(v, (int, float, str))
                    }
                    for key in ("coded_fit", "coded_replan")
                },
            }
            print(
                f"{row['volume']} CR {ratio} {variant}: {wall:.2f} s, N {m.n}, {row['psnr_db']:.2f} dB, {row['refinement'].get('forward_pass')}, deferred {row['refinement'].get('deferred_updates')}"
            )
            print("  stages", row["stages"], "fit", row["coded_fit"].get("seconds"), "replan", row["coded_replan"].get("seconds"))
            if args.kernels and rc is not None:
                cfg = dataclasses.replace(rc, graph=False)
                wp.synchronize()
                wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
                t = time.perf_counter()
                warpgauss.encode(source(vol), ratio=ratio, device=dev, **{**how, "refine": cfg})
                row["kernels_wall_s"] = time.perf_counter() - t
                per = defaultdict(lambda: [0.0, 0])
                for r in wp.timing_end():
                    name = r.name.rsplit("_", 1)[0] if r.name.startswith("forward kernel") else r.name
                    per[name][0] += r.elapsed / 1000.0
                    per[name][1] += 1
                top = sorted(per.items(), key=lambda kv: -kv[1][0])
                row["kernel_s_total"] = sum(v[0] for v in per.values())
                row["kernel_s"] = {k: [round(v[0], 4), v[1]] for k, v in top}
                print(f"  kernels total {row['kernel_s_total']:.3f} s of {row['kernels_wall_s']:.2f} s wall")
                for k, v in top[: args.top]:
                    print(f"    {v[0]:8.4f} s {v[1]:7d}x  {k}")
            _apply(saved)
            res["rows"].append(row)
    Path(args.out).write_text(json.dumps(res, indent=1))
    return res


def _variants(names: list[str], patches: dict) -> tuple[dict, dict[str, float]]:
    """(variant name -> RefineConfig, or None for ``--preset fast``; budgetT name -> T seconds)."""
    variants = {
        "default": RefineConfig(),
        "nolists": RefineConfig(cell_lists=False),
        "fast": None,
        "it300": RefineConfig(iterations=300),
        "nograph": RefineConfig(graph=False),
    }
    variants.update({name: RefineConfig() for name in patches})
    budgets = {name: float(name[len("budget") :]) for name in names if name.startswith("budget")}
    variants.update({name: RefineConfig() for name in budgets})
    for name in names:  # NAME+field=value+...: RefineConfig fields on a listed variant
        if "+" in name and name not in variants:
            base, *sets = name.split("+")
            fields = {k: float(v) if "." in v or "e" in v else int(v) for k, v in (x.split("=") for x in sets)}
            variants[name] = dataclasses.replace(variants[base] or RefineConfig(), **fields)
    return variants, budgets


def _patches(specs: list[str]) -> dict[str, dict[str, float]]:
    """--patch NAME=module.CONST:value+...: variant name -> {"module.CONST": value}."""
    out: dict[str, dict[str, float]] = {}
    for spec in specs:
        name, _, rest = spec.partition("=")
        out[name] = {k: float(v) for k, v in (item.rsplit(":", 1) for item in rest.split("+"))}
    return out


def _apply(values: dict[str, float]) -> dict[str, float]:
    """Set module constants ("module.CONST" -> value); returns the values they had."""
    import importlib

    old = {}
    for key, value in values.items():
        mod, const = key.rsplit(".", 1)
        m = importlib.import_module(mod)
        old[key] = getattr(m, const)
        setattr(m, const, type(old[key])(value))
    return old


if __name__ == "__main__":
    main()
