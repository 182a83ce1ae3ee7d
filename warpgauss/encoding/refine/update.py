"""Stage "update": the chain rule onto the training parameters, the regularisers, and one Adam step.

One fused kernel (:func:`warpgauss.kernels.optim.refine_update`) per primitive the iteration's
points touched: it adds the anchor, anisotropy and cap terms, applies sparse Adam with the
schedule's learning-rate factor and bias corrections, and re-prepares the primitive in place.
"""

from __future__ import annotations

import math

from ...core.warp import warp
from ...field.analysis import DeviceVolume
from .config import RefineConfig
from .state import Primitives


class Update:
    """Applies the pair gradients of an iteration to a :class:`Primitives` (see module docstring)."""

    def __init__(self, state: Primitives, dv: DeviceVolume, config: RefineConfig, quant):
        from ...kernels import field as kf

        self._wp = warp()
        self.state, self.dv, self.cfg = state, dv, config
        self.quant = quant  # kernels.optim.QuantGrid shared with the re-bin: on = straight-through on the coded grids
        c = config
        self.lr = kf.vec12(
            *([c.lr * c.lr_position] * 3),
            *([c.lr * c.lr_scale] * 3),
            *([c.lr * c.lr_rotation] * 4),
            c.lr * c.lr_value,
            c.lr * c.lr_weight,
        )

    def step(self, now) -> None:
        """One Adam step of every primitive with gradient (``now``: the iteration's scalars)."""
        from ...kernels import optim as ko

        s, cfg, w = self.state, self.cfg, self.cfg.weights
        self._wp.launch(
            ko.refine_update,
            dim=s.n,
            inputs=[
                s.raw,
                s.m1,
                s.m2,
                *s.pair_grads,
                self.dv.values,
                w.anchor,
                w.aniso,
                w.cap,
                math.log(3.0),
                s.log_cap,
                s.log_min,
                self.lr,
                now,
                cfg.beta1,
                cfg.beta2,
                cfg.eps,
                s.log_min - math.log(4.0),  # the cap term acts first; hard bounds catch runaways
                s.log_cap + math.log(4.0),
                s.bounds,
                s.prims,
                self.quant,
                s.ids,
                s.n_train,
            ],
            outputs=[s.counts, s.reach],
            device=s.device,
        )

    def finish_grads(self) -> None:
        """The full gradient (pair terms + regularisers) into ``state.grad`` and the
        regulariser losses into ``state.reg_loss``, without stepping (tests, losses)."""
        from ...kernels import backward as kb

        s, w = self.state, self.cfg.weights
        self._wp.launch(
            kb.finish_grads,
            dim=s.n,
            inputs=[s.raw, *s.pair_grads, self.dv.values, w.anchor, w.aniso, w.cap, math.log(3.0), s.log_cap, s.log_min],
            outputs=[s.grad, s.reg_loss],
            device=s.device,
        )
