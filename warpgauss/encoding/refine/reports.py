"""What a refiner reports (:class:`Reported`, a part of :class:`.refiner.Refiner`): the loss
terms, the sample and estimated full-grid PSNRs, the end-of-training estimate, skipped and
deferred steps, re-bins and relocations."""

from __future__ import annotations

from typing import Any

import numpy as np

# draws of samples the end-of-training estimates (Refiner.end_estimate) average over, and the salt
# of their RNG streams (apart from the training's, SAMPLER_SALT)
END_DRAWS = 8
END_SALT = 77_773
# samples (and primitives) one thread of a loss record sums (kernels.analysis.loss_partials)
LOSS_SLICE = 64


class Reported:
    """The reports of :class:`.refiner.Refiner`."""

    # the refiner's own, which these methods read
    _split_cuda: Any
    _split_dense: Any
    _wp: Any
    cfg: Any
    device: Any
    dv: Any
    forward: Any
    iteration: Any
    m: Any
    n: Any
    n_points: Any
    passes: Any
    point_loss: Any
    rebins: Any
    relocations: Any
    sampler: Any
    seed: Any
    split: Any
    state: Any
    target: Any
    updater: Any
    value: Any
    weight: Any

    def losses(self) -> dict:
        """Loss terms of the last iteration, a running PSNR estimate over its samples and, with
        importance weights, their estimate of the decoded model's full-grid PSNR
        (``grid_psnr_db``, see :meth:`grid_mse_estimate`; syncs once: the sums are taken on the
        device, float64 partials added on the host in a fixed order)."""
        if self.state.clean:
            self.updater.finish_grads()  # per-primitive terms of the current parameters (pair buffers are zero)
        pl, rl = self._loss_sums(regularisers=True)
        terms = {"value": pl[0], "density": pl[1], "smooth": pl[2], "anchor": rl[0], "aniso": rl[1], "cap": rl[2]}
        terms = {k: float(x) for k, x in terms.items()}
        terms["total"] = float(sum(terms.values()))
        return terms | self._psnr_terms(pl[3], pl[4], pl[5], self.m)

    def _loss_sums(self, regularisers: bool) -> tuple[np.ndarray, np.ndarray]:
        """Sums over the current samples (value, density and smooth terms, om (v - t)^2, om,
        om (clamp(v) - t)^2) and over the primitives (anchor, aniso, cap; zeros unless
        ``regularisers``), float64 (one launch, one read)."""
        from ...kernels import analysis as ka

        m, n = self.m, self.state.n if regularisers else 0
        per = LOSS_SLICE
        ms, ns = -(-m // per), -(-n // per)
        out = self._wp.empty((ms + ns, 6), dtype=self._wp.float64, device=self.device)
        self._wp.launch(
            ka.loss_partials,
            dim=ms + ns,
            inputs=[self.point_loss, self.value, self.target, self.weight, self.state.reg_loss, per, ms],
            outputs=[out],
            device=self.device,
        )
        parts = out.numpy()
        return parts[:ms].sum(0), parts[ms:, :3].sum(0)

    def _psnr_terms(self, sq: float, om: float, sq_clamped: float, count: int) -> dict:
        """``sample_psnr_db`` (the weighted MSE over the samples: ``sq`` = sum om (v - t)^2 over
        ``om`` = sum om) and, where it can be estimated, ``grid_psnr_db`` (:meth:`grid_mse_estimate`
        from ``sq_clamped`` = sum om (clamp(v) - t)^2 over ``count`` samples)."""
        mse = float(sq) / max(float(om), 1.0)
        out = {"sample_psnr_db": float(10 * np.log10(1 / max(mse, 1e-20)))}
        grid = self._grid_mse(float(sq_clamped), count)
        if grid is not None:
            out["grid_psnr_db"] = float(10 * np.log10(1 / max(grid, 1e-20)))
        return out

    def grid_mse_estimate(self, v: np.ndarray, t: np.ndarray, om: np.ndarray) -> float | None:
        """The full-grid MSE of the decoded model (values clamped as the decode clamps them)
        estimated from samples' model values ``v``, targets ``t`` and importance weights ``om``:
        with importance weights 1 / (D q(v)) the mean of
        w e^2 times D estimates the squared error summed over the voxels the draw reaches; the
        voxels it cannot reach decode to 0 and add their V^2 (:meth:`.draw.Sampler.unreached_error`);
        over the grid's valid voxels. None without importance weights, or where the unreached
        voxels' model values are not known. ``sample_psnr_db`` is the MSE over the reach alone
        (the rate control's input, as calibrated)."""
        e = np.clip(v, 0.0, 1.0) - t
        return self._grid_mse(float(np.sum(om * e * e)), len(v))

    def _grid_mse(self, sq_clamped: float, count: int) -> float | None:
        """:meth:`grid_mse_estimate` from sum om (clamp(v) - t)^2 over ``count`` samples."""
        if not self.cfg.importance:
            return None
        unreached = self.sampler.unreached_error()
        if unreached is None:
            return None
        valid = int(getattr(self.dv.field, "n_valid", 0)) or int(self.dv.values.size)
        reached = sq_clamped * self.sampler.reach() / max(count, 1)
        return (reached + unreached) / valid

    def end_estimate(self, draws: int = END_DRAWS) -> dict:
        """The current model's ``sample_psnr_db`` and ``grid_psnr_db`` (see :meth:`losses`) over
        ``draws`` fresh sample draws (RNG streams of their own, :data:`END_SALT`; forward passes
        only). Fresh, because the model has stepped on the last iterations' samples: scored on
        those it read 0.1-1.6 dB above the decoded model's grid PSNR (H200, three MRIs and two
        512^3 fields), where one iteration's draw scored before its step was within 0.7 dB.
        Parameters and the iteration count are left as they were; empty before the first
        iteration. Syncs."""
        if self.iteration == 0 or draws <= 0:
            return {}
        from ..allocate import rng_stream

        stream = self._wp.zeros(1, dtype=int, device=self.device)
        total = np.zeros(6)
        for j in range(draws):
            stream.assign(np.array([rng_stream(self.seed, j, salt=END_SALT)], np.int32))
            self.sampler.draw(stream)
            self.passes.points_changed()
            self.forward()
            total += self._loss_sums(regularisers=False)[0]
        return {"draws": draws, "samples": draws * self.m} | self._psnr_terms(total[3], total[4], total[5], draws * self.m)

    def skipped_steps(self) -> int:
        """Primitive updates skipped because their gradient or result was not finite, so far."""
        return int(self.state.counts.numpy()[0])

    def deferred_steps(self) -> int:
        """Primitive updates deferred to the next re-bin (they would have left their cell's reach)."""
        return int(self.state.counts.numpy()[1])

    def step_counts(self) -> dict:
        """The report's counts of the run's steps (syncs): primitive updates skipped as not
        finite and deferred to a re-bin, the re-bins, and the primitives relocations moved."""
        return {
            "skipped_nonfinite_updates": self.skipped_steps(),
            "deferred_updates": self.deferred_steps(),
            "rebins": self.rebins,
            "relocated": sum(r["moved"] for r in self.relocations),
        }

    @property
    def forward_pass(self) -> str:
        """The forward pass the iterations run and why (the report's ``refinement.forward_pass``)."""
        from .passes import PARTIAL_MAX_ENTRIES

        kind = "split" if self.passes.use_partials() else ("point-major, cell lists" if self.passes.listed else "point-major")
        if self._split_cuda is None:
            why = f"split_cells={self.cfg.split_cells}"
            if self.split and not self.passes.use_partials():
                why += f" (its partial sums would pass {PARTIAL_MAX_ENTRIES:,} entries)"
        elif not self._split_cuda:
            why = "the CPU"
        else:
            why = f"{self.n_points:,} points an iteration, {self.n:,} primitives on CUDA"
            if not self._split_dense:
                why += ", beside other refiners (no dense-model rule)"
        return f"{kind}: {why}"
