"""Rate-distortion benchmark (issue #8 part 3): warpgauss against SZ3 and ZFP.

For each volume (the built-in example fields generated at ``--size``, and the real volumes in
``../shared/data`` when present) this measures PSNR against compression ratio, plus encode and
decode seconds, for:

- ``wg-full``: warpgauss, full-precision file (48 N + H bytes), one model per budget of a ladder
  (one read and one S1a analysis for the whole ladder, as ``encode --ladder``);
- ``wg-compact``: the same models saved with ``compact=True`` (12 N + H), reloaded and decoded;
- ``sz3-matched``: SZ3 (PyPI ``pysz``), absolute error bound bisected until its ratio is within
  ``--match-tol`` of each warpgauss full-precision ratio; ``sz3``: SZ3 at a few error bounds;
- ``zfp-rate`` (fixed rate, bits/value), ``zfp-rate-matched`` (the rate giving each warpgauss
  ratio) and ``zfp-acc`` (fixed accuracy, absolute tolerance), PyPI ``zfpy``.

Every codec is scored by the same function: PSNR = 10 log10(1 / MSE) on the FULL grid, values
normalised to [0, 1] by the volume's finite min/max (warpgauss's normalisation), masked voxels
excluded. Ratio = source bytes (voxels x source dtype size, warpgauss's definition) / compressed
bytes for every codec; SZ3 and ZFP compress the float32 volume. Encode seconds exclude reading
the volume (stage P) and evaluation; warpgauss's include analysis (S1a, shared by the ladder but
counted in every row), allocation and refinement (with the one-off self-test in the first row).
Decode seconds: the full-grid decode (warpgauss: ``Model.decode``; compact: load + decode).

The JSON is rewritten atomically after every row, so a run that is stopped keeps what it measured.

    python benchmarks/bench_rd.py --size 128 --budgets 1000,4000,16000 --preset fast \\
        --real nAChR_M2_water.plt,1jzv.ccp4 --out benchmarks/results/rd_cpu_128.json
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss._warp import device_name, resolve_device, warp
from warpgauss.allocate import AllocationConfig
from warpgauss.analysis import seed_limit
from warpgauss.model import Model
from warpgauss.pipeline import EncodeOptions, ReadOptions, encode_field, load_field, resolve_refine
from warpgauss.profiling import StageRecorder
from warpgauss.synthetic import EXAMPLES, generate

DATA_DIR = Path(__file__).resolve().parents[2] / "shared" / "data"
SZ3_BOUNDS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 1e-4)  # x (max - min)
ZFP_RATES = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)  # bits per value
ZFP_MIN_RATE = 0.25  # the lowest fixed rate run (see bench_volume)
ZFP_TOLERANCES = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 1e-4)  # x (max - min)


# ---------------------------------------------------------------------------- scoring


class Truth:
    """The reference every codec is scored against: normalised float64 values and the valid set."""

    def __init__(self, raw: np.ndarray, vmin: float, vmax: float, valid: np.ndarray | None):
        self.vmin, self.vmax = float(vmin), float(vmax)
        self.valid = valid
        self.norm = (raw.astype(np.float64) - self.vmin) / (self.vmax - self.vmin)
        # what SZ3 and ZFP compress: float32 in source units, masked voxels set to the minimum
        self.codec_input = np.ascontiguousarray(raw, dtype=np.float32)
        if valid is not None:
            self.codec_input = np.where(valid, self.codec_input, np.float32(self.vmin)).astype(np.float32)

    def psnr(self, recon: np.ndarray, normalised: bool = False) -> float:
        """PSNR (dB) of a full-grid reconstruction (source units, or [0, 1] with ``normalised``)."""
        r = recon.astype(np.float64)
        if not normalised:
            r = (r - self.vmin) / (self.vmax - self.vmin)
        err = r - self.norm
        if self.valid is not None:
            err = err[self.valid]
        mse = float(np.mean(err * err))
        return float(10.0 * math.log10(1.0 / max(mse, 1e-20)))


# ---------------------------------------------------------------------------- codecs


def sz3_run(data: np.ndarray, eb: float):
    """SZ3 absolute error bound ``eb``: (compressed bytes, decoded array, encode s, decode s)."""
    from pysz import sz, szConfig, szErrorBoundMode

    conf = szConfig()
    conf.errorBoundMode = szErrorBoundMode.ABS
    conf.absErrorBound = float(eb)
    t0 = time.perf_counter()
    comp, _ = sz.compress(data, conf)
    t1 = time.perf_counter()
    dec, _ = sz.decompress(comp, np.float32, data.shape)
    t2 = time.perf_counter()
    return int(comp.nbytes), dec.reshape(data.shape), t1 - t0, t2 - t1


def zfp_run(data: np.ndarray, **mode):
    """ZFP (``rate=`` bits/value or ``tolerance=``): (bytes, decoded array, encode s, decode s)."""
    import zfpy

    t0 = time.perf_counter()
    comp = zfpy.compress_numpy(data, **mode)
    t1 = time.perf_counter()
    dec = zfpy.decompress_numpy(comp)
    t2 = time.perf_counter()
    return len(comp), dec.reshape(data.shape), t1 - t0, t2 - t1


def sz3_matched(data: np.ndarray, source_bytes: int, target: float, rng: float, tol: float, max_steps: int = 40):
    """Bisect SZ3's absolute error bound (log scale) until its ratio is within ``tol`` of ``target``.

    Returns (eb, nbytes, decoded, enc_s, dec_s, steps, reached)."""
    lo, hi = 1e-9 * rng, 2.0 * rng
    best = None
    for step in range(1, max_steps + 1):
        eb = math.sqrt(lo * hi)
        nbytes, dec, te, td = sz3_run(data, eb)
        ratio = source_bytes / nbytes
        if best is None or abs(math.log(ratio / target)) < abs(math.log(best[1] / target)):
            best = (eb, ratio, nbytes, dec, te, td, step)
        if abs(ratio / target - 1.0) <= tol:
            break
        if ratio < target:
            lo = eb
        else:
            hi = eb
        if hi / lo < 1.0 + 1e-6:
            break
    eb, ratio, nbytes, dec, te, td, step = best
    return eb, nbytes, dec, te, td, step, abs(ratio / target - 1.0) <= tol


# ---------------------------------------------------------------------------- volumes


def volumes(args):
    """(label, load_field source kwargs, raw array in source units) for each requested volume."""
    from warpgauss.io import read_volume

    for name in [x for x in args.fields.split(",") if x]:
        raw = generate(name, args.size, seed=0)
        yield f"{name} {args.size}^3", {"source": raw}, raw
    real = args.real
    if real in ("", "none") or not DATA_DIR.is_dir():
        return
    names = sorted(p.name for p in DATA_DIR.iterdir() if p.name != "README.md") if real == "all" else real.split(",")
    for fname in names:
        path = DATA_DIR / fname
        if not path.is_file():
            print(f"skip {fname}: not in {DATA_DIR}", flush=True)
            continue
        stride = 1
        vol = read_volume(path)
        while np.prod(vol.data.shape) / stride**3 > args.max_voxels:
            stride += 1
        raw = vol.data[::stride, ::stride, ::stride]
        shape = "x".join(str(s) for s in raw.shape[::-1])
        yield f"{fname} {shape}" + (f" (stride {stride})" if stride > 1 else ""), {
            "source": str(path),
            "read": ReadOptions(stride=stride),
        }, raw


# ---------------------------------------------------------------------------- benchmark


def _write(result: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=str) + "\n")
    os.replace(tmp, out)


def _print(label: str, row: dict) -> None:
    print(
        f"{label[:34]:34s} {row['codec']:17s} {row['param']:>16s}  ratio {row['ratio']:9.2f}  "
        f"PSNR {row['psnr_db']:7.2f} dB  enc {row['encode_s']:8.3f} s  dec {row['decode_s']:7.3f} s",
        flush=True,
    )


def _available(module: str) -> str | None:
    try:
        from importlib.metadata import version

        __import__(module)
        return version({"pysz": "pysz", "zfpy": "zfpy"}[module])
    except Exception:  # noqa: BLE001 - not installed (or broken): the codec is skipped
        return None


def bench_volume(label, src, raw, args, dev, result, out):
    entry = {"rows": []}
    result["volumes"][label] = entry

    def add(row):
        entry["rows"].append(row)
        _print(label, row)
        _write(result, out)

    t0 = time.perf_counter()
    f, info = load_field(src["source"], src.get("read"))
    load_s = time.perf_counter() - t0
    truth = Truth(raw, f.vmin, f.vmax, f.mask)
    n_max = seed_limit(f.eligible, f.occupied)
    entry.update(
        {
            "shape_xyz": list(f.shape_xyz),
            "source_dtype": f.source_dtype,
            "source_bytes": f.source_bytes,
            "stride": info["stride"],
            "value_range": [f.vmin, f.vmax],
            "masked_voxels": info["masked_voxels"],
            "n_max": n_max,
            "load_seconds": load_s,
        }
    )
    sb = f.source_bytes
    rng = f.vmax - f.vmin

    # warpgauss: one model per budget, the volume read and analysed once
    refine = resolve_refine(None, args.preset, args.iterations, None)
    budgets = sorted({b for b in args.budgets if b <= n_max})
    cache: dict = {}
    wg_ratios = []
    for i, n in enumerate(budgets):
        opts = EncodeOptions(budget=n, seed=0, allocation=AllocationConfig(), refine=refine, self_test=i == 0)
        timer = StageRecorder()
        model = encode_field(f, opts, device=dev, timer=timer, input_info=info, evaluate=False, cache=cache)
        stages = {s.name: s.seconds for s in timer.stages}
        enc = sum(stages.values()) + (cache["seconds"] if "S1a" not in stages else 0.0)
        if model.compression_ratio(False) < args.min_ratio:
            print(f"{label}: budget {n} gives ratio {model.compression_ratio(False):.2f} < {args.min_ratio}: skipped", flush=True)
            continue
        ref = model.report["refinement"]
        t0 = time.perf_counter()
        dec = model.decode(device=dev, normalised=True)
        dec_s = time.perf_counter() - t0
        common = {"n": n, "iterations": ref.get("iterations_done", 0), "samples": ref.get("samples"), "stages": stages}
        add(
            {
                "codec": "wg-full",
                "param": f"N={n}",
                "ratio": model.compression_ratio(False),
                "bytes": model.file_size(False),
                "psnr_db": truth.psnr(dec, normalised=True),
                "encode_s": enc,
                "decode_s": dec_s,
                **common,
            }
        )
        wg_ratios.append((n, model.compression_ratio(False)))
        del dec
        with tempfile.TemporaryDirectory() as td:
            p = Path(td) / "m.wgs"
            t0 = time.perf_counter()
            nbytes = model.save(p, compact=True)
            save_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            cm = Model.load(p)
            dec = cm.decode(device=dev, normalised=True)
            dec_s = time.perf_counter() - t0
        assert nbytes == model.file_size(True), (nbytes, model.file_size(True))
        add(
            {
                "codec": "wg-compact",
                "param": f"N={n}",
                "ratio": sb / nbytes,
                "bytes": nbytes,
                "psnr_db": truth.psnr(dec, normalised=True),
                "encode_s": enc + save_s,
                "decode_s": dec_s,
                **common,
            }
        )
        del dec
        if "sz3" in args.codecs:
            for target_name, target in (("full", model.compression_ratio(False)), ("compact", sb / nbytes)):
                if target_name == "compact" and not args.match_compact:
                    continue
                eb, cb, d, te, tdec, steps, ok = sz3_matched(truth.codec_input, sb, target, rng, args.match_tol)
                add(
                    {
                        "codec": "sz3-matched",
                        "param": f"eb={eb / rng:.3g}R",
                        "ratio": sb / cb,
                        "bytes": cb,
                        "psnr_db": truth.psnr(d),
                        "encode_s": te,
                        "decode_s": tdec,
                        "abs_error_bound": eb,
                        "matched_to": {"n": n, "format": target_name, "ratio": target, "within_tol": ok, "bisection_steps": steps},
                    }
                )
        if "zfp" in args.codecs:
            for target_name, target in (("full", model.compression_ratio(False)), ("compact", sb / nbytes)):
                rate = 8.0 * sb / (f.n_voxels * target)
                if rate < ZFP_MIN_RATE:  # zfpy 1.0.1 corrupts the heap (malloc abort) at 0.107 bits/value
                    print(f"{label}: zfp rate {rate:.3g} < {ZFP_MIN_RATE} bits/value: not run", flush=True)
                    continue
                try:
                    cb, d, te, tdec = zfp_run(truth.codec_input, rate=rate)
                except Exception as e:  # noqa: BLE001 - a rate zfp refuses: recorded, not fatal
                    print(f"{label}: zfp rate {rate:.4g} failed: {e}", flush=True)
                    continue
                add(
                    {
                        "codec": "zfp-rate-matched",
                        "param": f"rate={rate:.3g}",
                        "ratio": sb / cb,
                        "bytes": cb,
                        "psnr_db": truth.psnr(d),
                        "encode_s": te,
                        "decode_s": tdec,
                        "rate_bits_per_value": rate,
                        "matched_to": {"n": n, "format": target_name, "ratio": target},
                    }
                )
        del model
    entry["warpgauss_budgets"] = budgets

    # the reference codecs' own curves
    data = truth.codec_input
    if "sz3" in args.codecs:
        for rel in SZ3_BOUNDS:
            cb, d, te, tdec = sz3_run(data, rel * rng)
            add({"codec": "sz3", "param": f"eb={rel:g}R", "ratio": sb / cb, "bytes": cb, "psnr_db": truth.psnr(d), "encode_s": te, "decode_s": tdec, "abs_error_bound": rel * rng})
    if "zfp" in args.codecs:
        for rate in ZFP_RATES:
            cb, d, te, tdec = zfp_run(data, rate=rate)
            add({"codec": "zfp-rate", "param": f"rate={rate:g}", "ratio": sb / cb, "bytes": cb, "psnr_db": truth.psnr(d), "encode_s": te, "decode_s": tdec, "rate_bits_per_value": rate})
        for rel in ZFP_TOLERANCES:
            cb, d, te, tdec = zfp_run(data, tolerance=rel * rng)
            add({"codec": "zfp-acc", "param": f"tol={rel:g}R", "ratio": sb / cb, "bytes": cb, "psnr_db": truth.psnr(d), "encode_s": te, "decode_s": tdec, "tolerance": rel * rng})
    return entry


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fields", default=",".join(EXAMPLES), help="example fields (comma list; '' for none)")
    ap.add_argument("--size", type=int, default=256, help="example field size (cube edge)")
    ap.add_argument("--real", default="all", help="files in ../shared/data: 'all', a comma list, or 'none'")
    ap.add_argument("--max-voxels", type=int, default=256**3, help="stride real volumes down to at most this many voxels")
    ap.add_argument("--budgets", default="2000,8000,32000,128000", help="warpgauss ladder (capped at each volume's N_max)")
    ap.add_argument("--min-ratio", type=float, default=2.0, help="drop budgets whose full-precision ratio is below this")
    ap.add_argument("--preset", default="fast", help="warpgauss refinement preset (fast: 300 x 3,072)")
    ap.add_argument("--iterations", type=int, default=None, help="override the preset's iterations (0: analytic)")
    ap.add_argument("--codecs", default="sz3,zfp", help="reference codecs to run (those not installed are skipped)")
    ap.add_argument("--match-tol", type=float, default=0.02, help="relative ratio tolerance of the SZ3 bisection")
    ap.add_argument("--match-compact", action="store_true", help="also match SZ3 to the compact ratios")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="benchmarks/results/rd_cpu.json")
    args = ap.parse_args(argv)
    args.budgets = [int(b) for b in args.budgets.split(",") if b]
    versions = {"pysz": _available("pysz"), "zfpy": _available("zfpy")}
    wanted = [c for c in args.codecs.split(",") if c]
    args.codecs = [c for c in wanted if versions[{"sz3": "pysz", "zfp": "zfpy"}[c]]]
    for c in set(wanted) - set(args.codecs):
        print(f"{c}: not installed (pip install -e '.[bench]'): skipped", flush=True)

    wp = warp()
    dev = resolve_device(args.device)
    t0 = time.perf_counter()
    warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64)  # compile kernels
    warm = time.perf_counter() - t0
    refine = resolve_refine(None, args.preset, args.iterations, None)
    out = Path(args.out)
    result = {
        "benchmark": "rate-distortion: warpgauss (full precision, compact) vs SZ3 (abs error bound) vs ZFP (fixed rate, fixed accuracy)",
        "command": "python benchmarks/bench_rd.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "device": dev,
        "device_name": device_name(dev),
        "cpu_count": os.cpu_count(),
        "host": platform.node(),
        "warp_version": wp.config.version,
        "warpgauss_version": warpgauss.__version__,
        "codec_versions": versions,
        "numpy_version": np.__version__,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "warmup_seconds": warm,
        "settings": {
            "preset": args.preset,
            "iterations": refine.iterations,
            "samples": refine.samples,
            "budgets": args.budgets,
            "min_ratio": args.min_ratio,
            "match_tol": args.match_tol,
            "psnr": "10 log10(1/MSE), full grid, normalised by the volume's finite min/max, masked voxels excluded; same function for every codec",
            "ratio": "source bytes (voxels x source dtype size) / compressed bytes; SZ3 and ZFP compress float32",
        },
        "volumes": {},
        "complete": False,
    }
    for label, src, raw in volumes(args):
        bench_volume(label, src, raw, args, dev, result, out)
    result["complete"] = True
    _write(result, out)
    print(f"\n{result['device_name']}, Warp {result['warp_version']}, pysz {versions['pysz']}, zfpy {versions['zfpy']} -> {out}")
    return result


if __name__ == "__main__":
    main()
