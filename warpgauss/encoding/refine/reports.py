"""What a refiner reports (:class:`Reported`, a part of :class:`.refiner.Refiner`): the loss
terms, the sample and estimated full-grid PSNRs, the end-of-training estimate, skipped and
deferred steps."""

from __future__ import annotations

from typing import Any

import numpy as np

# draws of samples the end-of-training estimates (Refiner.end_estimate) average over, and the salt
# of their RNG streams (apart from the training's, SAMPLER_SALT)
END_DRAWS = 8
END_SALT = 77_773


class Reported:
    """The reports of :class:`.refiner.Refiner`."""

    # the refiner's own, which these methods read
    _wp: Any
    cfg: Any
    device: Any
    dv: Any
    forward: Any
    iteration: Any
    m: Any
    passes: Any
    point_loss: Any
    sampler: Any
    seed: Any
    state: Any
    target: Any
    updater: Any
    value: Any
    weight: Any

    def losses(self) -> dict:
        """Loss terms of the last iteration, a running PSNR estimate over its samples and, with
        importance weights, their estimate of the decoded model's full-grid PSNR
        (``grid_psnr_db``, see :meth:`grid_mse_estimate`; syncs)."""
        if self.state.clean:
            self.updater.finish_grads()  # per-primitive terms of the current parameters (pair buffers are zero)
        pl = self.point_loss.numpy().astype(np.float64).sum(0)
        rl = self.state.reg_loss.numpy().astype(np.float64).sum(0)
        terms = {"value": pl[0], "density": pl[1], "smooth": pl[2], "anchor": rl[0], "aniso": rl[1], "cap": rl[2]}
        terms = {k: float(x) for k, x in terms.items()}
        terms["total"] = float(sum(terms.values()))
        return terms | self._psnr_terms(*self._drawn())

    def _drawn(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current samples' model values, targets and weights (float64; syncs)."""
        v = self.value.numpy()[: self.m].astype(np.float64)
        return v, self.target.numpy().astype(np.float64), self.weight.numpy().astype(np.float64)

    def _psnr_terms(self, v: np.ndarray, t: np.ndarray, om: np.ndarray) -> dict:
        """``sample_psnr_db`` (the weighted MSE over the samples) and, where it can be estimated,
        ``grid_psnr_db`` (:meth:`grid_mse_estimate`) of these model values, targets and weights."""
        mse = float(np.sum(om * (v - t) ** 2) / max(om.sum(), 1.0))
        out = {"sample_psnr_db": float(10 * np.log10(1 / max(mse, 1e-20)))}
        grid = self.grid_mse_estimate(v, t, om)
        if grid is not None:
            out["grid_psnr_db"] = float(10 * np.log10(1 / max(grid, 1e-20)))
        return out

    def grid_mse_estimate(self, v: np.ndarray, t: np.ndarray, om: np.ndarray) -> float | None:
        """The full-grid MSE of the decoded model (values clamped as the decode clamps them)
        estimated from this iteration's samples: with importance weights 1 / (D q(v)) the mean of
        w e^2 times D estimates the squared error summed over the voxels the draw reaches; the
        voxels it cannot reach decode to 0 and add their V^2 (:meth:`.draw.Sampler.unreached_error`);
        over the grid's valid voxels. None without importance weights, or where the unreached
        voxels' model values are not known. ``sample_psnr_db`` is the MSE over the reach alone
        (the rate control's input, as calibrated)."""
        if not self.cfg.importance:
            return None
        unreached = self.sampler.unreached_error()
        if unreached is None:
            return None
        e = np.clip(v, 0.0, 1.0) - t
        valid = int(getattr(self.dv.field, "n_valid", 0)) or int(self.dv.values.size)
        reached = float(np.sum(om * e * e)) * self.sampler.reach() / max(len(v), 1)
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
        drawn = []
        for j in range(draws):
            stream.assign(np.array([rng_stream(self.seed, j, salt=END_SALT)], np.int32))
            self.sampler.draw(stream)
            self.passes.points_changed()
            self.forward()
            drawn.append(self._drawn())
        v, t, om = (np.concatenate(parts) for parts in zip(*drawn))
        return {"draws": draws, "samples": len(v)} | self._psnr_terms(v, t, om)

    def skipped_steps(self) -> int:
        """Primitive updates skipped because their gradient or result was not finite, so far."""
        return int(self.state.counts.numpy()[0])

    def deferred_steps(self) -> int:
        """Primitive updates deferred to the next re-bin (they would have left their cell's reach)."""
        return int(self.state.counts.numpy()[1])
