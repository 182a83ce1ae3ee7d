"""Bytes per primitive and PSNR loss of the coded format against the full-precision model.

For each (model, source volume) pair: full-grid PSNR of the model as stored in float32, then of
the same model through the coded quantiser at several bit allocations, with the coded payload's
bytes per primitive (payload only, and with the header). Writes JSON.

    python3 benchmarks/rate_distortion/coded_loss.py OUT.json MODEL.wgs:VOLUME [...]
"""

import json
import sys

import warpgauss
from warpgauss.encoding.bench import result_header
from warpgauss.format import coded
from warpgauss.format.model import Model
from warpgauss.format.wgs import wgs_bytes

VARIANTS = {
    "default": dict(coded.CODED_BITS),
    "first_draft": {"mu": 3, "log_s": 4, "q": 6, "a": 8, "w": 7},
    "mu2": {**coded.CODED_BITS, "mu": 2},
    "mu4": {**coded.CODED_BITS, "mu": 4},
    "s3": {**coded.CODED_BITS, "log_s": 3},
    "s5": {**coded.CODED_BITS, "log_s": 5},
    "q5": {**coded.CODED_BITS, "q": 5},
    "q7": {**coded.CODED_BITS, "q": 7},
    "a7": {**coded.CODED_BITS, "a": 7},
    "w6": {**coded.CODED_BITS, "w": 6},
    "lean": {"mu": 2, "log_s": 3, "q": 5, "a": 7, "w": 6},
    "lean_s4": {"mu": 2, "log_s": 4, "q": 5, "a": 7, "w": 6},
    "lean_mu1": {"mu": 1, "log_s": 3, "q": 5, "a": 7, "w": 6},
    "lean_q4": {"mu": 2, "log_s": 3, "q": 4, "a": 7, "w": 6},
    "lean_a6w5": {"mu": 2, "log_s": 3, "q": 5, "a": 6, "w": 5},
    "lean_mu1_a6w5": {"mu": 1, "log_s": 3, "q": 5, "a": 6, "w": 5},
    "s4_a6w5": {"mu": 2, "log_s": 4, "q": 5, "a": 6, "w": 5},
    "a6": {**coded.CODED_BITS, "a": 6},
    "w5": {**coded.CODED_BITS, "w": 5},
    "mu2_s4_q6_a7_w5": {"mu": 2, "log_s": 4, "q": 6, "a": 7, "w": 5},
    "mu2_s4_q5_a7_w5": {"mu": 2, "log_s": 4, "q": 5, "a": 7, "w": 5},
}
if len(sys.argv) > 2 and sys.argv[1] == "--only":
    keep = sys.argv[2].split(",")
    VARIANTS = {k: v for k, v in VARIANTS.items() if k in keep}
    sys.argv[1:3] = []
out, pairs = sys.argv[1], sys.argv[2:]
rows = []
for pair in pairs:
    path, vol = pair.split(":", 1)
    m = Model.load(path)
    base = warpgauss.psnr(m, vol, full=True, device="cpu")
    row = {"model": path, "volume": vol, "n": m.n, "psnr_full_precision_db": base, "variants": {}}
    print(f"{path}: N {m.n}, full precision {base:.3f} dB", flush=True)
    for name, bits in VARIANTS.items():
        payload, quant, order = coded.encode_coded(m.params, bits)
        q = coded.decode_coded(payload, m.n, quant)
        mq = Model(q, m.header)
        p = warpgauss.psnr(mq, vol, full=True, device="cpu")
        total = len(wgs_bytes(m.params, m.header, encoding="coded")) if name == "default" else None
        row["variants"][name] = {
            "bits": bits,
            "payload_bytes_per_primitive": len(payload) / m.n,
            "psnr_db": p,
            "loss_db": base - p,
            "raw_bytes_per_primitive": coded.zstandard_module().get_frame_parameters(payload).content_size / m.n,  # either layout
            "file_bytes": total,
        }
        print(
            f"  {name:8s} {len(payload) / m.n:6.2f} B/prim  {p:7.3f} dB  loss {base - p:6.3f}" + (f"  file {total}" if total else ""),
            flush=True,
        )
    rows.append(row)
json.dump(
    {**result_header("coded format: bytes per primitive and PSNR loss (full grid) against float32", __file__, None, "cpu"), "rows": rows},
    open(out, "w"),
    indent=1,
)
