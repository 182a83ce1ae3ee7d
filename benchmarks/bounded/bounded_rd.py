"""Bounded encodes (issue #36): compression ratio and PSNR at point-wise bounds of 1e-2, 1e-3 and
1e-4 of the range, the Gaussians as predictor plus the residual, against SZ3 at the same bound.

For each volume (the three head/brain MRIs of ../shared/data, as .npz copies under
benchmarks/build/rdvol, and example fields at --size): one model per Gaussian ratio
(``--gaussian-ratios``), its float64 prediction, then the residual at every bound; and the
residual with no Gaussians at all (the 3D Lorenzo predictor alone, ``gaussian_ratio`` None).
Rows: ``volume``, ``bound_rel``, ``gaussian_ratio``, ``ratio`` (source bytes over the whole
file), ``psnr_db``, ``max_abs_error`` (checked <= bound), the predictor chosen, the sizes every
predictor gave, encode / predict / code / decode seconds. SZ3's ratio and PSNR at the same
absolute bound come from ``benchmarks/results/rate_distortion/bench_rd_codecs_cpu.json`` (pysz 1.1.0, one CPU core,
the float32 volume), where it holds the volume at this size.

``--export K`` saves each example field's model at K^3 (with a residual at 1e-4) and its float64
prediction beside ``--out``; ``--check-predictions FOLDER``, run where Warp has a CPU device, predicts
them again there: the largest CPU/CUDA difference against the margin the residual keeps, and the
bounded decode on both (each within the bound; the same values).

    python benchmarks/bounded/bounded_rd.py --size 256 --export 96 --out $OUT/bounded_rd.json
    python benchmarks/bounded/bounded_rd.py --check-predictions FOLDER --out FOLDER/devices.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header
from warpgauss.field.evaluate import psnr_from_mse
from warpgauss.format import residual as R
from warpgauss.readers.lazy import valid_mask
from warpgauss.readers.synthetic import generate

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
MRIS = ("mean_reg2mean.nii.gz", "mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz", "inia19-t1-brain.nii.gz")


def volumes(size: int, fields: list[str], mris: list[str]):
    for name in mris:
        p = ROOT / "benchmarks" / "build" / "rdvol" / f"{name}.npz"
        if p.is_file():
            yield name, np.load(p)["data"]
        else:
            print(f"skipped {name}: {p} not there (copy it from ../shared/data as benchmarks/rate_distortion/bench_rd.py does)")
    for f in fields:
        yield f"{f} {size}^3", generate(f, size, seed=0)


def sz3_rows(name: str, shape_zyx) -> dict[float, dict]:
    """SZ3 at bounds (share of the range) from the codec sweep, where it holds this volume at this size."""
    p = ROOT / "benchmarks" / "results" / "rate_distortion/bench_rd_codecs_cpu.json"
    if not p.is_file():
        return {}
    vols = json.loads(p.read_text())["volumes"]
    for key, v in vols.items():
        if key.split(" ")[0] == name.split(" ")[0] and tuple(v["shape_xyz"]) == tuple(reversed(shape_zyx)):
            return {
                float(r["param"].split("=")[1].rstrip("R")): {"ratio": r["ratio"], "psnr_db": r["psnr_db"]}
                for r in v["rows"]
                if r["codec"] == "sz3"
            }
    return {}


def bounded_rows(name: str, data: np.ndarray, ratios: list[float], bounds: list[float], dev: str, log) -> list[dict]:
    valid = valid_mask(data, None)
    x = data.astype(np.float64)
    lo, hi = float(x[valid].min()), float(x[valid].max())
    source_bytes = data.nbytes
    sz3 = sz3_rows(name, data.shape)
    rows = []
    for gr in [None, *ratios]:
        t0 = time.perf_counter()
        m = None
        if gr is None:
            pred, fragile, gbytes, model_psnr, enc_s = np.full(data.shape, lo), np.zeros(data.shape, bool), 0, None, 0.0
            predictors: tuple[str, ...] = ("interp", "interp-linear")
            pred_s = 0.0
        else:
            m = warpgauss.encode(data, ratio=gr, device=dev, evaluate=True, full_eval=True)
            enc_s = time.perf_counter() - t0
            gbytes = m.file_size(encoding="coded")
            model_psnr = m.run_report["evaluation"]["final"]["psnr_db"]
            t1 = time.perf_counter()
            pred, fragile = R.prediction(m, dev)
            pred_s = time.perf_counter() - t1
            predictors = R.PREDICTORS
        for rel in bounds:
            bound = rel * (hi - lo)
            t2 = time.perf_counter()
            res, facts = R.code_residual(data, None, pred, fragile, bound, (lo, hi), predictors=predictors)
            code_s = time.perf_counter() - t2
            t3 = time.perf_counter()
            out = R.apply_residual(res, pred)
            apply_s = time.perf_counter() - t3
            err = out.astype(np.float64) - x
            worst = float(np.abs(err[valid]).max())
            assert worst <= bound, (name, rel, gr, worst, bound)
            if m is None:  # the residual alone: no file holds it; its bytes and a header of about a block
                total = res.nbytes + 4096
            else:  # the file as written: Gaussians, residual and the header that describes both
                m.residual = res
                total = m.file_size(encoding="coded")
                m.residual = None
            row = {
                "volume": name,
                "shape_zyx": list(data.shape),
                "source_dtype": str(data.dtype),
                "bound_rel": rel,
                "bound": bound,
                "gaussian_ratio": gr,
                "gaussian_bytes": gbytes,
                "gaussian_psnr_db": model_psnr,
                "residual_bytes": res.nbytes,
                "file_bytes": total,
                "ratio": source_bytes / total,
                "psnr_db": psnr_from_mse(float(np.mean((err[valid] / (hi - lo)) ** 2))),
                "max_abs_error": worst,
                "predictor": facts["predictor"],
                "sizes": facts["sizes"],
                "literals": facts["literals"],
                "fragile": facts["fragile"],
                "decoded_dtype": str(out.dtype),
                "encode_s": enc_s,
                "predict_s": pred_s,
                "code_s": code_s,
                "decode_s": pred_s + apply_s,
                "sz3": sz3.get(rel),
            }
            rows.append(row)
            s = row["sz3"]
            log(
                f"{name:>28} {rel:7.0e} G{'-' if gr is None else int(gr):>5} ratio {row['ratio']:8.2f} PSNR {row['psnr_db']:6.2f} "
                f"({facts['predictor']}, G {gbytes} B + R {res.nbytes} B, lit {facts['literals']})"
                + (f"  SZ3 {s['ratio']:.2f} / {s['psnr_db']:.2f} dB" if s else "")
                + f"  enc {enc_s:.1f}+{pred_s:.2f}+{code_s:.1f} s dec {pred_s + apply_s:.2f} s"
            )
    return rows


def export_predictions(size: int, dev: str, where: Path, log) -> list[dict]:
    """For the CPU/CUDA check (``--check-predictions``, run where the CPU device is): each example
    field's model at ratio 200, its float64 prediction on this device and a residual at 1e-4, saved."""
    out = []
    for f in ("vortex", "interface"):
        data = generate(f, size, seed=0)
        m = warpgauss.encode(data, ratio=200, device=dev, evaluate=False)
        t = time.perf_counter()
        p, fragile = R.prediction(m, dev)
        secs = time.perf_counter() - t
        m.residual, _ = R.code_residual(data, None, p, fragile, 1e-4, (0.0, 1.0))
        m.save(where / f"{f}{size}.wgs", force=True)
        np.savez_compressed(
            where / f"{f}{size}_prediction.npz", prediction=p, fragile=fragile, decoded=R.apply_residual(m.residual, p), source=data
        )
        log(f"exported {f} {size}^3: predict {secs:.3f} s on {dev}")
        out.append({"field": f, "size": size, "predict_s": secs, "device": dev})
    return out


def check_predictions(where: Path, log) -> list[dict]:
    """Load the exported models, predict on the CPU, compare with the exported (CUDA) prediction and
    decode: the largest difference against the margin, and whether the bounded decodes agree."""
    out = []
    for p in sorted(where.glob("*_prediction.npz")):
        name = p.name.replace("_prediction.npz", "")
        m = warpgauss.Model.load(where / f"{name}.wgs")
        ref = np.load(p)
        t = time.perf_counter()
        mine, fragile = R.prediction(m, "cpu")
        secs = time.perf_counter() - t
        assert m.residual is not None
        dec = R.apply_residual(m.residual, mine)
        if "source" in ref.files:  # the volume the exporting machine coded (another numpy may generate it a few ulp apart)
            src = ref["source"].astype(np.float64)
        else:
            field = "vortex" if name.startswith("vortex") else "interface"
            src = generate(field, int(name[len(field) :]), seed=0)
        row = {
            "model": name,
            "max_prediction_difference": float(np.abs(mine - ref["prediction"]).max()),
            "margin": m.residual.info["margin"],
            "fragile_cpu": int(fragile.sum()),
            "fragile_cuda": int(ref["fragile"].sum()),
            "same_decode": bool(np.array_equal(dec, ref["decoded"])),
            "max_abs_error_cpu": float(np.abs(dec.astype(np.float64) - src).max()),
            "max_abs_error_cuda": float(np.abs(ref["decoded"].astype(np.float64) - src).max()),
            "bound": m.residual.info["bound"],
            "predict_s_cpu": secs,
        }
        log(json.dumps(row))
        out.append(row)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--mris", default=",".join(MRIS))
    ap.add_argument("--gaussian-ratios", default="100,300,1000")
    ap.add_argument("--bounds", default="1e-2,1e-3,1e-4")
    ap.add_argument("--device", default=None)
    ap.add_argument(
        "--export", type=int, default=0, help="edge of the fields whose models and predictions are saved beside --out (0: none)"
    )
    ap.add_argument("--check-predictions", default=None, help="a folder --export wrote: predict on the CPU and compare")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    dev = resolve_device(a.device)
    result = result_header("bounded_rd", __file__, argv, dev)
    result["rows"], result["devices"] = [], []
    if a.check_predictions:
        result["devices"] = check_predictions(Path(a.check_predictions), print)
        if a.out:
            Path(a.out).write_text(json.dumps(result, indent=1))
        return
    warpgauss.encode(example="vortex", example_size=32, budget=200, iterations=20, device=dev, evaluate=False)  # warm-up
    ratios = [float(r) for r in a.gaussian_ratios.split(",") if r]
    bounds = [float(b) for b in a.bounds.split(",") if b]

    def save():
        if a.out:
            Path(a.out).write_text(json.dumps(result, indent=1))

    for name, data in volumes(a.size, [f for f in a.fields.split(",") if f], [m for m in a.mris.split(",") if m]):
        result["rows"] += bounded_rows(name, data, ratios, bounds, dev, print)
        save()
    if a.export and a.out:
        result["devices"] = export_predictions(a.export, dev, Path(a.out).parent, print)
    save()


if __name__ == "__main__":
    main()
