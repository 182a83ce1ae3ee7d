"""Stage S2: fixed-budget refinement (closed-form gradients, Adam, stratified samples).

The count never changes: :class:`Refiner` owns the N primitives in the training
parameterisation (log-sigmas, unnormalised quaternion, weight logit) and each :meth:`Refiner.step`
draws samples, re-bins the primitives, evaluates the field, turns the loss into per-point
gradients, scatters them onto the primitives over the truncated pairs only, and takes one Adam
step. Every term of the loss (see :mod:`warpgauss.kernels.backward`) has a weight; 0 turns it off.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .allocate import rng_stream
from .analysis import DeviceVolume
from .errors import WarpgaussError

STRATA = (0.35, 0.40, 0.25)  # high (V > 0.4), occupied mid-range, uniform (SPEC section 3)
SAMPLER_SALT = 99_991  # keeps the sampler's RNG streams apart from the allocation's
BUDGET_PROBE = 5  # iterations timed to size a time-budgeted run
BUDGET_SAFETY = 0.9  # share of the remaining budget planned as iterations
MAX_BUDGET_ITERATIONS = 20_000  # more iterations than this gain nothing measurable


@dataclass
class LossWeights:
    """Weights of the loss terms (0 switches a term off).

    Measured (vortex, interface, bubbles at 40^3 with 1,200 Gaussians, 200-600 iterations, PSNR of
    the refined model): the density term costs 0.3-2.5 dB at 0.01 and more at 0.1, so it is kept
    only as a weak regulariser (0.001) against runaway overlap; smoothness at 1.0 costs 1-2 dB
    and off gains 0.2-0.5 dB, so it starts weak (0.01) and anneals to 0.0001; the anchor is
    neutral at 0.001 and costs 0.7-3 dB at 0.1; ``value_empty`` 0 (the paper supervises occupied
    samples only) loses 0.7 dB on the interface field, because full-field PSNR counts empty space,
    so empty samples are fitted too (1). The anisotropy and cap terms are stiff penalties that act
    only outside their bounds.
    """

    value_empty: float = 1.0
    density: float = 0.001
    smooth: float = 0.01
    smooth_final: float = 0.0001
    anchor: float = 0.001
    aniso: float = 1.0
    cap: float = 1.0


@dataclass
class RefineConfig:
    """Refinement schedule and optimiser settings.

    The base learning rate is the paper's 8e-3; each parameter group multiplies it and the rate
    decays geometrically to ``lr_decay`` of its start by the last iteration. Measured against a
    flat 8e-3 for every group (same fields as :class:`LossWeights`, 600 iterations): +3.7 dB
    vortex, +1.6 dB interface, +2.2 dB bubbles.

    Attributes:
        iterations: Adam steps (paper: 1,500; the "fast" time-budget mode: 300).
        samples: Samples per iteration (paper: 3,072), each with a smoothness partner.
        lr: Base learning rate (paper: 8e-3).
        lr_position, lr_scale, lr_rotation, lr_value, lr_weight: Per-group multipliers.
        lr_decay: Learning rate at the last iteration relative to the first (geometric decay).
        touch_ref: Sample-primitive contacts per primitive per iteration at and above which the
            full rates apply; below, rates scale by sqrt(contacts / touch_ref) (0 disables).
            When samples are few for N (3,072 samples for 1.4M primitives touch each one about
            0.4 times an iteration) every touch is a one-sample gradient that Adam turns into a
            full-size step. Measured on vortex 64^3 with 20,000 Gaussians and 128 samples (0.8
            contacts): full rates 37.7 -> 38.1 dB, 1/8 rate 45.9 dB, 1/4 45.5 dB; with 2,048
            samples (12.5 contacts) full rates reach 53.9 dB.
        replan_every: Iterations between re-planning the bin levels from the current radii.
        partner_distance: Range of the partner offset in voxels.
        split_cells: One thread per (point, neighbour cell) instead of per point, summing through
            atomics; None picks it on CUDA devices (one thread per sample leaves a GPU idle) and
            not on the CPU (where it only adds work, and the serial sums stay bit-reproducible).
    """

    iterations: int = 1500
    samples: int = 3072
    lr: float = 8e-3
    lr_position: float = 7.5
    lr_scale: float = 5.625
    lr_rotation: float = 5.625
    lr_value: float = 3.75
    lr_weight: float = 3.75
    lr_decay: float = 0.1
    touch_ref: float = 12.0
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-15
    replan_every: int = 100
    partner_distance: tuple[float, float] = (0.5, 1.5)
    split_cells: bool | None = None
    weights: LossWeights = field(default_factory=LossWeights)

    def to_dict(self) -> dict:
        return asdict(self)


# quality: measured on the H100 (benchmarks/results/quality_grid_h100.json, vortex and interface
# at 128^3 with 20,000 Gaussians, split-cell kernels): 1,500 x 12,288 gives +2.7 / +1.0 dB over
# the paper configuration in 7.1 / 4.7 s of refinement (paper: 2.2 / 1.7 s); doubling the samples
# again adds only 0.3-0.6 dB for twice the time, and doubling iterations instead gains the same.
PRESETS = {
    "paper": {"iterations": 1500, "samples": 3072},
    "fast": {"iterations": 300, "samples": 3072},
    "quality": {"iterations": 1500, "samples": 12288},
}


def stratum_counts(m: int, n_high: int, n_mid: int) -> tuple[int, int, int]:
    """Samples per stratum (high, mid, uniform): 35/40/25, an empty stratum's share going to the rest."""
    shares = [STRATA[0] if n_high else 0.0, STRATA[1] if n_mid else 0.0, STRATA[2]]
    total = sum(shares)
    m_high = int(round(m * shares[0] / total))
    m_mid = int(round(m * shares[1] / total))
    return m_high, m_mid, m - m_high - m_mid


class Refiner:
    """N primitives under refinement on one device.

    Args:
        dv: The normalised field on the device.
        params: (N, 12) model parameters (weight in slot 11), e.g. the analytic allocation.
        config: Schedule, learning rates, loss weights.
        seed: Seed of the sampler; same seed and device give the same result.
        scale_min, scale_cap: Scale range of the cap term (sigma in voxels).
    """

    def __init__(
        self,
        dv: DeviceVolume,
        params: np.ndarray,
        config: RefineConfig,
        seed: int,
        scale_min: float,
        scale_cap: float,
    ):
        from ._warp import warp
        from .field import GaussianField
        from .kernels import field as kf
        from .kernels import optim as ko

        from .kernels import backward as kb
        from .kernels import sampling as ks

        wp = warp()
        self._wp = wp
        for module in (kf, ko, kb, ks):  # compile now, so that no time budget pays for it
            wp.load_module(module, device=dv.device)
        self.dv, self.cfg, self.seed = dv, config, seed
        dev = self.device = dv.device
        if config.samples < 1 or config.iterations < 0:
            raise WarpgaussError("--samples must be >= 1 and --iterations >= 0")
        self.n = n = int(params.shape[0])
        model = wp.array(np.ascontiguousarray(params, np.float32), dtype=kf.vec12, device=dev)
        self.raw = wp.empty(n, dtype=kf.vec12, device=dev)
        wp.launch(ko.to_raw, dim=n, inputs=[model], outputs=[self.raw], device=dev)
        self.field = GaussianField(self.raw, dv.field.shape_xyz, device=dev, raw=True)
        self.log_min = math.log(scale_min)
        self.log_cap = math.log(scale_cap)
        self.m1 = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.m2 = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.grad = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.d_mu = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_ls = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_rot = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.d_a = wp.zeros(n, dtype=float, device=dev)
        self.d_w = wp.zeros(n, dtype=float, device=dev)
        self.reg_loss = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.skipped = wp.zeros(1, dtype=int, device=dev)
        m = self.m = int(config.samples)
        self.points = wp.zeros(2 * m, dtype=wp.vec3, device=dev)
        self.target = wp.zeros(m, dtype=float, device=dev)
        self.weight = wp.zeros(m, dtype=float, device=dev)
        self.occupied = wp.zeros(m, dtype=float, device=dev)
        self.value = wp.zeros(2 * m, dtype=float, device=dev)
        self.density = wp.zeros(2 * m, dtype=float, device=dev)
        self.pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.back_pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.g_value = wp.zeros(2 * m, dtype=float, device=dev)
        self.g_density = wp.zeros(2 * m, dtype=float, device=dev)
        self.point_loss = wp.zeros(m, dtype=wp.vec3, device=dev)
        self.num = wp.zeros(2 * m, dtype=float, device=dev)
        self.split = wp.get_device(dev).is_cuda if config.split_cells is None else bool(config.split_cells)
        self._build_strata()
        w = config
        self.lr = kf.vec12(
            *([w.lr * w.lr_position] * 3),
            *([w.lr * w.lr_scale] * 3),
            *([w.lr * w.lr_rotation] * 4),
            w.lr * w.lr_value,
            w.lr * w.lr_weight,
        )
        self.iteration = 0
        self.touch_scale = 1.0  # learning-rate factor from the contact density (see touch_ref)
        self.contacts = None

    def _build_strata(self) -> None:
        """Voxel lists of the high and mid strata, sorted so that sampling is deterministic."""
        from .kernels import sampling as ks

        wp, dv, dev = self._wp, self.dv, self.device
        counts = wp.zeros(2, dtype=int, device=dev)
        dummy = wp.zeros(1, dtype=int, device=dev)
        wp.launch(ks.strata_lists, dim=dv.values.shape, inputs=[dv.values, dv.mask, dv.has_mask, 0], outputs=[counts, dummy, dummy], device=dev)
        n_high, n_mid = (int(c) for c in counts.numpy())
        self.high = wp.zeros(max(2 * n_high, 2), dtype=int, device=dev)
        self.mid = wp.zeros(max(2 * n_mid, 2), dtype=int, device=dev)
        counts.zero_()
        wp.launch(ks.strata_lists, dim=dv.values.shape, inputs=[dv.values, dv.mask, dv.has_mask, 1], outputs=[counts, self.high, self.mid], device=dev)
        for lst, k in ((self.high, n_high), (self.mid, n_mid)):
            if k > 1:  # list order from atomics is arbitrary on a GPU
                vals = wp.zeros(2 * k, dtype=int, device=dev)
                wp.utils.radix_sort_pairs(lst, vals, k)
        self.n_high, self.n_mid = n_high, n_mid
        self.strata = stratum_counts(self.m, n_high, n_mid)

    def smooth_weight(self, it: int) -> float:
        """Smoothness weight annealed geometrically from strong to weak over the run."""
        w = self.cfg.weights
        if w.smooth <= 0.0:
            return 0.0
        t = it / max(self.cfg.iterations - 1, 1)
        return w.smooth * (max(w.smooth_final, 1e-12) / w.smooth) ** t

    def sample(self, it: int) -> None:
        from .kernels import sampling as ks

        wp, dv, dev = self._wp, self.dv, self.device
        m_high, m_mid, _ = self.strata
        pmin, pmax = self.cfg.partner_distance
        wp.launch(
            ks.draw_samples,
            dim=self.m,
            inputs=[
                dv.values,
                dv.mask,
                dv.has_mask,
                self.high,
                self.mid,
                max(self.n_high, 1),
                max(self.n_mid, 1),
                m_high,
                m_mid,
                rng_stream(self.seed, it, salt=SAMPLER_SALT),
                float(pmin),
                float(pmax),
            ],
            outputs=[self.points, self.target, self.weight, self.occupied],
            device=dev,
        )

    def forward_backward(self, it: int) -> None:
        """Field at the current samples, per-point gradients, pair scatter, chain rule -> self.grad."""
        from .kernels import backward as kb
        from .kernels import field as kf

        wp, dev, w = self._wp, self.device, self.cfg.weights
        f = self.field
        if self.split:
            for arr in (self.num, self.density, self.pairs):
                arr.zero_()
            wp.launch(
                kf.eval_points_split,
                dim=(2 * self.m, 27 * len(f.plan.sizes)),
                inputs=[self.points, f.prims],
                outputs=[self.num, self.density, self.pairs],
                device=dev,
            )
            wp.launch(kf.finish_values, dim=2 * self.m, inputs=[self.num, self.density], outputs=[self.value], device=dev)
        else:
            wp.launch(
                kf.eval_points_binned,
                dim=2 * self.m,
                inputs=[self.points, f.prims],
                outputs=[self.value, self.density, self.pairs],
                device=dev,
            )
        wp.launch(
            kb.point_grads,
            dim=self.m,
            inputs=[self.value, self.density, self.target, self.weight, self.occupied, self.m, w.value_empty, w.density, self.smooth_weight(it)],
            outputs=[self.g_value, self.g_density, self.point_loss],
            device=dev,
        )
        self.accumulate()
        wp.launch(
            kb.finish_grads,
            dim=self.n,
            inputs=[
                self.raw,
                f.prims.order,
                self.d_mu,
                self.d_ls,
                self.d_rot,
                self.d_a,
                self.d_w,
                self.dv.values,
                w.anchor,
                w.aniso,
                w.cap,
                math.log(3.0),
                self.log_cap,
                self.log_min,
            ],
            outputs=[self.grad, self.reg_loss],
            device=dev,
        )

    @property
    def pair_grads(self) -> tuple:
        """The per-primitive (cell order) gradient buffers the pair pass accumulates into."""
        return (self.d_mu, self.d_ls, self.d_rot, self.d_a, self.d_w)

    def accumulate(self, kernel=None, count: int | None = None) -> None:
        """Scatter the per-point gradients of the first ``count`` points (all by default).

        Args:
            kernel: A point-major pair kernel (the dense reference in the self-test); None for
                the refiner's own (split per cell on GPUs, point-major on the CPU).
            count: Points to scatter from, the first ``count`` of the buffers.
        """
        from .kernels import backward as kb

        wp, dev = self._wp, self.device
        for arr in self.pair_grads:
            arr.zero_()
        count = 2 * self.m if count is None else count
        dim = count
        if kernel is None and self.split:
            kernel = kb.accumulate_pairs_split
            dim = (count, 27 * len(self.field.plan.sizes))
            self.back_pairs.zero_()
        elif kernel is None:
            kernel = kb.accumulate_pairs
        wp.launch(
            kernel,
            dim=dim,
            inputs=[self.points, self.value, self.density, self.g_value, self.g_density, self.field.prims],
            outputs=[*self.pair_grads, self.back_pairs],
            device=dev,
        )

    def step(self) -> None:
        """One iteration: sample, re-bin, forward, backward, Adam."""
        from .kernels import optim as ko

        wp, cfg, it = self._wp, self.cfg, self.iteration
        self.sample(it)
        replan = it % max(cfg.replan_every, 1) == 0
        self.field.update(replan=replan)
        self.forward_backward(it)
        if replan and cfg.touch_ref > 0:  # re-estimate the contact density with the bins
            self.contacts = float(self.pairs.numpy()[: self.m].astype(np.float64).sum()) / self.n
            self.touch_scale = min(1.0, math.sqrt(self.contacts / cfg.touch_ref))
        t = it + 1
        wp.launch(
            ko.adam_step,
            dim=self.n,
            inputs=[
                self.raw,
                self.grad,
                self.m1,
                self.m2,
                self.lr,
                self.touch_scale * cfg.lr_decay ** (it / max(cfg.iterations - 1, 1)),
                cfg.beta1,
                cfg.beta2,
                cfg.eps,
                1.0 - cfg.beta1**t,
                1.0 - cfg.beta2**t,
                self.log_min - math.log(4.0),  # the cap term acts first; hard bounds catch runaways
                self.log_cap + math.log(4.0),
            ],
            outputs=[self.skipped],
            device=self.device,
        )
        self.iteration += 1

    def losses(self) -> dict:
        """Loss terms of the last iteration and a running PSNR estimate over its samples (syncs)."""
        pl = self.point_loss.numpy().astype(np.float64).sum(0)
        rl = self.reg_loss.numpy().astype(np.float64).sum(0)
        v = self.value.numpy()[: self.m].astype(np.float64)
        t = self.target.numpy().astype(np.float64)
        om = self.weight.numpy().astype(np.float64)
        mse = float(np.sum(om * (v - t) ** 2) / max(om.sum(), 1.0))
        terms = {"value": pl[0], "density": pl[1], "smooth": pl[2], "anchor": rl[0], "aniso": rl[1], "cap": rl[2]}
        terms = {k: float(x) for k, x in terms.items()}
        terms["total"] = float(sum(terms.values()))
        terms["sample_psnr_db"] = float(10 * np.log10(1 / max(mse, 1e-20)))
        return terms

    def model_params(self) -> np.ndarray:
        """Current primitives as model parameters (unit quaternion, weight in (0, 1))."""
        from .kernels import field as kf
        from .kernels import optim as ko

        wp = self._wp
        out = wp.empty(self.n, dtype=kf.vec12, device=self.device)
        wp.launch(ko.to_model, dim=self.n, inputs=[self.raw], outputs=[out], device=self.device)
        return out.numpy().reshape(self.n, 12)

    def skipped_steps(self) -> int:
        """Primitive updates skipped because of a non-finite gradient, over the run so far."""
        return int(self.skipped.numpy()[0])

    def run(
        self,
        progress=None,
        log_every: int = 25,
        deadline: float | None = None,
        clock=time.perf_counter,
    ) -> list[dict]:
        """Run the iterations; ``progress(it, total, losses)`` every ``log_every`` iterations.

        Args:
            progress: Optional callback.
            log_every: Iterations between loss records.
            deadline: A ``clock()`` time by which refinement must have ended (time-budget mode).
                The first :data:`BUDGET_PROBE` iterations measure the cost of one; the schedule
                (learning-rate decay, smoothness anneal) is then resized to the iterations that
                fit, and no iteration starts that is expected to end past the deadline. The
                primitives are valid after every step, so stopping anywhere leaves a valid model.
            clock: Time source (seconds); the device is synchronised before each reading.

        Returns:
            The logged loss records.
        """
        history: list[dict] = []
        it = 0
        per_it = None
        self.budget = None
        if deadline is not None:
            t0 = last = self._now(clock)
            slowest = 0.0
            self.budget = {"seconds": deadline - t0, "planned_iterations": None, "stopped_early": False}
        while it < self.cfg.iterations:
            if deadline is not None:
                now = self._now(clock)
                slowest, last = max(slowest, now - last), now
                if per_it is None and it == BUDGET_PROBE:
                    per_it = (now - t0) / it
                    fit = it + int(max(deadline - now, 0.0) / max(per_it, 1e-9) * BUDGET_SAFETY)
                    planned = max(it, min(fit, MAX_BUDGET_ITERATIONS))
                    self.cfg = dataclasses.replace(self.cfg, iterations=planned)
                    self.budget["planned_iterations"] = planned
                    if it >= planned:
                        break
                if now + max(slowest, per_it or 0.0) > deadline:  # the next step would end too late
                    self.budget["stopped_early"] = True
                    break
            self.step()
            it += 1
            if it % log_every == 0 or it == self.cfg.iterations:
                rec = {"iteration": it, **self.losses()}
                history.append(rec)
                if progress is not None:
                    progress(it, self.cfg.iterations, rec)
        if deadline is not None:
            self.budget["iterations_done"] = it
            self.budget["ms_per_iteration"] = None if per_it is None else 1000 * per_it
        return history

    def _now(self, clock) -> float:
        self._wp.synchronize_device(self.device)
        return clock()


def self_test(refiner: Refiner, points: int = 64) -> dict:
    """The paper's pre-run check: binned vs dense values and gradients on a few samples.

    Draws samples, evaluates the first ``points`` of them through the bins and against every
    primitive, and compares V~, rho, the contributing pairs (forward and backward) and every
    accumulated gradient, on the refiner's current primitives.

    Returns:
        The worst differences; raises :class:`WarpgaussError` if the two paths disagree.
    """
    from .kernels import backward as kb

    f = refiner.field
    k = min(points, refiner.m)
    refiner.sample(0)
    f.update(replan=True)
    refiner.forward_backward(0)
    grads = refiner.pair_grads
    refiner.accumulate(count=k)
    binned = [a.numpy().copy() for a in grads]
    pairs_b = refiner.back_pairs.numpy()[:k].copy()
    refiner.accumulate(kb.accumulate_pairs_dense, count=k)
    dense = [a.numpy() for a in grads]
    pairs_d = refiner.back_pairs.numpy()[:k]
    pts = refiner.points.numpy()[:k]
    v, d, c = f.evaluate_full(pts)
    vd, dd, cd = f.evaluate_dense(pts)
    scale = max(float(np.abs(x).max()) for x in dense) or 1.0
    result = {
        "points": k,
        "value_max_abs_diff": float(np.abs(v - vd).max()),
        "density_max_rel_diff": float(np.abs(d - dd).max() / max(float(np.abs(dd).max()), 1.0)),
        "pairs_equal": bool(np.array_equal(c, cd) and np.array_equal(pairs_b, pairs_d) and np.array_equal(c, pairs_b)),
        "gradient_max_rel_diff": max(float(np.abs(b - x).max()) / scale for b, x in zip(binned, dense)),
    }
    result["passed"] = bool(
        result["pairs_equal"]
        and result["value_max_abs_diff"] < 1e-4
        and result["density_max_rel_diff"] < 1e-4
        and result["gradient_max_rel_diff"] < 1e-4
    )
    if not result["passed"]:
        raise WarpgaussError(f"self-test failed: binned and dense evaluation disagree ({result}); please report this")
    return result
