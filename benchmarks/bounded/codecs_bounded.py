"""SZ3 (absolute bound), ZFP (fixed accuracy) and SPERR (point-wise error) at the bounds of
``bounded_rd.py`` (1e-2, 1e-3, 1e-4 of the range), on one CPU core: compression ratio (source
bytes over compressed bytes), PSNR, maximum error against the bound, encode / decode seconds.

The codecs compress the float32 volume (integer sources cast, as ``bench_rd.py`` does); the ratio
counts the source's own bytes. Needs the ``bench`` extra (pysz, zfpy, numcodecs-wasm-sperr).

    python benchmarks/bounded/codecs_bounded.py --size 256 --out benchmarks/results/bounded/codecs_bounded256_cpu.json
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "rate_distortion"))
sys.path.insert(0, str(HERE))

from bench_rd import sperr_run, sz3_run, zfp_run  # noqa: E402
from bounded_rd import MRIS, volumes  # noqa: E402

from warpgauss.encoding.bench import result_header  # noqa: E402
from warpgauss.field.evaluate import psnr_from_mse  # noqa: E402

CODECS = {
    "sz3": lambda d, e: sz3_run(d, e),
    "zfp-acc": lambda d, e: zfp_run(d, tolerance=float(e)),
    "sperr-pwe": lambda d, e: sperr_run(d, mode="pwe", pwe=float(e)),
}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--mris", default=",".join(MRIS))
    ap.add_argument("--bounds", default="1e-2,1e-3,1e-4")
    ap.add_argument("--codecs", default=",".join(CODECS))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    result = result_header("codecs_bounded", __file__, argv, "cpu")
    import importlib.metadata as md

    result["codec_versions"] = {p: md.version(p) for p in ("pysz", "zfpy", "numcodecs-wasm-sperr")}
    result["rows"] = []
    for name, data in volumes(a.size, [f for f in a.fields.split(",") if f], [m for m in a.mris.split(",") if m]):
        x = data.astype(np.float64)
        lo, hi = float(x.min()), float(x.max())
        f32 = np.ascontiguousarray(data.astype(np.float32))
        for rel in (float(b) for b in a.bounds.split(",")):
            bound = rel * (hi - lo)
            for codec in a.codecs.split(","):
                nbytes, dec, enc_s, dec_s = CODECS[codec](f32, bound)
                err = dec.astype(np.float64) - x
                row = {
                    "volume": name,
                    "codec": codec,
                    "bound_rel": rel,
                    "bound": bound,
                    "bytes": nbytes,
                    "ratio": data.nbytes / nbytes,
                    "psnr_db": psnr_from_mse(float(np.mean((err / (hi - lo)) ** 2))),
                    "max_abs_error": float(np.abs(err).max()),
                    "within_bound": bool(np.abs(err).max() <= bound),
                    "encode_s": enc_s,
                    "decode_s": dec_s,
                }
                result["rows"].append(row)
                print(
                    f"{name:>28} {rel:7.0e} {codec:>9} ratio {row['ratio']:9.2f} PSNR {row['psnr_db']:6.2f} "
                    f"max err / bound {row['max_abs_error'] / bound:.3f} enc {enc_s:.1f} s dec {dec_s:.1f} s",
                    flush=True,
                )
                if a.out:
                    Path(a.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
