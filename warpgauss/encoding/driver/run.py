"""The staged encoder driver: S1a-S1e, S1x, S2 and EV of one normalised field (:func:`encode_field`),
each stage a method of :class:`EncodeRun`, timed and memory-profiled.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ...core.profiling import StageRecorder
from ...errors import WarpgaussError
from ...field.analysis import Field
from ...format.model import Model
from ..allocate import allocate
from . import replan
from .checkpoints import Checkpoints, stop_on_sigint
from .options import EncodeOptions, encoding_of, header_for
from .report import budget_facts, run_facts
from .sizing import coded_budget, resolve_budget, target_bytes

# --time-budget is the whole call's (reading to writing, the kernels' compile not counted):
# refinement ends early enough to leave this share of it, and TAIL_CODINGS codings of the model
# at the pilot's measured speed, for what follows (the fit to the byte budget, evaluation, writing).
# The fit codes on threads, several codings at a time: one H200 host, the three MRIs at CR 100 with
# --time-budget 1 / 2 / 4 (results/speed/profile_time_budget_mri_h200.json) fitted in 0.06-0.33 s,
# at most 4.9 of the pilot's codings (mean_reg2mean at 1 s: 16 codings of the analytic model in
# 0.37 s, a coding 0.067 s; results/speed/host_profile_mean100_budget1_h200.json). At 8 the reserve
# (0.54 s there) left that call no iteration at all (26.51 dB, the whole call 0.78 s of its 1 s),
# and every call of those nine ended 13-35 % short of its budget
TAIL_SHARE = 0.05
TAIL_CODINGS = 5


def encode_field(
    f: Field,
    opts: EncodeOptions,
    *,
    device: str | None = None,
    timer: StageRecorder | None = None,
    input_info: dict | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    on_stats: Callable[[dict], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
    log_every: int = 25,
    analytic_output=None,
    force: bool = False,
    cache: dict | None = None,
    volume_on_host: bool = False,
    peers: list[str] | None = None,
) -> Model:
    """Stages S1a-S1e, S1x, S2 and EV on a normalised field; returns the model with its report.

    The body is the paper's stage table; each stage is a method of :class:`EncodeRun`, which
    also holds the skip decisions (the report's ``skipped`` list) and assembles the report.

    Args:
        f: Output of stage P.
        opts: Encoding options (budget or ratio, seed, allocation knobs).
        device: Warp device (None: CUDA when present, else CPU).
        timer: Stage recorder (stage P may already be in it).
        input_info: Input description for the report.
        evaluate: Run stage EV.
        full_eval: Evaluate on the full grid instead of 500,000 sampled voxels.
        on_stats: Optional callback(stats dict), called as soon as the structure statistics exist.
        on_progress: Optional callback(iteration, total, losses) during refinement.
        log_every: Iterations between loss records (and progress calls).
        analytic_output: If given, also write the analytic (pre-refinement) model there (S1x).
        force: Overwrite ``analytic_output`` if it exists.
        cache: A dict shared by encodes of the same field on the same device (a budget ladder):
            the device volume and structure statistics of the first are reused (S1a skipped).
        volume_on_host: Keep the volume in pinned host memory, read by a GPU's kernels over the
            bus (the model whole on the device); the report's ``volume_memory`` says where it was.
        peers: Other devices that refine the same model beside ``device`` (S2), each drawing its
            share of the samples (:mod:`warpgauss.encoding.refine.replicas`).
    """
    run = EncodeRun(f, opts, device, timer, evaluate, full_eval, analytic_output)
    run.volume_on_host = volume_on_host
    run.peers = list(peers or [])
    run.analyse(cache, on_stats)  # S1a   occupancy, gradients, structure statistics
    run.size_coded()  # S1p   coded size pilot (a coded byte budget only)
    run.allocate()  # S1b-e seeds, shapes, values and weights
    run.analytic_model(force)  # S1x   the analytic model (and --save-analytic)
    run.check_target()  # EVa   --target-psnr: is refinement needed at all?
    run.refine(on_progress, log_every)  # S2    refinement
    run.evaluate()  # EV    PSNR; keep the better of the two models
    return run.result(input_info)  # the model, its file size and its report


class EncodeRun(replan.Replan):
    """One encode's state between the stages of :func:`encode_field`, the skip decisions (each
    recorded in ``skipped`` with why) and the report assembly."""

    def __init__(self, f: Field, opts: EncodeOptions, device, timer, evaluate: bool, full_eval: bool, analytic_output):
        from ...core.warp import resolve_device, warp
        from ...format.wgs import header_size

        self.f = f
        self.enc = encoding_of(opts)
        self.budget_bytes = target_bytes(f, opts)  # the file size budget, or None for an explicit N
        self.header = header_for(f, opts)
        self.n = resolve_budget(f, opts, header_size(self.header, 1 << 40, encoding=self.enc))
        self.wp = warp()
        self.dev = resolve_device(device)
        self.voxels = int(np.prod(f.shape_xyz))
        self.base_refine = opts.refine
        scaled = opts.refine.for_budget(self.n, self.voxels, self.dev)
        if scaled is not opts.refine:  # more samples for a large budget or a GPU: the header says so
            opts = dataclasses.replace(opts, refine=scaled)
            self.header = header_for(f, opts)
            self.n = resolve_budget(f, opts, header_size(self.header, 1 << 40, encoding=self.enc))
        self.opts = opts
        self.timer = timer or StageRecorder()
        self.timer.device = self.dev
        self.skipped: list[dict] = []
        self.do_evaluate, self.full_eval = evaluate, full_eval
        self.sizing: dict | None = None
        self.analytic_fit: dict | None = None
        self.refined_fit: dict | None = None
        self.coded_bits_note: dict | None = None
        self.refinement: dict = {"iterations": 0}
        self.replan: dict | None = None  # the re-plan of N during refinement (coded byte budgets)
        self.time_budget_note: dict | None = None  # how --time-budget was shared (budget_deadline)
        self.replan_half: float | None = None  # the sample PSNR half-way to the re-plan
        self.early_eval: dict | None = None
        self.early_eval_s = 0.0  # seconds the early evaluation took
        self.start_eval: dict | None = None  # a warm start scored before refinement (to choose warm or cold)
        self.start_choice: dict | None = None
        self.evaluation: dict = {}
        # a coded byte budget fits the analytic model (several codings) only where it may be the
        # result: no refinement, an --analytic-output file, or a refined model that scores below it
        self.fit_later = self.enc == "coded" and self.budget_bytes is not None and opts.refine.iterations > 0 and analytic_output is None
        self.analytic_output = analytic_output
        self.volume_on_host = False  # encode_field's volume_on_host
        self.peers: list[str] = []  # encode_field's peers: S2 on these devices too

    def skip(self, what: str, why: str, **facts) -> None:
        self.skipped.append({"what": what, "why": why, **facts})

    def stored(self, m: Model) -> tuple[Model, dict | None]:
        """The model as the file will hold it (coded: fitted to the byte budget)."""
        if self.enc == "coded" and self.budget_bytes is not None:
            t = time.perf_counter()
            if self.opts.time_budget is not None or self.opts.deadline is not None:
                # on a time budget the first fit is the result: the choice below costs up to 4x
                # its codings and an evaluation each (mni_icbm152 CR 10 on one H200: 25 codings, 2.9 s)
                self.skip("coded fit choice", "a time budget: the first fit that meets the bytes is kept, pruning is not tried against it")
                fitted, info = m.fit_bytes(self.budget_bytes)
            else:
                # where bits would be dropped, pruning instead is tried too and the better PSNR kept
                fitted, info = m.fit_bytes(self.budget_bytes, score=lambda fitted: float(self._evaluate(fitted, full=False)["psnr_db"]))
            return fitted, {**info, "seconds": time.perf_counter() - t}
        m = m.stored(self.enc)
        m.format = self.enc
        return m, None

    def budget_deadline(self, now: float, compile_s: float, eval_s: float = 0.0) -> float:
        """When refinement must end for the whole call to keep ``--time-budget``: the call's start
        plus the budget (and the kernels' compile, which it does not count), less a reserve for
        what follows refinement: :data:`TAIL_SHARE` of the budget, :data:`TAIL_CODINGS` codings
        of the model at the pilot's measured seconds a primitive (at least the pilot's own coding
        time: a coding has a fixed cost) and ``eval_s``, the measured evaluation of the analytic
        model, for the final model's."""
        opts = self.opts
        assert opts.time_budget is not None
        start = now if opts.budget_start is None else opts.budget_start
        sizing = self.sizing or {}
        coding = max(sizing.get("coding_seconds_per_primitive", 0.0) * self.n, sizing.get("coding_seconds", 0.0))
        tail = TAIL_SHARE * opts.time_budget + TAIL_CODINGS * coding + eval_s
        self.time_budget_note = {
            "seconds": opts.time_budget,
            "spent_before_refinement_s": now - start - compile_s,
            "compile_s": compile_s,
            "reserved_after_s": tail,
            "reserved_evaluation_s": eval_s,
            "reserved_coding_s": TAIL_CODINGS * coding,
        }
        return start + compile_s + opts.time_budget - tail

    def _budget_eval_s(self) -> float:
        """On a time budget: evaluate the analytic model now (stage EV would, after refinement)
        and return the seconds it took, the reserve for evaluating the final model; 0 when
        nothing will be evaluated or the analytic model's figures exist already."""
        if not self.do_evaluate or self.opts.init is not None:
            return 0.0
        if self.early_eval is None:
            self._evaluate_analytic_early()
        return self.early_eval_s

    def _evaluate_analytic_early(self) -> None:
        """Stage EV's figures of the analytic model before refinement (EV reuses them), and the
        seconds they took."""
        t = time.perf_counter()
        self.early_eval = self._evaluate(self.analytic)
        self.early_eval_s = time.perf_counter() - t

    def _evaluate(self, m: Model, full: bool | None = None) -> dict:
        """Stage EV's figures for ``m`` (``full``: every voxel rather than the sample; default:
        as the run was asked)."""
        from ...field.evaluate import evaluate_field

        return evaluate_field(m.field(self.dev), self.f, full=self.full_eval if full is None else full)

    # -- S1a ---------------------------------------------------------------------------------
    def analyse(self, cache: dict | None, on_stats) -> None:
        from ...field.analysis import DeviceVolume, structure_stats

        f, dev = self.f, self.dev
        if cache is not None and cache.get("device") == dev and cache.get("field") is f:
            self.dv, self.stats = cache["dv"], cache["stats"]
            self.skip("S1a", "device volume and statistics reused from the previous budget of the ladder", seconds_saved=cache["seconds"])
        elif self.opts.init is not None or self.opts.deadline is not None:
            # a warm start allocates nothing, and an Encoder call on a time budget spends nothing on
            # figures only the report would show: the statistics are skipped
            with self.timer.stage("S1a", "the field on the device"):
                self.dv = DeviceVolume(f, dev, on_host=self.volume_on_host)
            self.stats = None
            why = (
                "warm start: no allocation needs them"
                if self.opts.init is not None
                else "an Encoder call on a time budget: only the report would show them"
            )
            self.skip("S1a structure statistics", why)
            return
        else:
            t0 = time.perf_counter()
            with self.timer.stage("S1a", "occupancy, gradients, structure statistics"):
                self.dv = DeviceVolume(f, dev, on_host=self.volume_on_host)
                self.stats = structure_stats(self.dv)
            if cache is not None:
                cache.update({"device": dev, "field": f, "dv": self.dv, "stats": self.stats, "seconds": time.perf_counter() - t0})
        if on_stats is not None:
            on_stats(self.stats)

    # -- S1p ---------------------------------------------------------------------------------
    def size_coded(self) -> None:
        if self.enc != "coded" or self.budget_bytes is None:
            return
        with self.timer.stage("S1p", "coded size pilot"):
            self.n, self.sizing = coded_budget(self.dv, self.f, self.opts, self.header, self.budget_bytes, self.n)
            scaled = self.base_refine.for_budget(self.n, self.voxels, self.dev)
            if scaled != self.opts.refine:  # the samples follow the measured N, not its bound
                self.opts = dataclasses.replace(self.opts, refine=scaled)
                self.header = header_for(self.f, self.opts)

    # -- S1b-S1e -----------------------------------------------------------------------------
    def allocate(self) -> None:
        init = self.opts.init
        if init is None:
            self.params, self.facts = allocate(self.dv, self.n, self.opts.seed, self.opts.allocation, self.timer)
            return
        if init.shape != (self.n, 12):
            raise WarpgaussError(
                f"a warm start needs a model of the same budget: the previous model has {init.shape[0]:,} Gaussians, this encode {self.n:,}; "
                "give --budget N of the previous model (or encode cold)"
            )
        self.params = np.array(init, np.float32, copy=True)
        self.facts = {"warm_start": True, "n": self.n}
        self.skip("S1b-S1e allocation", "warm start: the previous timestep's model is the starting point")
        as_given = self.opts
        if self.opts.motion:
            from ..motion import WARM_LR_SCALE, compensate

            with self.timer.stage("S1m", "motion compensation of the warm start"):
                self.params, self.facts["motion"] = compensate(self.params, self.dv)
            # the rate of the refinement that follows (see WARM_LR_SCALE for what was measured)
            if WARM_LR_SCALE != 1.0:
                cfg = self.opts.refine
                self.opts = dataclasses.replace(self.opts, refine=dataclasses.replace(cfg, lr=cfg.lr * WARM_LR_SCALE))
                self.header = header_for(self.f, self.opts)  # the file says which rates refined it
            self.facts["motion"]["lr_scale"] = WARM_LR_SCALE
        else:
            self.skip("S1m motion compensation", "motion=False: the previous model starts where it was")
        ref = self.opts.cold_start_psnr
        if ref is None:
            return
        with self.timer.stage("S1w", "warm or cold: score the warm start"):
            self.start_eval = self._evaluate(Model(self.params, self.header))
        start = self.start_eval["psnr_db"]
        warm = start >= ref
        self.start_choice = {
            "warm": warm,
            "warm_start_psnr_db": start,
            "last_cold_start_psnr_db": ref,
            "why": "the warm start scores at least what the last cold start's allocation did"
            if warm
            else "the warm start scores below what the last cold start's allocation did: the field changed too much",
        }
        if not warm:  # allocate afresh (the warm start's score is not the start model's any more)
            self.start_eval = None
            self.skipped = [x for x in self.skipped if x["what"] != "S1b-S1e allocation"]
            self.opts = dataclasses.replace(as_given, init=None, evaluate_start=True)
            self.header = header_for(self.f, self.opts)
            self.params, self.facts = allocate(self.dv, self.n, self.opts.seed, self.opts.allocation, self.timer)

    # -- S1x ---------------------------------------------------------------------------------
    def analytic_model(self, force: bool) -> None:
        with self.timer.stage("S1x", "analytic model"):
            analytic = Model(self.params, self.header)
            analytic.coded_bits = None if self.sizing is None else self.sizing["bits"]  # the depths N was sized for
            self.analytic, self.analytic_fit = (analytic, None) if self.fit_later else self.stored(analytic)
            if self.analytic_output is not None:
                self.analytic.save(self.analytic_output, encoding=self.enc, force=force)
        if self.fit_later:
            self.skip(
                "S1x rate control of the analytic model",
                "it is fitted to the byte budget only if the refined model scores below it; until then it is evaluated as allocated",
            )
        self.model = self.analytic

    # -- EVa: --target-psnr ------------------------------------------------------------------
    def check_target(self) -> None:
        cfg = self.opts.refine
        if not (cfg.iterations > 0 and cfg.target_psnr is not None and self.do_evaluate):
            return
        with self.timer.stage("EVa", "analytic model evaluation (for --target-psnr)"):
            self._evaluate_analytic_early()
        assert self.early_eval is not None
        if self.early_eval["psnr_db"] < cfg.target_psnr:
            return
        self.skip(
            "S2 refinement", f"the analytic model already reaches the target ({self.early_eval['psnr_db']:.2f} >= {cfg.target_psnr:g} dB)"
        )
        self.refinement = {
            "iterations": 0,
            "stop": {"reason": "target PSNR reached by the analytic model", "iterations_skipped": cfg.iterations},
        }
        if self.fit_later:  # it is the result: fitted to the budget and scored as stored
            self.analytic, self.analytic_fit = self.stored(self.analytic)
            self.model = self.analytic
            self.early_eval = self._evaluate(self.analytic)

    # -- S2 ----------------------------------------------------------------------------------
    def refine(self, on_progress, log_every: int) -> None:
        if self.opts.refine.iterations == 0:
            self.skip("S2 refinement", "iterations = 0: the analytic model is the result")
            return
        if self.refinement.get("stop"):
            return
        from ..refine import Refiner, load_kernels

        opts, cfg, dev, refinement = self.opts, self.opts.refine, self.dev, self.refinement
        cap = opts.allocation.resolved_cap(self.f.shape_xyz)
        eval_s = 0.0
        if opts.time_budget is not None and not opts.resume:
            with self.timer.stage("EVa", "analytic model evaluation (measures the time budget's reserve for the final one)"):
                eval_s = self._budget_eval_s()
        with self.timer.stage("S2", "refinement"):
            compiled = time.perf_counter()
            load_kernels(dev)
            stage_start = time.perf_counter()
            compile_s = stage_start - compiled  # the time budget does not count the kernels' compile
            refiner = Refiner(self.dv, self.params, cfg, opts.seed, opts.allocation.scale_min, cap)
            refiner.replicate(self.peers)
            self._sampling_skips(refiner)
            ckpt = Checkpoints(opts, self.params, cfg, dev)
            if opts.resume:
                ckpt.resume(refiner)
            self._self_test(refiner)
            if cfg.target_psnr is not None or cfg.plateau_db is not None:
                refiner.set_validation(self.f)
            t0 = time.perf_counter()
            deadline = opts.deadline
            if opts.time_budget is not None and not opts.resume:
                deadline = self.budget_deadline(stage_start, compile_s, eval_s)
            ckpt.start(t0)
            after_step = ckpt.maybe_save
            replan_at = self.replan_iteration(deadline)
            if replan_at is not None:
                late_at = self.replan_late_iteration(replan_at)

                def after_step(r, save=ckpt.maybe_save, at=replan_at, late=late_at):
                    if r.iteration == at // 2:
                        self.replan_half = float(r.losses()["sample_psnr_db"])
                    elif r.iteration == at:
                        self.replan_n(r)
                    elif r.iteration == late:
                        self.replan_late(r)
                    save(r)

            with stop_on_sigint(refiner):
                history = refiner.run(progress=on_progress, log_every=log_every, deadline=deadline, after_step=after_step)
            seconds = time.perf_counter() - t0
            if refiner.interrupted:
                ckpt.save(refiner)
            end = {}
            if opts.deadline is not None:  # as for the statistics: an in situ call pays for no figure only the report shows
                self.skip("end-of-training estimate", "an Encoder call on a time budget: only the report would show it")
            elif not refiner.interrupted:
                end = refiner.end_estimate()
            params = refiner.model_params()
            refined = Model(params[: refiner.n_live], self.header)  # without those the re-plan took out
            if replan.REFINED_BITS == "sizing" and self.sizing is not None:  # the depths N was sized for
                refined.coded_bits = dict(self.sizing["bits"])
            elif self.enc == "coded" and history:
                from ...format.ratefit import accuracy_bits  # finer grids for a more accurate model

                self.coded_bits_note = accuracy_bits(history[-1].get("sample_psnr_db"))
                refined.coded_bits = replan.held_start(self.coded_bits_note, self.replan)
            self.model, self.refined_fit = self.stored(refined)
            if self.refined_fit is not None and not refiner.interrupted:
                self.refit_pruned(refined, cap, deadline)
        sessions = ckpt.sessions + [{"from_iteration": ckpt.start_iteration, "to_iteration": refiner.iteration, "seconds": seconds}]
        total = sum(x["seconds"] for x in sessions)
        refinement.update(
            {
                "time_budget": refiner.budget
                if refiner.budget is None or self.time_budget_note is None
                else {**refiner.budget, "call": self.time_budget_note},
                "iterations": refiner.cfg.iterations,
                "samples": refiner.m if refiner.replicas is None else refiner.replicas.total,
                "samples_rule": self.base_refine.samples_rule(self.n, self.voxels, dev)[1],
                "seconds": total,
                "sessions": sessions,
                "iterations_done": refiner.iteration,
                "interrupted": refiner.interrupted,
                "checkpoint": ckpt.report(),
                "contacts_per_primitive": refiner.contacts,
                "lr_touch_scale": refiner.touch_scale,
                "ms_per_iteration": 1000 * total / max(refiner.iteration, 1),
                **refiner.step_counts(),  # skipped_nonfinite_updates, deferred_updates, rebins, relocated
                "forward_pass": refiner.forward_pass,
                "error_stratum": refiner.sampler.error_report(),
                "cuda_graph": refiner.use_graph,
                "cuda_graph_error": refiner.graph_error,
                "cuda_graph_captures": refiner.captures,
                "cell_list_entries": refiner.passes.list_entries if refiner.passes.listed else None,
                "strata_samples": dict(zip(("high", "mid", "uniform"), refiner.strata)),
                "uniform_support_share": refiner.support_share(),
                "loss_history": history,
                "end_estimate": end,
                **({} if refiner.replicas is None else {"replicas": refiner.replicas.report()}),  # --devices
            }
        )
        if refiner.stop_reason is not None:
            left = refiner.cfg.iterations - refiner.iteration
            refinement["stop"] = {
                "reason": refiner.stop_reason,
                "at_iteration": refiner.iteration,
                "iterations_skipped": left,
                "seconds_saved_estimate": left * total / max(refiner.iteration, 1),
                "checks": refiner.checks,
            }
            self.skip(
                f"S2 iterations {refiner.iteration}-{refiner.cfg.iterations}",
                refiner.stop_reason,
                seconds_saved=refinement["stop"]["seconds_saved_estimate"],
            )
        elif refiner.checks:
            refinement["checks"] = refiner.checks
        if refiner.interrupted:
            self.do_evaluate = False
            self.skip("EV evaluation", f"interrupted at iteration {refiner.iteration}")

    def _sampling_skips(self, refiner) -> None:
        """Where the refiner draws no samples, and why (recorded before it runs)."""
        if refiner.uniform_occupied:
            occ = refiner.n_high + refiner.n_mid
            self.skip(
                "uniform samples in empty space",
                f"value_empty = 0: a sample where V <= 0.02 adds no loss; the uniform stratum is drawn among the {occ:,} occupied voxels",
                uniform_samples_moved_share=1.0 - occ / self.dv.field.values.size,
            )
        elif refiner.uniform_support:
            share = refiner.support_share()
            if share < 1.0:
                self.skip(
                    "uniform samples outside the model's support",
                    "no Gaussian's 5-sigma box (+2 voxels) reaches there: a sample would score 0 with no gradient; "
                    "the uniform stratum is drawn over the 4^3 bricks the boxes reach, re-marked at every re-bin",
                    share_skipped_at_start=1.0 - share,
                )
        if not refiner.partners:
            self.skip(
                "partner points",
                "smoothness weight 0: the partners serve only that term, so each iteration evaluates the samples alone (half the points)",
            )

    def _self_test(self, refiner) -> None:
        """The binned-vs-dense self-test: once per process and device (the kernels cannot change)."""
        from ..refine import SELF_TESTS, self_test

        dev = self.dev
        if self.opts.self_test and dev in SELF_TESTS:
            self.refinement["self_test"] = {**SELF_TESTS[dev], "reused": True, "seconds": 0.0}
            self.skip("self-test", "passed earlier in this process on this device", seconds_saved=SELF_TESTS[dev]["seconds"])
        elif self.opts.self_test:  # the self-test leaves the training state as it was
            t0 = time.perf_counter()
            self.refinement["self_test"] = self_test(refiner)
            self.refinement["self_test"]["seconds"] = time.perf_counter() - t0
            SELF_TESTS[dev] = dict(self.refinement["self_test"])
        else:
            self.skip("self-test", "--no-self-test")

    # -- EV ----------------------------------------------------------------------------------
    def evaluate(self) -> None:
        if not self.do_evaluate:
            if not self.refinement.get("interrupted"):
                self.skip("EV evaluation", "disabled by the caller")
            return
        evaluation = self.evaluation
        model = self.model
        assert model is not None  # allocate() or the warm start set it
        if self.opts.init is not None and not self.opts.evaluate_start and model is not self.analytic:
            with self.timer.stage("EV", "evaluation"):
                evaluation["analytic"] = self.start_eval
                evaluation["final"] = self._evaluate(model)
            evaluation["gain_db"] = None if self.start_eval is None else evaluation["final"]["psnr_db"] - self.start_eval["psnr_db"]
            if self.start_eval is None:
                self.skip("EV of the starting model", "an Encoder call on a time budget scores only the model it returns")
            return
        with self.timer.stage("EV", "evaluation"):
            evaluation["analytic"] = self.early_eval or self.start_eval or self._evaluate(self.analytic)
            if self.model is self.analytic:
                evaluation["final"] = evaluation["analytic"]
            else:
                t0 = time.perf_counter()
                evaluation["final"] = self._evaluate(model)
                share = evaluation["final"].get("bricks_evaluated_share")
                if share is not None and 0.0 < share < 1.0:
                    self.skip(
                        "empty 8^3 bricks in the full-grid evaluation",
                        "no Gaussian's 5-sigma box reaches them: written 0 without evaluation (exactly the model's value)",
                        share_skipped=1.0 - share,
                        seconds_saved_estimate=(time.perf_counter() - t0) * (1.0 - share) / share,
                    )
                self._keep_the_better(evaluation)
        evaluation["gain_db"] = evaluation["final"]["psnr_db"] - evaluation["analytic"]["psnr_db"]

    def _keep_the_better(self, evaluation: dict) -> None:
        """A refinement that scores below the analytic model (e.g. too few iterations for a large
        N) is discarded, the analytic model compared as it would be stored."""
        refined_db, analytic_db = evaluation["final"]["psnr_db"], evaluation["analytic"]["psnr_db"]
        if refined_db < analytic_db and self.fit_later:
            self.analytic, self.analytic_fit = self.stored(self.analytic)
            evaluation["analytic"] = self._evaluate(self.analytic)
            analytic_db = evaluation["analytic"]["psnr_db"]
        if refined_db < analytic_db:
            evaluation["discarded_refined"] = evaluation["final"]
            evaluation["final"] = evaluation["analytic"]
            self.model = self.analytic
            self.skip(
                "refined model",
                f"it scored {refined_db:.2f} dB, below the analytic model's {analytic_db:.2f} dB: the analytic model is the result",
            )

    # -- the report --------------------------------------------------------------------------
    def result(self, input_info: dict | None) -> Model:

        f, opts, model, dev = self.f, self.opts, self.model, self.dev
        assert model is not None  # allocate() or the warm start set it
        is_analytic = model is self.analytic
        fit = self.analytic_fit if is_analytic else self.refined_fit
        note = None if is_analytic else self.coded_bits_note
        replan_facts = None if is_analytic else self.replan
        model.report = {
            **run_facts(dev, input_info, f),
            "budget": budget_facts(model, opts, f, self.enc, self.budget_bytes, self.sizing, fit, replan_facts, note),
            "seed": opts.seed,
            "structure": self.stats,
            "allocation": self.facts,
            "refinement": self.refinement,
            "evaluation": self.evaluation,
            "psnr_db": self.evaluation.get("final", {}).get("psnr_db"),
            "interrupted": bool(self.refinement.get("interrupted")),
            "skipped": self.skipped,
        }
        if self.start_choice is not None:
            model.report["start_choice"] = self.start_choice
        if self.volume_on_host:
            where = "pinned host memory, read by the device's kernels over the bus" if self.dv.on_host else "host memory (the CPU device)"
            if not self.dv.on_host and str(dev).startswith("cuda"):
                where = "the device: the source was a device array already"
            model.report["volume_memory"] = {"where": where}
        return model
