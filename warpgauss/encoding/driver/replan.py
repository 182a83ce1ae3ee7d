"""Rate control during refinement: the mid-training re-plan of N for a coded byte budget, and the
(off by default) refit after pruning, as methods of :class:`Replan` that the encode run mixes in.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np

from ...format.model import Model
from .options import EncodeOptions

# a refined model pruned to fit its byte budget (ratefit.fit_bytes) may be refined again, the rest
# filling what the pruned ones carried: for this share of the iterations (at least
# REFIT_MIN_ITERATIONS), at REFIT_LR x the learning rate, when more than REFIT_MIN_PRUNED of the
# primitives went; then fitted once more. Off (0): measured on an H100 (benchmarks/results/accuracy/),
# a refit from fresh Adam moments moves every parameter by about the learning rate in its first
# steps and wrecks an accurate model (vortex 256^3 at ratio 300: 68.6 dB coded without, 43.6 with
# a refit at 0.3x, 47.7 at 0.02x); dropping bits beyond a 3 % excess (ratefit.PRUNE_SHARE) paid more
REFIT_SHARE = 0.0
# a coded byte budget's N is re-planned once the model's accuracy is known: after this share of the
# iterations the model is coded at the depths its expected final sample PSNR needs (extrapolated
# from the sample PSNR half-way there and now, at least REPLAN_REST_GAIN_DB more); where that,
# times REPLAN_GROWTH (how much larger the model codes by the end), exceeds the budget by more
# than REPLAN_TOLERANCE, the least important primitives are taken out and the rest refine on. The pilot's N (CODED_REFINE_GAIN_DB) under-predicts the depths
# of a model trained at voxel centres by 1-4 bits: refined models coded 1.2-2.3x their budget and
# lost 1-13 dB to the bits the rate control then dropped (benchmarks/results/accuracy/rd_*.json)
REPLAN_AT = 0.25
REPLAN_REST_GAIN_DB = 2.0
# the sample PSNR grows faster than linearly in log(iterations) as the learning rate decays: from
# K = T / 4 to T it gained 0.54-3.19x its gain from K / 2 to K times log2(T / K) (three MRIs at CR
# 10-1000, vortex and interface at 512^3 CR 100-1000; H200, sweep_*_choice_h200.json), the most
# where N is large (interface 512^3: 2.1-2.6). At 1.25 three of those 21 rows planned a bit depth
# short of the end's (benchmarks/accuracy/replan_extrapolation.py); at 2.5 none, but encoded again
# (sweep_*_replan25_h200.json) the six rows it changed all lost 0.18-0.40 dB (fewer primitives),
# the interface's too: its coded - float32 gap at the same N (-1.17 / -1.94 dB at CR 100 / 300)
# comes from the quantisation at the planned depths, not from bits dropped at export
REPLAN_EXTRAPOLATE = 1.25
REPLAN_MAX_GAIN_DB = 30.0
REPLAN_GROWTH = 1.05
# the re-plan's codings at fewer bits run this many at a time (0: a quarter of the host's cores,
# each coding's Zstandard levels on threads of their own; 1: one after the other). The interface
# field at 512^3, CR 100, coded its 1.1M Gaussians four times there, 12.8 s on one H200 host
# (benchmarks/results/speed/host_profile_interface512_h200.json)
REPLAN_WORKERS = 0
REPLAN_TOLERANCE = 0.01
REPLAN_MIN_ITERATIONS = 100
# the re-plan takes out at most this share of the primitives while it can code fewer bits instead
# (one bit of every attribute at a time, down to the default depths). With samples drawn where the
# error is (RefineConfig.error_share) the interface field at 512^3, CR 300, was 52.2 dB at a
# quarter of the run, planned 4 more bits, lost 58 % of its primitives, fell to 35.0 dB and ended
# at 46.4 (52.6 without the error stratum, a 37 % cut; H200, accuracy/sweep_fields512_err_h200.json);
# of the 83 other rows of the two sweeps (three MRIs too) none cut more than 38 %: this changes none of them
REPLAN_MAX_CUT = 0.4
# the order in which the re-plan takes primitives out: "left-out" (ratefit.importance_left_out:
# what leaving each out changes at its own centre, the training state evaluated there once
# (PairPasses.values_at: no second copy of the model on the device); those that say
# what their neighbours say go first) or "weight" (ratefit.importance: weight x sigma volume, the
# order before). On one H200 the weight order's cut of 24 / 36 % at CR 10 took the sample PSNR of
# mni_icbm152 / inia19 from 39.84 / 51.95 to 35.58 / 47.97 dB, regained only by iteration 750 / 600
# of 1,500, and mni_icbm152 ended 3 dB under a float32 model trained at the final N from the start
# (accuracy/sweep_round3b_h200.json). Left out against weight, CPU (accuracy/cut_order48*_cpu.json:
# vortex, interface, bubbles 48^3, 400 iterations, 8,192 samples, cuts of 23-37 %): final PSNR CR 10
# +0.26 / +1.79 / +0.01 dB, CR 30 +1.61 / +1.20 / +0.10; pruning float32 models by 30 % offline
# (accuracy/prune_order_*_cpu.json, "loo-hole") cost 0.37 / 1.11 / 8.14 / 1.54 dB on mni_icbm152,
# mean_reg2mean, vortex and interface 96^3 against 0.92 / 1.76 / 9.12 / 2.02. Not yet measured in a
# GPU encode (sweep.py variant cut-weight is the order before)
CUT_ORDER = "left-out"
# a second look half-way from the re-plan to the end (iteration (T + K) / 2), off: the rest of the
# run is then as long as the span since the re-plan and is expected to gain what that span gained
# (REPLAN_LATE_EXTRAPOLATE x; nothing where it lost); where the model would code at more bits than
# the re-plan planned for, the least important of the primitives still in are taken out so that it
# fits at those depths (at most REPLAN_MAX_CUT of them). On the histories of 86 encodes (three MRIs
# at CR 10-1000, vortex and interface 512^3 at CR 100-1000, five sample strata; H200,
# accuracy/sweep_*_err_h200.json, sweep_*_float2_h200.json) it asks for more bits on exactly the 10
# rows whose export coded over 4 % above budget and dropped bits there, at the end's depths on all
# 10, and on none of the 76 others. Encoded (accuracy/sweep_*_late_h200.json), what it took out
# was not filled in by the last 37 % of the run: mni_icbm152 CR 10 45.26 -> 42.47 dB (15 % cut),
# the interface at 512^3 CR 100 / 300 63.47 -> 51.80 / 59.81 -> 51.65, CR 1000 48.01 -> 49.88;
# the rows it left alone came out bit for bit the same. Dropping bits at the end costs less
REPLAN_LATE = False
REPLAN_LATE_EXTRAPOLATE = 1.0
# the bit depths a refined model is coded at: "accuracy" (bits_for_psnr of its sample PSNR) or
# "sizing" (those N was sized for; more only where the budget leaves room)
REFINED_BITS = "accuracy"
# where the re-plan held bits back (REPLAN_MAX_CUT: its planned accuracy below the expected), the
# fit to the byte budget starts from the re-plan's depths where they are below the accuracy's
# (adding bits while they fit) rather than from the accuracy's (dropping bits, then trying the
# prune shares against it): the model was cut to fit at those depths. Measured on one H200 on the
# three rows that held bits back of ten (interface 512^3 at CR 100 / 300 / 1000; vortex 512^3 at
# CR 300 / 1000 do not): the same models bit for bit (N, bytes and PSNR equal) in 8 / 5 / 5
# codings instead of 22 / 19 / 16, the encode 24.96 -> 21.02, 10.93 -> 10.19, 6.83 -> 6.35 s
# (benchmarks/results/speed/profile_heldstart_*_h200.json)
REFINED_HELD_START = True
REFIT_MIN_ITERATIONS = 30
REFIT_LR = 0.3
REFIT_MIN_PRUNED = 0.01


def held_start(note: dict, plan: dict | None) -> dict[str, int]:
    """The depths a refined model's fit starts from: ``note``'s (``accuracy_bits``), or each the
    lower of those and the re-plan's where :data:`REFINED_HELD_START` and the re-plan held bits
    back (``note`` then says so under ``held_by_replan``)."""
    bits = dict(note["bits"])
    if not REFINED_HELD_START or plan is None or plan["planned_psnr_db"] >= plan["expected_psnr_db"]:
        return bits
    held = {k: min(v, plan["bits"][k]) for k, v in bits.items()}
    if held != bits:
        note["held_by_replan"] = held
    return held


def replan_workers() -> int:
    """How many of the re-plan's codings run at once (:data:`REPLAN_WORKERS`)."""
    if REPLAN_WORKERS > 0:
        return int(REPLAN_WORKERS)
    return max(1, (os.cpu_count() or 1) // 4)


class Replan:
    """The re-plan and refit steps of :class:`~warpgauss.encoding.driver.run.EncodeRun` (mixed in: they read
    and change the run's state)."""

    # the run's state these steps read and change (set by EncodeRun.__init__ and its stages)
    opts: EncodeOptions
    enc: str
    budget_bytes: int | None
    header: dict
    dv: Any
    model: Model | None
    refined_fit: dict | None
    replan: dict | None
    replan_half: float | None
    skip: Callable[..., None]
    stored: Callable[[Model], tuple[Model, dict | None]]

    def replan_iteration(self, deadline: float | None) -> int | None:
        """The iteration after which a coded byte budget's N is re-planned (see :data:`REPLAN_AT`),
        or None where it is not: no coded byte budget, a warm start, a time budget."""
        cfg = self.opts.refine
        if self.enc != "coded" or self.budget_bytes is None or REPLAN_AT <= 0 or self.opts.init is not None:
            return None
        if deadline is not None or cfg.iterations < REPLAN_MIN_ITERATIONS:
            return None
        return max(1, int(round(REPLAN_AT * cfg.iterations)))

    def replan_n(self, refiner) -> None:
        """N for the bit depths the model's accuracy needs: at :data:`REPLAN_AT` of the iterations
        the current model is coded at the depths of its expected final sample PSNR;
        where that (times :data:`REPLAN_GROWTH`) exceeds the budget, the least important
        primitives are taken out (:meth:`Refiner.silence`) and the others refine on to fill in."""
        at = float(refiner.losses()["sample_psnr_db"])
        # the sample PSNR grows about linearly in log(iterations): what it gained from K/2 to K,
        # times log2(T / K), is what the rest of the run adds (at least REPLAN_REST_GAIN_DB)
        half = self.replan_half if self.replan_half is not None and math.isfinite(self.replan_half) else at
        t_total, k = self.opts.refine.iterations, refiner.iteration
        rest = max(REPLAN_REST_GAIN_DB, (at - half) * REPLAN_EXTRAPOLATE * math.log2(t_total / k))
        expected = at + min(rest, REPLAN_MAX_GAIN_DB)
        t = time.perf_counter()
        cut = self._cut_to(refiner, expected)
        self.replan = {"iteration": k, "sample_psnr_db": at, "sample_psnr_db_at_half": half, **cut, "seconds": time.perf_counter() - t}

    def replan_late_iteration(self, first: int) -> int | None:
        """The iteration of the late re-plan (see :data:`REPLAN_LATE`): half-way from the re-plan
        at ``first`` to the end, or None where it is off."""
        t_total = self.opts.refine.iterations
        late = (t_total + first) // 2
        return late if REPLAN_LATE and first < late < t_total else None

    def replan_late(self, refiner) -> None:
        """The late re-plan (see :data:`REPLAN_LATE`): where the model, expected to gain as much
        again as since the re-plan, would code at more bits than that planned for, the least
        important primitives still in are taken out so that it fits at those depths. The report's
        ``coded_replan.late`` says what it saw and did."""
        from ...format.ratefit import bits_for_psnr

        first = self.replan
        if first is None:  # no re-plan in this session (a resumed run): nothing to extrapolate from
            return
        at = float(refiner.losses()["sample_psnr_db"])
        gain = max(0.0, at - first["sample_psnr_db"]) * REPLAN_LATE_EXTRAPOLATE
        expected = at + min(gain, REPLAN_MAX_GAIN_DB)
        late: dict[str, Any] = {"iteration": refiner.iteration, "sample_psnr_db": at, "expected_psnr_db": expected}
        if bits_for_psnr(expected)[1] > first["bits_added"]:
            late.update(self._cut_to(refiner, expected))
        else:
            late.update(n_before=refiner.n_live, n_after=refiner.n_live, bits_added=first["bits_added"])
        first["late"] = late

    def _cut_to(self, refiner, expected: float) -> dict[str, Any]:
        """Take the least important of the primitives still in out of ``refiner`` so that the
        model codes within the budget (times :data:`REPLAN_GROWTH`) at the depths of ``expected``
        (fewer bits while more than :data:`REPLAN_MAX_CUT` would go); what was planned and done."""
        from ...format.coded import BITS_REFERENCE_DB, DB_PER_BIT
        from ...format.ratefit import bits_for_psnr
        from ...format.wgs import payload_size, wgs_bytes

        assert self.budget_bytes is not None
        budget = self.budget_bytes
        n = refiner.n_live
        params = refiner.model_params()[:n]

        def plan(planned: float) -> dict[str, Any]:  # the model coded at the depths of ``planned``
            bits, extra = bits_for_psnr(planned)
            data = wgs_bytes(params, self.header, encoding="coded", bits=bits)
            size, payload = len(data), payload_size(data)
            head = size - payload
            predicted = head + payload * REPLAN_GROWTH
            keep = n
            if predicted > budget * (1.0 + REPLAN_TOLERANCE):
                keep = max(1, int(n * (budget - head) / (payload * REPLAN_GROWTH)))
            return {"planned": planned, "bits": bits, "extra": extra, "size": size, "predicted": predicted, "keep": keep}

        def enough(r: dict) -> bool:  # few enough taken out, or no bit left to drop
            return r["keep"] >= (1.0 - REPLAN_MAX_CUT) * n or r["extra"] == 0

        # the depths of the expected accuracy, one bit fewer on every attribute while they would
        # cut too many: after the first, the fewer-bit codings run REPLAN_WORKERS at a time (the
        # same decision: the first of them, in order, that is enough)
        r = plan(expected)
        rest = [BITS_REFERENCE_DB + e * DB_PER_BIT for e in range(r["extra"] - 1, -1, -1)]
        workers = max(1, min(len(rest), replan_workers()))
        while not enough(r) and rest:
            wave, rest = rest[:workers], rest[workers:]
            if len(wave) == 1:
                results = [plan(wave[0])]
            else:
                with ThreadPoolExecutor(max_workers=len(wave)) as ex:
                    results = list(ex.map(plan, wave))
            r = next((x for x in results if enough(x)), results[-1])
        planned, bits, extra, keep, predicted = r["planned"], r["bits"], r["extra"], r["keep"], r["predicted"]
        if keep < n:
            order = np.argsort(self._cut_importance(refiner, params), kind="stable")  # least important first
            refiner.silence(order[: n - keep])
        return {
            "expected_psnr_db": expected,
            "planned_psnr_db": planned,  # below expected where REPLAN_MAX_CUT held the bits back
            "bits": bits,
            "bits_added": extra,
            "coded_bytes_now": r["size"],
            "predicted_bytes": predicted,
            "n_before": n,
            "n_after": keep,
        }

    def _cut_importance(self, refiner, params: np.ndarray) -> np.ndarray:
        """Each live primitive's importance for the re-plan's cut, by :data:`CUT_ORDER`."""
        from ...format.ratefit import importance, importance_left_out

        if CUT_ORDER == "weight":
            return importance(params)
        if CUT_ORDER != "left-out":
            raise ValueError(f"replan.CUT_ORDER must be 'weight' or 'left-out', not {CUT_ORDER!r}")
        value, density = refiner.passes.values_at(params[:, 0:3])
        return importance_left_out(params, value, density)

    def refit_pruned(self, refined: Model, cap: float, deadline: float | None) -> None:
        """A model pruned to its byte budget, refined again briefly without the pruned primitives
        (see :data:`REFIT_SHARE`) and fitted once more; the report's ``coded_fit.refit`` says so."""
        from ..refine import Refiner

        assert self.model is not None and self.refined_fit is not None  # refine() stored the refined model
        fit, kept = self.refined_fit, self.model.kept_rows
        cfg = self.opts.refine
        if kept is None or fit["pruned"] <= REFIT_MIN_PRUNED * refined.n or REFIT_SHARE <= 0:
            return
        if deadline is not None and time.perf_counter() >= deadline:
            self.skip("refit of the pruned model", "the time budget is spent", pruned=fit["pruned"])
            return
        iterations = max(REFIT_MIN_ITERATIONS, int(round(REFIT_SHARE * cfg.iterations)))
        rcfg = dataclasses.replace(
            cfg, iterations=iterations, lr=cfg.lr * REFIT_LR, target_psnr=None, plateau_db=None, budget_samples=False
        )
        t0 = time.perf_counter()
        refiner = Refiner(self.dv, refined.params[kept], rcfg, self.opts.seed, self.opts.allocation.scale_min, cap)
        history = refiner.run(log_every=max(iterations, 1), deadline=deadline)
        again = Model(refiner.model_params(), self.header)
        again.coded_bits = fit["bits"]
        self.model, refit = self.stored(again)
        assert refit is not None
        first = {k: fit[k] for k in ("steps", "pruned", "bytes", "first_bytes", "bits")}
        self.refined_fit = {
            **refit,
            "pruned": fit["pruned"] + refit["pruned"],
            "steps": fit["steps"] + refit["steps"],
            "first_bytes": fit["first_bytes"],
            "refit": {
                "iterations": refiner.iteration,
                "lr_scale": REFIT_LR,
                "seconds": time.perf_counter() - t0,
                "first_fit": first,
                "pruned_after": refit["pruned"],
                "sample_psnr_db": history[-1].get("sample_psnr_db") if history else None,
            },
        }
