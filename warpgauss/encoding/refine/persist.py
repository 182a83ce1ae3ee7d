"""A refiner's state between two steps, for checkpoints (:class:`Checkpointed`, a part of
:class:`.refiner.Refiner`): :meth:`~Checkpointed.state_arrays` and :meth:`~Checkpointed.restore`."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ...errors import WarpgaussError


class Checkpointed:
    """What :class:`.refiner.Refiner` stores in a checkpoint and restores from it."""

    # the refiner's own, which these methods read
    _freeze_geometry: Any
    binner: Any
    cfg: Any
    device: Any
    m: Any
    n: Any
    passes: Any
    quant: Any
    quantising: Any
    rebins: Any
    relocations: Any
    replicas: Any
    sampler: Any
    schedule: Any
    set_samples: Any
    state: Any
    write_schedule: Any
    updater: Any

    def state_arrays(self) -> tuple[dict, dict]:
        """Everything the next iterations depend on, between two steps: (arrays, scalars).

        Arrays are in slot order with the bins as they stand (cells, slot bounds), so that
        :meth:`restore` continues bit-identically on the same device; the prepared primitives
        are not stored, since they are a function of the raw parameters.
        """
        s, b, p, smp = self.state, self.state.bounds, self.state.prims, self.sampler
        arrays = {
            "raw": s.raw.numpy(),
            "m1": s.m1.numpy(),
            "m2": s.m2.numpy(),
            "ids": s.ids.numpy(),
            "bounds_lo": b.lo.numpy(),
            "bounds_hi": b.hi.numpy(),
            "bounds_cell": b.cell.numpy(),
            "cell_start": p.cell_start.numpy(),
            "cell_end": p.cell_end.numpy(),
            "counts": s.counts.numpy(),
            "reach": s.reach.numpy(),
            "list_centre": self.passes.list_centre.numpy(),
            "list_half": self.passes.list_half.numpy(),
            # the support as marked at the last re-bin, not as the current primitives would mark it
            "support": (smp.support_marks[0].numpy().reshape(-1) != 0).astype(np.uint8) if smp.uniform_support else np.zeros(0, np.uint8),
            **smp.error_arrays(),
        }
        plan = s.binned
        scalars = {
            "n": self.n,
            "iteration": self.iteration,
            "iterations": self.cfg.iterations,
            "samples": self.m,
            "touch_scale": self.touch_scale,
            "contacts": self.contacts,
            "rebins": self.rebins,
            "relocations": list(self.relocations),
            "n_train": self.state.n_train,
            "silenced": self.silenced,
            "split": self.split,
            "support_everything": int(smp.support_marks[1].numpy()[0]) if smp.uniform_support else 0,
            "plan": {
                "sizes": list(plan.sizes),
                "dims": [list(d) for d in plan.dims],
                "offsets": list(plan.offsets),
                "total_cells": plan.total_cells,
            },
        }
        return {k: np.ascontiguousarray(v) for k, v in arrays.items()}, scalars

    def restore(self, arrays: dict, scalars: dict) -> None:
        """Continue from :meth:`state_arrays` (same primitives count; shapes checked by the caller)."""
        from ...field.gaussians import BinPlan, set_plan

        dev, s = self.device, self.state
        p, b = s.prims, s.bounds
        if int(scalars["n"]) != self.n:
            raise WarpgaussError(f"checkpoint holds {scalars['n']} primitives, this run has {self.n}")
        pl = scalars["plan"]
        plan = BinPlan(
            tuple(float(x) for x in pl["sizes"]),
            tuple(tuple(int(v) for v in d) for d in pl["dims"]),
            tuple(int(x) for x in pl["offsets"]),
            int(pl["total_cells"]),
        )
        s.plan = plan
        set_plan(p, plan, dev, arrays["cell_start"], arrays["cell_end"])
        self.binner.slot_cells()
        self.passes.invalidate()
        for dst, key in (
            (s.raw, "raw"),
            (s.m1, "m1"),
            (s.m2, "m2"),
            (s.ids, "ids"),
            (b.lo, "bounds_lo"),
            (b.hi, "bounds_hi"),
            (b.cell, "bounds_cell"),
            (s.counts, "counts"),
            (s.reach, "reach"),
            (self.passes.list_centre, "list_centre"),
            (self.passes.list_half, "list_half"),
        ):
            dst.assign(arrays[key])
        self.passes.lists_restored()
        it = int(scalars["iteration"])
        refit = self.cfg.quantise_mode == "refit"
        self.quant.on = int(self.quantising(it) and not refit)
        if refit and self.quantising(it) and it > int(self.cfg.quantise_from * self.cfg.iterations):
            self._freeze_geometry()  # the geometry was fixed before the checkpoint
        radius = self.binner.prep[4]  # scratch: the prepared primitives go straight into slot order
        self.binner.prepare_into([p.mu, p.rot, p.inv_s2, p.ext, radius, p.a, p.w, p.conic])
        if self.updater.refresh_anchors():  # held anchor targets (a volume on the host): read at the resume
            self._graph = None
        s.zero_grads()
        smp = self.sampler
        if smp.uniform_support:
            marks, everything, _ = smp.support_marks
            if arrays["support"].size != marks.size:
                raise WarpgaussError(f"checkpoint holds {arrays['support'].size} support bricks, this run has {marks.size}")
            marks.assign(arrays["support"].reshape(marks.shape).astype(np.int32))
            everything.fill_(int(scalars.get("support_everything", 0)))
            smp.index_support()
        smp.restore_errors(arrays["errors_new"], arrays["errors"])
        if int(scalars["samples"]) != self.m:
            self.set_samples(int(scalars["samples"]))
        if int(scalars["iterations"]) != self.cfg.iterations:
            self.cfg = dataclasses.replace(self.cfg, iterations=int(scalars["iterations"]))
            self.write_schedule()
        self.split = bool(scalars["split"])
        self.iteration = int(scalars["iteration"])
        self.schedule.set_iteration(self.iteration)
        self.touch_scale = float(scalars["touch_scale"])
        self.schedule.touch.fill_(self.touch_scale)
        self.contacts = scalars["contacts"]
        self.binner.rebins = int(scalars["rebins"])
        self.relocations = [dict(r) for r in scalars.get("relocations", [])]  # none before relocation existed
        self.state.n_train = int(scalars.get("n_train", self.state.n_train))  # after a silence()
        # a checkpoint holds no bricked run (no frozen neighbours): every frozen row was silenced
        self.silenced = int(scalars.get("silenced", self.state.n - self.state.n_train))
        self._graph = None
        if self.replicas is not None:  # the peers continue from the same state
            self.replicas.sync()
