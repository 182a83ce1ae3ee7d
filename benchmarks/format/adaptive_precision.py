"""Per-Gaussian precision in the coded format (issue #53 part 1): how many dB a rule that sets a
Gaussian's quantisation depth from its own (decoded) shape loses, and how many bits a Gaussian it
saves, against the rate control's own trade (one bit less on one attribute for every Gaussian).
Host only (Warp CPU device).

For each refined model (a ``.npz`` of the encoder's float32 ``params`` and the ``bits_*`` depths
its rate control chose; the ``.wgs`` beside it for the header) and its source volume:

* *stored*: the parameters through the coder's own :func:`coded.quantise` / :func:`coded.dequantise`
  at the model's depths (canonical turns), decoded on the full grid (``GaussianField`` on ``cpu``,
  as ``warpgauss.field.evaluate.evaluate_field`` with ``full=True``) against the source normalised by
  the model's value range (``warpgauss.field.analysis.normalise``): the reference PSNR;
* *global X-1*: the same with one bit less on attribute X for every Gaussian (what the rate
  control trades); bits saved measured two ways: the layout-2 payload ``encode_coded`` writes (real)
  and the order-0 entropy of the codes (the same estimator as the per-Gaussian rules);
* per-Gaussian rules, each re-quantising one attribute of the stored model in numpy with a depth
  computed from what a decoder already has (the stored log-scales), all else as stored:

  - ``q_aniso T``: the three rotation components lose k = floor(log2(T / A)) bits (0 to b_q - 2),
    A = max - min of the Gaussian's log-scales (the shape change a turn makes per radian grows
    with it); A = 0 (three equal log-scale codes): no rotation stored (identity);
  - ``q_axis T``: component x, y or z of the (canonical, near-identity) quaternion, about the
    local axis k, loses floor(log2(T / D_k)) bits, D_k = |s_i - s_j| of the two other axes (a turn
    about k mixes only them); D_k = 0: that component is not stored (0);
  - ``mu_size T``: the centre loses k = floor(log2(sigma_min 2^b_mu / T)) fractional bits (0 to b_mu):
    a centre error that is a small share of the Gaussian's smallest sigma barely changes the field;
  - ``a_vol Q`` / ``s_vol Q``: the value a (log-scales) lose k = floor(log2(V_Q / V) / 2) bits (0-3),
    V the Gaussian's volume exp(s_x + s_y + s_z), V_Q its Q-quantile over the model (the squared
    error a Gaussian's a or s error makes grows as its volume, one bit is a factor 4);
  - ``combined``: q_aniso 1, mu_size 4 and a_vol 0.9 together.

Bits saved a Gaussian: *nominal* (bits removed: k a component, 3 k a centre, a component's whole
depth where it is not stored) and *entropy*: for every attribute but the centres, the order-0
entropy of each code column given the depth class (which a decoder knows) before less after (the
same classes both sides, so the conditioning itself gains nothing); for the centres, the layout-2
centre stream (Morton key gap symbols' order-0 entropy plus their raw bits) at depth b_mu before,
after: that stream at the coarsest depth any Gaussian gets plus the refinement bits 3 (k_max - k)
each Gaussian keeps (a nested coding). dB a byte = dB lost / (entropy bits saved / 8).

    python benchmarks/format/adaptive_precision.py /work/models/{mean_reg2mean,mni_icbm152,inia19}_cr100.npz \\
        --vol /work/main/benchmarks/build/vol --out benchmarks/results/format/adaptive_precision_cpu.json
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

from warpgauss import Model
from warpgauss.encoding.bench import result_header
from warpgauss.field.analysis import normalise
from warpgauss.field.evaluate import evaluate_field
from warpgauss.format import coded
from warpgauss.format.coded_keys import centre_keys, gap_streams

R = coded.Q_RANGE
GLOBAL = (("mu", 1), ("log_s", 1), ("q", 1), ("a", 1), ("a", 2), ("w", 1))  # (attribute, bits less)
RULES = (
    ("q_aniso", 1.0),
    ("q_aniso", 2.0),
    ("q_axis", 1.0),
    ("q_axis", 2.0),
    ("mu_size", 2.0),
    ("mu_size", 4.0),
    ("mu_size", 8.0),
    ("a_vol", 0.5),
    ("a_vol", 0.9),
    ("s_vol", 0.5),
    ("s_vol", 0.9),
    ("combined", 0.0),
)
COMBINED = (("q_aniso", 1.0), ("mu_size", 4.0), ("a_vol", 0.9))


# -- code lengths ---------------------------------------------------------------------------------


def entropy_bits(x: np.ndarray) -> float:
    """Empirical order-0 entropy of integer symbols, total bits."""
    if len(x) == 0:
        return 0.0
    _, counts = np.unique(x, return_counts=True)
    return float(-(counts * np.log2(counts / counts.sum())).sum())


def cond_bits(x: np.ndarray, cls: np.ndarray) -> float:
    """Sum over classes of the order-0 entropy of ``x`` within the class (total bits)."""
    total = 0.0
    for c in np.unique(cls):
        total += entropy_bits(x[cls == c])
    return total


def centre_stream_bits(mu: np.ndarray, depth: int) -> float:
    """Layout-2 centre bits (gap symbols' order-0 entropy plus raw bits) of centres ``mu`` on the
    grid of ``depth`` fractional bits."""
    c = np.rint(mu * float(2**depth)).astype(np.int64)
    key = centre_keys(c)
    sym, _, nbits = gap_streams(np.sort(key))
    return entropy_bits(np.frombuffer(sym, np.uint8)) + nbits


# -- per-Gaussian quantisers ----------------------------------------------------------------------


def grid_round(x: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(codes, values) of ``x`` on grids of per-element ``depth`` fractional bits."""
    scale = np.exp2(depth.astype(np.float64))
    code = np.rint(x * scale)
    return code.astype(np.int64), code / scale


def rotation_round(small: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(codes, values) of smallest-three components on 2^depth - 1 levels (depth 0: not stored, 0)."""
    lev = np.maximum(np.exp2(depth.astype(np.float64)) - 2.0, 1.0)
    code = np.clip(np.rint((small + R) / (2 * R) * lev), 0, lev)
    val = np.where(depth > 0, code * (2 * R / lev) - R, 0.0)
    return np.where(depth > 0, code, 0).astype(np.int64), val


def drop_bits(ratio: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """floor(log2(ratio)) clipped to [lo, hi] (ratio inf: hi)."""
    with np.errstate(divide="ignore"):
        k = np.floor(np.log2(ratio))
    return np.clip(np.nan_to_num(k, posinf=hi, neginf=lo), lo, hi).astype(np.int64)


def rule_depths(name: str, t: float, base: np.ndarray, b: dict) -> tuple[str, np.ndarray]:
    """(attribute, per-Gaussian depth (N,) or (N, 3)) of a rule, from the stored parameters."""
    s = base[:, 3:6].astype(np.float64)
    if name == "q_aniso":
        a = s.max(1) - s.min(1)
        with np.errstate(divide="ignore"):
            k = drop_bits(t / a, 0, b["q"] - 2)
        depth = np.where(a == 0, 0, b["q"] - k)
        return "q", np.repeat(depth[:, None], 3, 1)
    if name == "q_axis":
        d = np.abs(s[:, [1, 2, 0]] - s[:, [2, 0, 1]])  # component x: axes y, z; y: z, x; z: x, y
        with np.errstate(divide="ignore"):
            k = drop_bits(t / d, 0, b["q"] - 2)
        return "q", np.where(d == 0, 0, b["q"] - k)
    if name == "mu_size":
        k = drop_bits(np.exp(s.min(1)) * 2.0 ** b["mu"] / t, 0, b["mu"])
        return "mu", np.repeat((b["mu"] - k)[:, None], 3, 1)
    if name in ("a_vol", "s_vol"):
        logv = s.sum(1)
        k = np.clip(np.floor((np.quantile(logv, t) - logv) / np.log(2.0) / 2.0), 0, 3).astype(np.int64)
        attr = "a" if name == "a_vol" else "log_s"
        depth = b[attr] - k
        return attr, depth[:, None] if attr == "a" else np.repeat(depth[:, None], 3, 1)
    raise ValueError(name)


_COLS = {"mu": slice(0, 3), "log_s": slice(3, 6), "a": slice(10, 11)}


def apply_rule(attr: str, depth: np.ndarray, base: np.ndarray, codes: np.ndarray, b: dict) -> tuple[np.ndarray, dict]:
    """Parameters with ``attr`` re-quantised at per-Gaussian ``depth``, and the bits saved."""
    p = base.astype(np.float64).copy()
    n = len(p)
    drop = b[attr] - depth
    if attr == "q":
        qi, small = coded.smallest_three(p[:, 6:10])
        new, val = rotation_round(small, depth)
        p[:, 6:10] = coded.from_smallest_three(qi, val)
        old = codes[:, 7:10]
        nominal = float(np.where(depth == 0, b["q"], drop).sum())
    else:
        cols = _COLS[attr]
        new, p[:, cols] = grid_round(p[:, cols], depth)
        old = codes[:, cols]
        nominal = float(drop.sum())
    if attr == "mu":
        k = drop[:, 0]
        coarse = b["mu"] - int(k.max())
        after = centre_stream_bits(base[:, 0:3], coarse) + 3.0 * float((k.max() - k).sum())
        saved = centre_stream_bits(base[:, 0:3], b["mu"]) - after
    else:
        saved = sum(cond_bits(old[:, j], depth[:, j]) - cond_bits(new[:, j], depth[:, j]) for j in range(old.shape[1]))
    return p.astype(np.float32), {"nominal_bits": nominal / n, "entropy_bits": saved / n, "share_changed": float((drop.max(1) > 0).mean())}


# -- one model ------------------------------------------------------------------------------------


def psnr(params: np.ndarray, header: dict, f) -> float:
    return float(evaluate_field(Model(params, header).field("cpu"), f, full=True)["psnr_db"])


def global_rows(p: np.ndarray, b: dict, header: dict, f, ref: float, codes: np.ndarray) -> list[dict]:
    """One bit less on each attribute for every Gaussian: dB lost, real and entropy bits saved."""
    n = len(p)
    size0 = len(coded.encode_coded(p, b)[0])
    rows = []
    for attr, less in GLOBAL:
        b1 = dict(b, **{attr: b[attr] - less})
        if b1[attr] < (2 if attr == "q" else 0):
            continue
        c1 = coded.quantise(p, b1)
        real = (size0 - len(coded.encode_coded(p, b1)[0])) * 8.0 / n
        if attr == "mu":
            ent = centre_stream_bits(codes[:, 0:3] / 2.0 ** b["mu"], b["mu"]) - centre_stream_bits(codes[:, 0:3] / 2.0 ** b["mu"], b1["mu"])
        else:
            cols = {"log_s": range(3, 6), "q": range(7, 10), "a": [10], "w": [11]}[attr]
            ent = sum(entropy_bits(codes[:, j]) - entropy_bits(c1[:, j]) for j in cols)
        db = ref - psnr(coded.dequantise(c1, b1), header, f)
        nominal = (3.0 if attr in ("mu", "log_s", "q") else 1.0) * less
        rows.append(
            {"rule": f"global {attr}-{less}", "db_lost": db, "payload_bits": real, "entropy_bits": ent / n, "nominal_bits": nominal}
        )
    return rows


def analyse(path: Path, vol_dir: Path, fields: dict) -> dict:
    t0 = time.perf_counter()
    with np.load(path) as d:
        p = np.asarray(d["params"], np.float32)
        b = {k[5:]: int(d[k]) for k in d.files if k.startswith("bits_")}
    model = Model.load(path.with_suffix(".wgs"))
    volume = path.stem.rsplit("_cr", 1)[0]
    key = (volume, model.value_range)
    if key not in fields:
        fields[key] = normalise(np.load(vol_dir / f"{volume}.npy"), value_range=model.value_range, count_candidates=False)
    f = fields[key]
    codes = coded.quantise(p, b)
    base = coded.dequantise(codes, b)
    ref = psnr(base, model.header, f)
    out = {"model": path.stem, "n": len(p), "bits": b, "psnr_db": ref, "payload_bpg": len(coded.encode_coded(p, b)[0]) / len(p)}
    out["global"] = global_rows(p, b, model.header, f, ref, codes)
    rows = []
    for name, t in RULES:
        parts = COMBINED if name == "combined" else ((name, t),)
        q, saved = base, {"nominal_bits": 0.0, "entropy_bits": 0.0}
        for pn, pt in parts:
            attr, depth = rule_depths(pn, pt, base, b)
            q, s = apply_rule(attr, depth, q, codes, b)
            for k in saved:
                saved[k] += s[k]
            if len(parts) == 1:
                saved["share_changed"] = s["share_changed"]
        rows.append({"rule": f"{name} {t:g}" if name != "combined" else name, "db_lost": ref - psnr(q, model.header, f), **saved})
    out["rules"] = rows
    out["seconds"] = time.perf_counter() - t0
    return out


def db_per_byte(r: dict) -> float:
    bits = r["entropy_bits"]
    return r["db_lost"] / (bits / 8.0) if bits > 1e-9 else float("nan")


def exchange_rates(results: list[dict]) -> None:
    """Each model's ``db_per_bpg``: the dB one byte a Gaussian buys as more Gaussians at the same
    file size, from the PSNR slope in ln N between the two nearest models of the same volume
    (dPSNR / dln N over the payload's bytes a Gaussian: saving x B/G buys N x / bpg Gaussians), and
    each rule's ``net_bpg``: bytes a Gaussian saved less the bytes its dB lost would cost (> 0: pays)."""
    for m in results:
        vol = m["model"].rsplit("_cr", 1)[0]
        others = [o for o in results if o is not m and o["model"].rsplit("_cr", 1)[0] == vol]
        if not others:
            continue
        o = min(others, key=lambda o: abs(np.log(o["n"] / m["n"])))
        slope = (m["psnr_db"] - o["psnr_db"]) / np.log(m["n"] / o["n"])
        m["db_per_ln_n"] = float(slope)
        m["db_per_bpg"] = float(slope / m["payload_bpg"])
        for r in m["global"] + m["rules"]:
            r["net_bpg"] = r["entropy_bits"] / 8.0 - r["db_lost"] / m["db_per_bpg"]


def table(results: list[dict]) -> str:
    lines = [
        "| model | rule | changed | dB lost | bits saved nominal | bits saved entropy | payload bits (real) | dB a byte | net B/G |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for m in results:
        rate = f", {m['db_per_bpg']:.2f} dB a B/G" if "db_per_bpg" in m else ""
        lines.append(f"| {m['model']} (N {m['n']:,}, {m['psnr_db']:.2f} dB, {m['payload_bpg']:.2f} B/G{rate}) | stored | | | | | | | |")
        for r in m["global"] + m["rules"]:
            ch = f"{100 * r['share_changed']:.0f} %" if "share_changed" in r else ""
            real = f"{r['payload_bits']:.2f}" if "payload_bits" in r else ""
            net = f"{r['net_bpg']:+.2f}" if "net_bpg" in r else ""
            lines.append(
                f"| | {r['rule']} | {ch} | {r['db_lost']:.3f} | {r['nominal_bits']:.2f} | {r['entropy_bits']:.2f} | {real} | {db_per_byte(r):.3f} | {net} |"
            )
    return "\n".join(lines)


def summarise(results: list[dict]) -> dict:
    names = [r["rule"] for r in results[0]["global"] + results[0]["rules"]]
    out = {}
    for name in names:
        rs = [r for m in results for r in m["global"] + m["rules"] if r["rule"] == name]
        out[name] = {
            "median_db_lost": statistics.median(r["db_lost"] for r in rs),
            "median_entropy_bits": statistics.median(r["entropy_bits"] for r in rs),
            "median_db_per_byte": statistics.median(db_per_byte(r) for r in rs),
        }
        nets = [r["net_bpg"] for r in rs if "net_bpg" in r]
        if nets:
            out[name]["median_net_bpg"] = statistics.median(nets)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path, help="refined models as .npz (params, bits_*), the .wgs beside each")
    ap.add_argument("--vol", type=Path, default=None, help="folder of the source volumes, <name>.npy")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--merge", action="store_true", help="the models are JSON results of earlier runs: merge them")
    args = ap.parse_args(argv)
    fields: dict = {}
    results = []
    if args.merge:
        results = [m for path in args.models for m in json.loads(path.read_text())["models"]]
    for path in [] if args.merge else args.models:
        r = analyse(path, args.vol, fields)
        print(f"{r['model']}: {r['psnr_db']:.2f} dB ({r['seconds']:.0f} s)", file=sys.stderr)
        results.append(r)
    exchange_rates(results)
    out = {**result_header("per-Gaussian quantisation depth: dB lost against bits saved", __file__, argv, "cpu"), "models": results}
    out["summary"] = summarise(results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(table(results))
    return out


if __name__ == "__main__":
    main()
