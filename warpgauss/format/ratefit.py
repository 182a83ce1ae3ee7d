"""Rate control of the ``coded`` format: the quantisation depths and the primitives kept so that
a model's coded payload fits a byte budget (:func:`fit_bytes`, :func:`fit_at_share`), and the
depths an accuracy asks for (:func:`bits_for_psnr`). The format itself is :mod:`warpgauss.format.coded`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import WarpgaussError
from .coded import (
    BITS_REFERENCE_DB,
    CODED_BITS,
    DB_PER_BIT,
    _FitCodes,
    as_stored,
    canonical,
    check_bits,
    encode_coded,
    project_coded,
)

# rate control: one bit at a time, in the order of PSNR lost (or gained) per byte measured on four
# real volumes (benchmarks/results/rate_distortion/coded_loss_mri_cpu.json): dropping w, mu and a bits costs least,
# adding rotation and log-scale bits gains most
SHRINK_ORDER = ("w", "mu", "a", "log_s", "q")
GROW_ORDER = ("q", "log_s", "a", "mu", "w")
_MIN_BITS = {"mu": 0, "log_s": 1, "q": 3, "a": 3, "w": 2}
_MAX_BITS = {"mu": 8, "log_s": 8, "q": 10, "a": 12, "w": 10}
# an excess up to this share of the budget is pruned (the least important primitives), beyond it
# bits are dropped first, unless the caller can score the fits (fit_bytes' score; the encode can),
# which then also tries CHOICE_SHARES. Measured on an H100 before importance ranked by weight
# (benchmarks/results/accuracy/sweep_mri_vortex256_h100.json): pruning up to a 10 % excess by
# weight x |value| x volume lost 0.6-2.7 dB on the MRIs and 21.7 dB on vortex at 300; that ranking
# took the Gaussians of value 0 first (benchmarks/results/accuracy/prune_order_*_cpu.json)
PRUNE_SHARE = 0.03
FILL_SHARE = 0.002  # the prune search stops once the model is within this share under the budget
SEARCH_CODINGS = 12  # codings the prune search may spend after the first fit (to within one primitive)
GROW_MARGIN = 0.5  # a bit is tried when half its predicted bytes fit (its lowest bits may compress)
_BIT_COLUMNS = {"mu": 3, "log_s": 3, "q": 3, "a": 1, "w": 1}  # stored values per primitive and bit


def importance(params: np.ndarray) -> np.ndarray:
    """What a primitive adds to the model, for pruning: weight x sigma volume, its share of the
    blend's denominator around it. Not its value: the model is a normalised blend, so a
    primitive of value 0 holds its neighbourhood at 0 as much as any other holds its value.
    Measured (CPU, 400 iterations, float32 models, ``benchmarks/results/accuracy/prune_order_*_cpu.json``):
    pruning 3 / 10 % by weight x sigma volume cost 0.0-0.1 / 0.0-1.4 dB on vortex and interface
    96^3 and two head MRIs, where weight x |value| x volume (before) cost 0.3-9.1 / 1.9-12.9 dB
    (on the fields, worse than a random choice)."""
    p = np.asarray(params, np.float64)
    return np.abs(p[:, 11]) * np.exp(np.clip(p[:, 3:6].sum(1), -60.0, 60.0))


# the value difference a primitive is credited with whatever its neighbours hold (the hole a lone
# primitive leaves): benchmarks/accuracy/prune_order.py's "loo-hole" ranking
LEFT_OUT_HOLE = 0.05


def importance_left_out(params: np.ndarray, value: np.ndarray, density: np.ndarray) -> np.ndarray:
    """What leaving each primitive out changes at its own centre, for a cut of many at once:
    weight x sigma volume x (|its value - the model there| + :data:`LEFT_OUT_HOLE`) / (the rest of
    the blend's denominator there), given the model's value and density at the centres. A primitive
    that says what its neighbours say goes first. Measured (CPU, float32 models,
    ``benchmarks/results/accuracy/prune_order_*_cpu.json``): a cut of 30 % cost 0.37 / 1.11 / 8.14 /
    1.54 dB on mni_icbm152, mean_reg2mean, vortex and interface 96^3 where :func:`importance` cost
    0.92 / 1.76 / 9.12 / 2.02, and no more at 3 and 10 %."""
    p = np.asarray(params, np.float64)
    density = np.asarray(density, np.float64)
    floor = max(1e-3 * float(np.median(density)) if len(density) else 0.0, 1e-12)
    rest = np.maximum(density - np.abs(p[:, 11]), floor)
    return importance(p) * (np.abs(p[:, 10] - np.asarray(value, np.float64)) + LEFT_OUT_HOLE) / rest


def _bit_bytes(n: int, k: str) -> float:
    """Predicted bytes one more (or one fewer) bit of attribute ``k`` costs ``n`` primitives: a
    grid's lowest bit is close to noise, so about one bit per stored value (its columns)."""
    return n * _BIT_COLUMNS[k] / 8.0


# which attribute's bits are worth most depends on the volume: on the head MRIs a bit of mu costs
# least (the orders above), on the interface field (96^3, benchmarks/results/accuracy/
# prune_order_fields_cpu.json) it costs 4x more PSNR per byte than any other. With
# MEASURE_BIT_WORTH and a score (fit_bytes'), each attribute's bit is measured on the model itself:
# one bit more and one fewer on it alone, projected (no coding) and scored; a bit's worth is taken
# to fall 4x with each bit beyond (its noise power quarters). Off: measured, it does not pay. On
# float32 CPU models at equal bytes (benchmarks/results/accuracy/bit_order_*_cpu.json) it gained
# 0.00-0.10 dB over the scored choice alone; in the encode on an H200
# (sweep_interface512_worth_h200.json, sweep_mri300_worth_h200.json) the interface at 512^3 gained
# 0.18 dB at CR 100 and lost 0.45 at CR 300 (one bit's worth, measured alone, did not predict the
# drops together), the MRIs at CR 300 were unchanged, and the eleven scores cost 0.4-0.6 s on the
# MRIs and 2.8 / 8.5 s at 180,000 / 575,000 Gaussians
BIT_WORTH_DECAY = 4.0
MEASURE_BIT_WORTH = False
BitWorth = dict[str, tuple[float | None, float | None]]  # per attribute: (gain, loss) per byte of a bit


def bit_worth(params: np.ndarray, bits: dict[str, int], score) -> BitWorth:
    """Per attribute, the PSNR one bit more gains and one bit fewer loses, per predicted byte
    (:func:`_bit_bytes`), measured by ``score(projected, bits)`` on the model projected onto those
    grids (:func:`project_coded`: the stored values in the model's own order; None where the depth
    is at its bound): ``{k: (gain, loss)}``."""
    p = np.asarray(params, np.float32)
    b = check_bits(dict(bits))
    base = float(score(project_coded(p, b), b))
    out: BitWorth = {}
    for k in SHRINK_ORDER:
        per = max(_bit_bytes(len(p), k), 1e-9)
        more = {**b, k: b[k] + 1}
        fewer = {**b, k: b[k] - 1}
        gain = (float(score(project_coded(p, more), more)) - base) / per if b[k] < _MAX_BITS[k] else None
        loss = (base - float(score(project_coded(p, fewer), fewer))) / per if b[k] > _MIN_BITS[k] else None
        out[k] = (gain, loss)
    return out


def _next_drop(b: dict[str, int], start: dict[str, int], worth: BitWorth | None, turn: int) -> tuple[str | None, int]:
    """The attribute whose bit to drop next: the least loss per byte (falling 4x a bit dropped)
    with ``worth``, else :data:`SHRINK_ORDER` in turn; and the next turn."""
    if worth is None:
        for _ in range(len(SHRINK_ORDER)):
            k = SHRINK_ORDER[turn % len(SHRINK_ORDER)]
            turn += 1
            if b[k] > _MIN_BITS[k]:
                return k, turn
        return None, turn
    loss = {k: v for k, (_, v) in worth.items() if v is not None and b[k] > _MIN_BITS[k]}
    if not loss:
        return None, turn
    order = len(SHRINK_ORDER)  # ties go in turn, as without worth
    k = min(loss, key=lambda k: (loss[k] * BIT_WORTH_DECAY ** (start[k] - b[k]), (SHRINK_ORDER.index(k) - turn) % order))
    return k, SHRINK_ORDER.index(k) + 1


def _grow_order(b: dict[str, int], start: dict[str, int], worth: BitWorth | None) -> list[str]:
    """Attributes to try a bit more on, best first: :data:`GROW_ORDER` without ``worth``, else by
    gain per byte (falling 4x with each bit above ``start``; the budget is filled either way)."""
    if worth is None:
        return list(GROW_ORDER)
    gain = {k: g for k, (g, _) in worth.items() if g is not None}
    grown = {k: max(0, b[k] - start[k]) for k in gain}  # ties: the fewest bits grown first, then GROW_ORDER
    return sorted(gain, key=lambda k: (-gain[k] / BIT_WORTH_DECAY ** grown[k], grown[k], GROW_ORDER.index(k)))


# where a caller can measure a fitted model's accuracy (fit_bytes' score), the rate control fits at
# each of these prune shares (an excess up to the share pruned, beyond it bits dropped first; 1.0:
# pruning alone up to twice the budget) and keeps the one that scores best. Measured with the
# weight ranking (benchmarks/results/accuracy/prune_order_*_cpu.json): which pays depends on the
# volume and the excess, so it is measured per model rather than fixed. 0.0: bits alone, nothing
# pruned: the interface at 512^3, CR 1000, pruned 949 of 53,338 (1.8 %) beside three bits dropped
# and scored 6.5 dB under float32 of its N, where 8 % pruned cost 13 dB (H200,
# accuracy/sweep_fields512_float2_h200.json). On float32 CPU models at 0.85 / 0.92 / 0.97 of the
# bytes their accuracy asks for (interface and vortex 96^3 N 20,000, mni_icbm152 and inia19 N
# 10,000, 400 iterations) it was chosen twice in twelve (vortex 58.70 -> 58.74, inia19 41.91 ->
# 41.92 dB) and, being scored, lost nothing elsewhere (the interface and mni keep pruning: 49.33-
# 49.82 and 30.98-31.09 dB against 48.06-49.43 and 30.70-30.99 by bits alone). Not yet on a GPU
CHOICE_SHARES = (PRUNE_SHARE, 0.0, 0.15, 1.0)
# prune-search codings of an alternative before it is scored (a winner is fitted again in full):
# the choice cost 1.5-5.3 s of coding on 200,000-570,000-Gaussian models with the whole search
CHOICE_SEARCH_CODINGS = 1
# the first fit on a thread beside the alternatives (once the size at the starting depths says it
# will drop bits), not before them: the same fits, chosen alike, in the time of the longest. On
# one H200 host (16 cores) the interface field at 512^3, CR 100, spent 20.4 s in the rate control,
# the alternatives waiting on the first fit (benchmarks/results/speed/host_profile_interface512_h200.json)
CHOICE_CONCURRENT = True
# bit trials of the fill (a bit more where it still fits) coded at once, on threads, for models of
# warpgauss.format.coded_keys.PARALLEL_MIN_ROWS primitives or more: the fill takes the first in
# order that fits, as one trial after the other would (the extra trials coded for nothing)
GROW_WAVE = 3


def fit_bytes(
    params: np.ndarray,
    budget: int,
    bits: dict[str, int] | None = None,
    size_of=None,
    prune_share: float | None = None,
    score: Callable[[np.ndarray, dict[str, int]], float] | None = None,
) -> tuple[np.ndarray, dict, dict]:
    """The coded model that fits ``budget`` bytes, as :func:`fit_at_share` fits it; with ``score``
    (and no ``prune_share``) at each of :data:`CHOICE_SHARES` where the first fit had to drop bits,
    keeping the fit that ``score(stored, bits)`` (a PSNR) rates best. The info then holds
    ``choice``: each fit's share, steps, pruned count and score, and ``chosen``: its index."""

    def drops_bits(fit: tuple) -> bool:
        return any(step.endswith("-1") for step in fit[2]["steps"])

    t0 = time.perf_counter()
    worth = None if score is None or not MEASURE_BIT_WORTH else bit_worth(params, dict(CODED_BITS if bits is None else bits), score)
    facts = {}
    if worth is not None:
        facts = {"bit_worth": {k: {"gain": g, "loss": v} for k, (g, v) in worth.items()}, "bit_worth_seconds": time.perf_counter() - t0}
    if score is None or prune_share is not None:
        only = fit_at_share(params, budget, bits, size_of, prune_share, worth=worth)
        return only[0], only[1], {**only[2], **facts}
    # the size at the starting depths says whether the first fit will drop bits (and so whether
    # the alternatives are tried): coded once here, every fit starts from it
    start = check_bits(dict(CODED_BITS if bits is None else bits))
    base = canonical(params).astype(np.float32)  # what fit_at_share codes (turned once)
    at_start = (size_of or (lambda q, c: len(encode_coded(q, c)[0])))(base, start)
    drops = at_start > budget * (1.0 + PRUNE_SHARE) and any(start[k] > _MIN_BITS[k] for k in SHRINK_ORDER)
    first: tuple | None = None
    if not drops or not CHOICE_CONCURRENT:
        first = fit_at_share(params, budget, bits, size_of, None, worth=worth, at_start=at_start)
    # the alternatives with a short prune search (a little less full), each on a thread of its own
    # (the codings are numpy and Zstandard work, which release the GIL), the first fit beside them
    # where CHOICE_CONCURRENT; kept up to the first that fits by pruning alone, since a larger
    # share fits the same way: what a serial search keeps
    alternatives = CHOICE_SHARES[1:] if drops else ()
    tried = []
    with ThreadPoolExecutor(max_workers=len(CHOICE_SHARES)) as ex:
        if first is None:
            first_future = ex.submit(fit_at_share, params, budget, bits, size_of, None, SEARCH_CODINGS, worth, at_start)
        futures = [
            ex.submit(fit_at_share, params, budget, bits, size_of, share, CHOICE_SEARCH_CODINGS, worth, at_start) for share in alternatives
        ]
        tried.append(first if first is not None else first_future.result())
        if drops_bits(tried[0]):  # as the start size said (else what the serial search returns)
            for fut in futures:
                tried.append(fut.result())
                if not drops_bits(tried[-1]):
                    break
    if len(tried) == 1:
        return tried[0][0], tried[0][1], {**tried[0][2], **facts, "codings": tried[0][2]["codings"] + 1}
    scores = [float(score(stored, b)) for stored, b, _ in tried]
    best = int(np.argmax(scores))
    codings = 1 + sum(t[2]["codings"] for t in tried)  # the start size's coding and each fit's
    choice = [
        {"prune_share": t[2]["prune_share"], "steps": t[2]["steps"], "pruned": t[2]["pruned"], "psnr_db": sc}
        for t, sc in zip(tried, scores)
    ]
    if best > 0:  # the winner fitted again with the whole search, to fill the budget
        tried[best] = fit_at_share(params, budget, bits, size_of, tried[best][2]["prune_share"], worth=worth, at_start=at_start)
        codings += tried[best][2]["codings"]
    stored, b, info = tried[best]
    return stored, b, {**info, **facts, "codings": codings, "choice": choice, "chosen": best}


def fit_at_share(
    params: np.ndarray,
    budget: int,
    bits: dict[str, int] | None = None,
    size_of=None,
    prune_share: float | None = None,
    search: int = SEARCH_CODINGS,
    worth: BitWorth | None = None,
    at_start: int | None = None,
) -> tuple[np.ndarray, dict, dict]:
    """The coded model that fits ``budget`` bytes, as closely as bit depths and primitives allow.

    From ``bits`` (default :data:`CODED_BITS`): while the size exceeds the budget by more than
    ``prune_share`` (default :data:`PRUNE_SHARE`), drop bits of the attributes in :data:`SHRINK_ORDER` in turn; then prune
    the primitives that add least (:func:`importance`) until it fits (a primitive is the finest
    step there is, about 8 bytes). Then add bits in :data:`GROW_ORDER` while they still fit, so
    the budget buys precision when the primitives alone leave it unspent.

    Every size that decides is a real coding, but the steps between codings are predicted (a bit
    costs about one bit per stored value, a primitive the model's mean size), so a 900,000-
    primitive model is fitted in a handful of codings rather than dozens: bits are dropped as
    many at a time as the predicted excess needs, the prune count is found by interpolation
    (regula falsi) to within one primitive or :data:`FILL_SHARE` of the budget, and a bit is only
    tried when it is predicted to fit.

    Args:
        params: (N, 12) parameters.
        budget: Bytes the result may take, as ``size_of`` counts them.
        bits: Starting bit depths.
        size_of: ``size_of(params, bits)`` -> bytes (default: the coded payload alone; a model
            passes its whole file, header included).
        prune_share: See above.
        search: Codings the prune search may spend after the first fit.
        worth: :func:`bit_worth` of the model at ``bits``: bits are then dropped where they lose
            least and added where they gain most per byte, rather than in the fixed orders.
        at_start: ``size_of`` the (turned) parameters at ``bits``, where the caller coded them
            already (not coded again, nor counted in ``codings``).

    Returns:
        ``(stored, bits, info)``: the parameters as the file will hold them (projected, Morton
        order), the bit depths, and what was done (steps, pruned count, bytes, codings, the size
        at the starting depths as ``first_bytes``, and ``kept``: the rows of ``params`` kept, in
        their order, for a refit of the pruned model).
    """
    with _FitCodes(canonical(params).astype(np.float32)) as fit:  # turned once: every coding finds the turns at once
        return _fit_at_share(fit, params, budget, bits, size_of, prune_share, search, worth, at_start)


def _fit_at_share(fit: _FitCodes, params, budget, bits, size_of, prune_share, search, worth, at_start) -> tuple[np.ndarray, dict, dict]:
    """:func:`fit_at_share`'s search, its codings' columns kept in ``fit``."""
    b = check_bits(dict(CODED_BITS if bits is None else bits))
    p = fit.base
    share = PRUNE_SHARE if prune_share is None else float(prune_share)
    keep = np.arange(len(p))
    codings = 0

    def size(pp, bb) -> int:
        nonlocal codings
        codings += 1
        return (size_of or (lambda q, c: len(encode_coded(q, c)[0])))(pp, bb)

    steps: list[str] = []
    cur = first = size(p, b) if at_start is None else int(at_start)
    turn = 0
    pred: float  # the predicted size: less a bit's (fractional) bytes at each drop
    start = dict(b)
    while cur > budget * (1.0 + share):
        pred, dropped = cur, 0
        while pred > budget * (1.0 + share):
            k, turn = _next_drop(b, start, worth, turn)
            if k is None:
                break  # every depth at its least: pruning does the rest
            b[k] -= 1
            steps.append(f"{k}-1")
            pred -= _bit_bytes(len(p), k)
            dropped += 1
        if not dropped:
            break
        cur = size(p, b)
    pruned = 0
    if cur > budget:
        rank = np.argsort(-importance(p), kind="stable")  # most important first

        def kept(k: int) -> np.ndarray:
            return fit.subset(np.sort(rank[: len(p) - k]))

        lo, lo_size = 0, cur  # lo prunes too few (over budget); hi the fewest found that fit
        hi = hi_size = None
        cut = 0
        while hi is None:  # step out by the estimated excess (and 0.2 % more) until it fits
            per = cur / (len(p) - cut)
            cut = min(len(p) - 1, cut + max(1, int(np.ceil((cur - budget * (1.0 - FILL_SHARE / 2)) / per))))
            cur = size(kept(cut), b)
            if cur <= budget:
                hi, hi_size = cut, cur
            elif cut == len(p) - 1:
                raise WarpgaussError(f"no coded model of one primitive fits {budget} bytes; give a larger byte budget")
            else:
                lo, lo_size = cut, cur
        assert hi is not None and hi_size is not None  # the loop ends only where a size fits
        # then fewer pruned while more fit: interpolate between the two, halving when that stalls
        for _ in range(search):
            if hi - lo <= 1 or budget - hi_size <= FILL_SHARE * budget:
                break
            t = (lo_size - budget) / max(lo_size - hi_size, 1)
            mid = min(hi - 1, max(lo + 1, lo + int(round(t * (hi - lo)))))
            s = size(kept(mid), b)
            if s <= budget:
                hi, hi_size = mid, s
            else:
                lo, lo_size = mid, s
        p, pruned, cur = kept(hi), hi, hi_size
        keep = np.sort(rank[: len(rank) - hi])
    # add bits while they fit: from each state, the attributes in order whose bit is predicted to
    # fit are coded GROW_WAVE at a time (on threads) and the first that fits is taken, then the
    # rest of the order from the new state: the steps of trying them one at a time
    wave = grow_wave(len(p))
    trial_size = fit.in_thread(lambda bb: (size_of or (lambda q, c: len(encode_coded(q, c)[0])))(p, bb))
    grown = True
    while grown:
        grown = False
        order = _grow_order(b, start, worth)
        at = 0
        while at < len(order):
            cands = [k for k in order[at:] if b[k] < _MAX_BITS[k] and cur + _bit_bytes(len(p), k) * GROW_MARGIN <= budget]
            hit = None
            for i in range(0, len(cands), wave):
                trials = [{**b, k: b[k] + 1} for k in cands[i : i + wave]]
                codings += len(trials)
                if len(trials) == 1:
                    sizes = [trial_size(trials[0])]
                else:
                    with ThreadPoolExecutor(max_workers=len(trials)) as ex:
                        sizes = list(ex.map(trial_size, trials))
                hit = next(((k, t, tb) for k, t, tb in zip(cands[i : i + wave], sizes, trials) if t <= budget), None)
                if hit is not None:
                    break
            if hit is None:
                break
            k, cur, b = hit[0], hit[1], hit[2]
            grown = True
            steps.append(f"{k}+1")
            if worth is not None:
                break  # the order changes with each bit added
            at = order.index(k) + 1
    info = {"steps": steps, "pruned": pruned, "bytes": cur, "first_bytes": first, "codings": codings, "prune_share": share, "kept": keep}
    return as_stored(p, b), b, info


def grow_wave(n: int) -> int:
    """Bit trials a fit of ``n`` primitives codes at once (:data:`GROW_WAVE`; one below
    :data:`warpgauss.format.coded_keys.PARALLEL_MIN_ROWS`, where a coding is cheap)."""
    from .coded_keys import PARALLEL_MIN_ROWS

    return max(1, int(GROW_WAVE)) if n >= PARALLEL_MIN_ROWS else 1


def bits_for_psnr(psnr_db: float | None) -> tuple[dict[str, int], int]:
    """Bit depths for a model of about ``psnr_db`` (None: :data:`CODED_BITS`) and the bits added."""
    if psnr_db is None or not math.isfinite(psnr_db):
        return dict(CODED_BITS), 0
    extra = int(min(4, max(0, round((psnr_db - BITS_REFERENCE_DB) / DB_PER_BIT))))
    return {k: min(v + extra, _MAX_BITS[k]) for k, v in CODED_BITS.items()}, extra


def accuracy_bits(psnr_db: float | None) -> dict:
    """The report's ``coded_bits_from_accuracy``: the depths :func:`bits_for_psnr` gives a model
    whose training samples score ``psnr_db`` (``bits``) and the bits it added (``bits_added``)."""
    bits, extra = bits_for_psnr(psnr_db)
    return {"sample_psnr_db": psnr_db, "bits_added": extra, "bits": bits}
