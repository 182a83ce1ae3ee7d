"""Budget and bytes: N from --budget, --ratio or --bytes, and the coded size pilot that sizes N for
a coded file of a given size (one place for the rules and their refusals).
"""

from __future__ import annotations

import math
import time

import numpy as np

from ...core.profiling import StageRecorder
from ...errors import WarpgaussError
from ...field.analysis import Field, budget_from_bytes, check_budget, seed_limit
from ...format.model import Model
from ..allocate import allocate
from .options import DEFAULT_RATIO, EncodeOptions, encoding_of

# payload bytes a Gaussian of a refined model's coded file (layout 2, format version 3), as measured,
# rounded outwards; `warpgauss stats` quotes it before anything is encoded and adds the header
# itself. End to end (H200, default settings, commit bf04a95; (file bytes - header) / N): 6.28-10.21
# on the three head MRIs at CR 10-1000 (CR 10: benchmarks/results/speed/profile_final_h200.json;
# CR 100-1000: benchmarks/results/accuracy/sweep_round3_h200.json, 7.0-8.7; file bytes / N
# 6.29-10.22, a 1.9 KB header weighs at small N). The same refined models re-coded in layout 2
# (benchmarks/results/accuracy/coded_context_cpu.json): 6.36-10.40 on the MRIs, 7.77-10.09 on
# interface 256^3 and 12.11-12.75 on vortex 256^3 at CR 30-300 (more accurate models code on finer
# grids). The 512^3 example fields were not measured in layout 2 (layout 1: 8.6-14.0, RD.md round
# 11; layout 2 codes a model 4.4-8.8 % smaller).
CODED_BPP_MEASURED = (6.2, 12.8)
CODED_BPP_SIZING = 12  # bytes per primitive a coded file needs at most in practice (the "no room" check)
CODED_BPP_FLOOR = 4  # and at least: bounds N before its coded size is measured
# coded bytes per primitive of a refined model over its analytic allocation's: 1.19 / 1.22 / 1.22 /
# 1.34 on mni_icbm152 / inia19 / mean_reg2mean / nAChR water (benchmarks/results/rate_distortion/coded_loss_mri_cpu.json).
# N is sized a little below the median, so that a file rather comes out a few per cent over its
# budget, which pruning the least important primitives trims to within a primitive of it, than
# under it, which nothing after refinement can fill (ratefit.fit_bytes)
CODED_REFINE_GROWTH = 1.15
# refinement's gain over the analytic model, at least (full-grid PSNR, ratio 100, H100: vortex 512^3
# +18.9 dB, the three head MRIs +13.7 to +18.3 dB): the pilot sizes N for the bit depths a model
# that accurate needs (ratefit.bits_for_psnr), since an accurate model that must drop bits to fit
# loses more than the primitives cost. Measured on vortex 512^3 at ratio 100: N sized for the
# default depths (907,190) refined to 70.2 dB in float and 55.9 dB once fitted (mu at 0 bits);
# the float model at half that N scores 71.2 dB (benchmarks/results/rate_distortion/sizing_vortex512_h100.json)
CODED_REFINE_GAIN_DB = 12.0


def sizing_bpp(encoding: str) -> int:
    """Bytes per primitive a --ratio budget is sized with."""
    from ...format.wgs import ENCODINGS

    return ENCODINGS[encoding] or CODED_BPP_SIZING


def check_budget_options(budget, ratio, file_bytes) -> None:
    """Refuse, by name and before any work, budget options that cannot be used: more than one of
    them, a --budget or --bytes that is not a whole number of at least 1, a --ratio that is not a
    finite number above 0 (0, negative, NaN and infinity are refused, never replaced)."""
    given = [k for k, v in (("--budget", budget), ("--ratio", ratio), ("--bytes", file_bytes)) if v is not None]
    if len(given) > 1:
        raise WarpgaussError(f"give one of --budget, --ratio and --bytes, not {' and '.join(given)}")
    for name, value, unit in (("--budget", budget, "Gaussians"), ("--bytes", file_bytes, "bytes")):
        if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1):
            raise WarpgaussError(f"{name} must be a positive whole number of {unit}, got {value!r}")
    if ratio is not None:
        ok = not isinstance(ratio, bool) and isinstance(ratio, (int, float, np.integer, np.floating))
        if not ok or not math.isfinite(float(ratio)) or not ratio > 0:
            raise WarpgaussError(f"--ratio must be a finite number above 0 (source bytes over file bytes), got {ratio!r}")


def target_bytes(f: Field, opts: EncodeOptions) -> int | None:
    """The file size budget of --bytes or --ratio (floor(S_src / R)); None with --budget."""
    check_budget_options(opts.budget, opts.ratio, opts.bytes)
    if opts.budget is not None:
        return None
    if opts.bytes is not None:
        return int(opts.bytes)
    ratio = DEFAULT_RATIO if opts.ratio is None else float(opts.ratio)
    return int(f.source_bytes // ratio)


def resolve_budget(f: Field, opts: EncodeOptions, header_bytes: int) -> int:
    """N from --budget, --ratio or --bytes (SPEC section 4), validated against the seed limit:
    floor((bytes - H) / bytes per primitive), for the coded format an upper bound that
    :func:`coded_budget` refines once the volume is analysed."""
    bpp = sizing_bpp(encoding_of(opts))
    total = target_bytes(f, opts)
    if total is None:
        assert opts.budget is not None  # target_bytes gives None only for --budget
        n = int(opts.budget)
    else:
        n = budget_from_bytes(total, f.source_bytes, header_bytes, bpp, encoding_of(opts), CODED_BPP_MEASURED)
    if encoding_of(opts) == "coded" and total is not None:
        # a bound: the coded N is measured once the volume is analysed (coded_budget), at most N_max
        n_max = seed_limit(f.eligible, f.occupied)
        n = max(1, min(n_max, int((total - header_bytes) // CODED_BPP_FLOOR)))
        check_budget(f, n, header_bytes, bpp)
        return n
    check_budget(f, n, header_bytes, bpp)
    return n


def coded_budget(dv, f: Field, opts: EncodeOptions, header: dict, total: int, n_bound: int) -> tuple[int, dict]:
    """N for a coded file of ``total`` bytes: a pilot allocation's coded size per primitive, times
    the growth refinement brings (:data:`CODED_REFINE_GROWTH`; 1 without refinement), at the bit
    depths the expected accuracy needs (the pilot's PSNR plus :data:`CODED_REFINE_GAIN_DB` when
    refining, see :func:`warpgauss.format.ratefit.bits_for_psnr`)."""
    from ...field.evaluate import evaluate_field
    from ...format.ratefit import bits_for_psnr
    from ...format.wgs import header_size, payload_size, wgs_bytes

    pilot = max(1, min(n_bound, (total - header_size(header, n_bound, encoding="coded")) // 8))
    params, _ = allocate(dv, pilot, opts.seed, opts.allocation, StageRecorder())
    refining = opts.refine.iterations > 0
    pilot_db = evaluate_field(Model(params, header).field(dv.device), f)["psnr_db"]
    expected = pilot_db + (CODED_REFINE_GAIN_DB if refining else 0.0)
    bits, extra = bits_for_psnr(expected)
    t0 = time.perf_counter()
    data = wgs_bytes(params, header, encoding="coded", bits=bits)
    coding_s = time.perf_counter() - t0
    payload = payload_size(data)
    bpp = payload / pilot
    # the pilot's own header (the reserved bound is a few hundred bytes wider: at small budgets
    # that is a good share of the payload)
    head = len(data) - payload + 32
    growth = CODED_REFINE_GROWTH if refining else 1.0
    # n_bound counted the reserved header (its fields at their widest): the pilot's own leaves a
    # few hundred bytes more, which at a budget of a few hundred payload bytes is most of it
    n_bound = max(n_bound, min(seed_limit(f.eligible, f.occupied), int((total - head) // CODED_BPP_FLOOR)))
    n = max(1, min(n_bound, int((total - head) // (bpp * growth))))
    return n, {
        "pilot_n": pilot,
        "pilot_psnr_db": pilot_db,
        "expected_psnr_db": expected,
        "bits": bits,
        "bits_added": extra,
        "pilot_bytes_per_primitive": bpp,
        "header_bytes": head,
        "refine_growth": growth,
        "n": n,
        "coding_seconds_per_primitive": coding_s / pilot,
        "coding_seconds": coding_s,  # one coding of the pilot: a coding's fixed cost at least
    }


def coded_choice(sizing: dict | None, fit: dict | None, note: dict | None, replan: dict | None = None) -> str | None:
    """One sentence on how a coded file met its budget: primitives against precision (the
    measurements behind each rule are beside its constant, not in this user-facing text)."""
    if sizing is None and note is None:
        return None
    parts = []
    if sizing is not None:
        grids = (
            f"{sizing['bits_added']} bit(s) over the default grids, for the {sizing['expected_psnr_db']:.1f} dB expected "
            f"(pilot {sizing['pilot_psnr_db']:.1f} dB + refinement), since an accurate model that drops bits to fit loses more than "
            "the Gaussians cost"
            if sizing["bits_added"]
            else "the default grids, since each of their bits costs less PSNR than the Gaussians its bytes would buy"
        )
        parts.append(
            f"N {sizing['n']:,} from a pilot of {sizing['pilot_n']:,} at {sizing['pilot_bytes_per_primitive']:.2f} B x "
            f"{sizing['refine_growth']:.2f} (refined models code larger); {grids}"
        )
    if replan is not None:
        from .replan import REPLAN_MAX_CUT

        took = replan["n_before"] - replan["n_after"]
        parts.append(
            f"at iteration {replan['iteration']} the model scored {replan['sample_psnr_db']:.1f} dB on its samples and "
            + (
                f"would code at {replan['predicted_bytes']:,.0f} bytes on the grids that accuracy needs: its {took:,} least "
                "important Gaussians were taken out and the rest refined on"
                if took
                else "fitted its budget on the grids that accuracy needs"
            )
            + (
                f" (planned for {replan['planned_psnr_db']:.1f} dB, not the {replan['expected_psnr_db']:.1f} expected: "
                f"more bits would have taken out over {REPLAN_MAX_CUT:.0%} of them)"
                if replan.get("planned_psnr_db", replan["expected_psnr_db"]) < replan["expected_psnr_db"]
                else ""
            )
        )
        late = replan.get("late")
        if late is not None and late["n_after"] < late["n_before"]:
            parts.append(
                f"at iteration {late['iteration']} it scored {late['sample_psnr_db']:.1f} dB and was expected to reach "
                f"{late['expected_psnr_db']:.1f}, {late['bits_added']} bit(s) over the default grids: "
                f"{late['n_before'] - late['n_after']:,} more were taken out"
            )
    if note is not None and note["bits_added"]:
        parts.append(f"{note['bits_added']} bit(s) more on every attribute for a {note['sample_psnr_db']:.1f} dB model")
        if note.get("held_by_replan"):
            parts.append("the fit started from the re-plan's depths, which held bits back, and added bits while they fit")
    if fit is not None:
        did = ", ".join(fit["steps"]) or "no depth changed"
        pruned = f"{fit['pruned']:,} least important Gaussians pruned"
        if fit.get("refit"):
            pruned += f", the rest refined again for {fit['refit']['iterations']} iterations"
        if fit.get("choice"):
            tried = "; ".join(
                f"{c['pruned']:,} pruned with {', '.join(s for s in c['steps'] if s.endswith('-1')) or 'no bit dropped'}: {c['psnr_db']:.2f} dB"
                for c in fit["choice"]
            )
            parts.append(f"rate control: {did}; {pruned}, the best of the fits tried ({tried})")
        else:
            parts.append(
                f"rate control: {did}; {pruned} (an excess up to {fit.get('prune_share', 0):.0%} is pruned, beyond it bits "
                "are dropped first)"
            )
    return "; ".join(parts)
