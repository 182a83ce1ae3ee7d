"""When a run stops early: the validation PSNR against a target, or a plateau of it.

A fixed set of voxel centres (:data:`VALIDATION_POINTS` drawn with a fixed seed) is evaluated
every ``check_every`` iterations through the binned primitives; PSNR as stage EV defines it.
"""

from __future__ import annotations

import numpy as np

from ...core.warp import warp
from ...errors import WarpgaussError
from .config import RefineConfig

VALIDATION_POINTS = 65_536  # voxels whose PSNR decides the target and plateau stops


class StopRule:
    """Validation voxels and the record of their PSNR over a run."""

    def __init__(self, device: str):
        self._wp = warp()
        self.device = device
        self.points = None
        self.checks: list[dict] = []
        self.reason: str | None = None

    def set_validation(self, f, points: int = VALIDATION_POINTS) -> None:
        """Fix the voxel centres whose PSNR decides the target and plateau stops: up to
        ``points`` valid voxels drawn uniformly with a fixed seed (all of them on small grids)."""
        from ...field.evaluate import EVAL_SEED

        wp = self._wp
        n = f.n_voxels
        idx = np.arange(n, dtype=np.int64) if n <= points else np.random.default_rng(EVAL_SEED + 1).integers(0, n, points, dtype=np.int64)
        lazy = hasattr(f.values, "take_flat")  # read on demand, or on a device
        if f.mask is not None:
            idx = idx[f.mask.take_flat(idx) if lazy else f.mask.reshape(-1)[idx]]
        nz, ny, nx = f.values.shape
        pts = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1).astype(np.float32)
        self.truth = (f.values.take_flat(idx) if lazy else f.values.reshape(-1)[idx]).astype(np.float64)
        self.points = wp.array(pts, dtype=wp.vec3, device=self.device)
        self._out = [wp.empty(len(idx), dtype=t, device=self.device) for t in (float, float, int)]

    def psnr(self, prims) -> float:
        """PSNR of binned primitives at the validation voxels (syncs)."""
        from ...field.evaluate import psnr_from_mse
        from ...kernels import field as kf

        if self.points is None or self.points.shape[0] == 0:
            raise WarpgaussError("no validation voxels: call set_validation first")
        self._wp.launch(kf.eval_points_binned, dim=self.points.shape[0], inputs=[self.points, prims], outputs=self._out, device=self.device)
        err = self._out[0].numpy().astype(np.float64) - self.truth
        return psnr_from_mse(float(np.mean(err * err)))

    def check(self, cfg: RefineConfig, done: int, prims) -> bool:
        """At check iterations: record the validation PSNR; True if a target or plateau stop applies
        (the reason in :attr:`reason`)."""
        if (cfg.target_psnr is None and cfg.plateau_db is None) or self.points is None or done % max(cfg.check_every, 1):
            return False
        psnr = self.psnr(prims)
        self.checks.append({"iteration": done, "psnr_db": psnr})
        if cfg.target_psnr is not None and psnr >= cfg.target_psnr:
            self.reason = f"target PSNR {cfg.target_psnr:g} dB reached ({psnr:.2f} dB)"
            return True
        if cfg.plateau_db is not None:
            then = [c for c in self.checks if c["iteration"] <= done - cfg.plateau_window]
            if then and psnr - then[-1]["psnr_db"] < cfg.plateau_db:
                self.reason = f"plateau: +{psnr - then[-1]['psnr_db']:.3f} dB over {done - then[-1]['iteration']} iterations (< {cfg.plateau_db:g} dB)"
                return True
        return False
