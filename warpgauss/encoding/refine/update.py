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

# The anchor term's V(mu): read at every slot's centre at each re-bin and held until the next
# (the centres move a fraction of a voxel in between; the term's weight is 1e-3 / N) where the
# volume is in host memory: read every iteration there it crossed the bus for every touched slot,
# 2.8 of the 3.1 ms an iteration the host path added at 512^3 (H200, vortex CR 100,
# speed/profile_host512_h200.json: refine_update 4.58 s against 0.33 s in core over 1,500
# iterations). "host": cached there only (in core, read every iteration, as before); "always";
# "never"
ANCHOR_CACHE = "host"
# Where cached, the targets are read at every ANCHOR_REBINS-th re-bin and carried with their slots
# (gathered by the re-bin's permutation) in between: at 2048^3 on the host path reading them at
# every re-bin took 19.5 s of the encode (150 x 130 ms: 4M centres x 8 scattered reads across the
# bus; scale/out_of_core2048_kernels_h200x2.json). 1: read at every re-bin, as before.
ANCHOR_REBINS = 5


class Update:
    """Applies the pair gradients of an iteration to a :class:`Primitives` (see module docstring)."""

    def __init__(self, state: Primitives, dv: DeviceVolume, config: RefineConfig, quant):
        from ...kernels import field as kf

        self._wp = warp()
        self.state, self.dv, self.cfg = state, dv, config
        self.quant = quant  # kernels.optim.QuantGrid shared with the re-bin: on = straight-through on the coded grids
        on_host = bool(getattr(dv, "on_host", False))
        self.cached = ANCHOR_CACHE == "always" or (ANCHOR_CACHE == "host" and on_host)
        self.anchors = self._wp.zeros(1, dtype=float, device=state.device)  # unused until refresh_anchors
        self._anchors_b = self.anchors  # scratch of the gather (refresh_anchors)
        self._carried = 0  # re-bins the cached targets were carried through since they were read
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

        s, cfg = self.state, self.cfg
        self._wp.launch(
            ko.refine_update,
            dim=s.n,
            inputs=[
                s.raw,
                s.m1,
                s.m2,
                *s.pair_grads,
                *self._terms(),
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

    def _terms(self) -> list:
        """The per-primitive terms' inputs both kernels take: the volume and the anchor targets,
        the three weights, the anisotropy bound and the scale bounds (logs)."""
        s, w = self.state, self.cfg.weights
        return [self.dv.values, self.anchors, int(self.cached), w.anchor, w.aniso, w.cap, math.log(3.0), s.log_cap, s.log_min]

    def finish_grads(self) -> None:
        """The full gradient (pair terms + regularisers) into ``state.grad`` and the
        regulariser losses into ``state.reg_loss``, without stepping (tests, losses)."""
        from ...kernels import backward as kb

        s = self.state
        self._wp.launch(
            kb.finish_grads,
            dim=s.n,
            inputs=[s.raw, *s.pair_grads, *self._terms()],
            outputs=[s.grad, s.reg_loss],
            device=s.device,
        )

    def reread_anchors(self) -> None:
        """The next :meth:`refresh_anchors` reads the targets (the centres jumped: new parameters, a relocation)."""
        self._carried = ANCHOR_REBINS

    def refresh_anchors(self, perm=None) -> bool:
        """Where the anchor targets are cached: after a re-bin that moved the slots by ``perm``
        (new slot i holds old slot perm[i]), carry them with their slots, or read them at the
        slots' centres now at every :data:`ANCHOR_REBINS`-th (and with no ``perm``: a resume).
        True where their array was (re)allocated, which drops a captured iteration."""
        if not self.cached:
            return False
        from ...kernels import lists as kl
        from ...kernels import optim as ko

        s, new, wp = self.state, False, self._wp
        if self.anchors.shape[0] != s.n:
            self.anchors, self._anchors_b, new = (
                wp.zeros(s.n, dtype=float, device=s.device),
                wp.zeros(s.n, dtype=float, device=s.device),
                True,
            )
        self._carried += 1
        if new or perm is None or self._carried >= ANCHOR_REBINS:
            wp.launch(ko.anchor_targets, dim=s.n, inputs=[s.raw, self.quant, self.dv.values], outputs=[self.anchors], device=s.device)
            self._carried = 0
        else:  # the targets follow their primitives into the new slot order (a copy back: a graph holds the address)
            wp.launch(kl.gather_reach, dim=s.n, inputs=[perm, self.anchors], outputs=[self._anchors_b], device=s.device)
            wp.copy(self.anchors, self._anchors_b)
        return new
