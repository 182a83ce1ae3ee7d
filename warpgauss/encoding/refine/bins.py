"""Stage "re-bin": sort the training state into bin-cell order, re-planning the levels at times.

Between re-bins an iteration updates primitives in place; a step that would carry a primitive
out of reach of its cell waits for the next re-bin (:class:`warpgauss.kernels.optim.SlotBounds`),
so evaluation stays exact with stale bins.
"""

from __future__ import annotations

from ...core.warp import warp
from .state import Primitives


class Binner:
    """Re-bins a :class:`Primitives` on its device (scratch for the old slot order kept here)."""

    def __init__(self, state: Primitives, shape_xyz: tuple[int, int, int], quant):
        from ...kernels import field as kf

        self._wp = wp = warp()
        self.state, self.shape_xyz = state, shape_xyz
        self.quant = quant  # kernels.optim.QuantGrid: on = evaluation reads the parameters on the coded grids
        s, dev, n = state, state.device, state.n
        self._raw_b = wp.empty_like(s.raw)
        self._m1_b = wp.empty_like(s.m1)
        self._m2_b = wp.empty_like(s.m2)
        self._ids_b = wp.empty_like(s.ids)
        # prepared primitives in the old slot order: (mu, rot, inv_s2, ext, radius, a, w, conic)
        types = (wp.vec3, wp.mat33, wp.vec3, wp.vec3, float, float, float, kf.vec6)
        self.prep = [wp.empty(n, dtype=t, device=dev) for t in types]
        self._keys = wp.empty(2 * n, dtype=int, device=dev)
        self._perm = wp.empty(2 * n, dtype=int, device=dev)
        self.rebins = 0
        self._members = wp.zeros(1, dtype=int, device=dev)  # global_members' read-back

    @property
    def perm(self):
        """The last re-bin's permutation: new slot i holds old slot perm[i] (the first N entries)."""
        return self._perm

    def prepare(self) -> None:
        """Prepare the primitives in the current slot order into :attr:`prep` (on the coded grids
        while quantisation-aware), radii widened by the reach deferred steps ask for."""
        from ...kernels import optim as ko

        s = self.state
        self.prepare_into(self.prep)
        self._wp.launch(ko.effective_radius, dim=s.n, inputs=[self.prep[4], s.reach], device=s.device)

    def prepare_into(self, outputs) -> None:
        """Prepare the primitives in the current slot order into ``outputs`` (mu, rot, inv_s2,
        ext, radius, a, w, conic), from the parameters on the coded grids while straight-through."""
        from ...kernels import field as kf
        from ...kernels import optim as ko

        s, wp = self.state, self._wp
        src = s.raw
        if self.quant.on:  # straight-through: evaluation reads the projection, the step lands on raw
            wp.launch(ko.project_copy, dim=s.n, inputs=[s.raw, self.quant], outputs=[self._raw_b], device=s.device)
            src = self._raw_b
        wp.launch(kf.prepare_primitives, dim=s.n, inputs=[src, 1], outputs=outputs, device=s.device)

    def sort(self) -> None:
        """Sort the prepared primitives into the plan's cells (into ``state.prims``)."""
        from ...field.gaussians import sort_into_cells

        sort_into_cells(self.state.prims, self.prep, self._keys, self._perm, self.state.device)

    def rebin(self, replan: bool = False) -> bool:
        """Re-sort the training state into cell order (re-planning the levels with ``replan``, or
        when a primitive outgrew them); returns whether the plan changed (cell tables and every
        buffer sized by it are new)."""
        from ...kernels import optim as ko

        wp, s = self._wp, self.state
        dev, n, p = s.device, s.n, s.prims
        mu, radius = self.prep[0], self.prep[4]
        self.prepare()
        changed = False
        if replan or s.plan is None:
            changed = self.replan(radius)
        self.sort()
        # a primitive that outgrew the planned levels sits in the global level, where one thread
        # of the primitive-major pair pass would visit every point: re-plan instead
        if not replan and self.global_members() > 0 and self.replan(radius):
            changed = True
            self.sort()
        self.slot_cells()
        wp.launch(
            ko.permute_slots,
            dim=n,
            inputs=[self._perm, s.raw, s.m1, s.m2, s.ids, mu, radius, p.level_size, p.level_dims],
            outputs=[self._raw_b, self._m1_b, self._m2_b, self._ids_b, s.bounds],
            device=dev,
        )
        for dst, src in ((s.raw, self._raw_b), (s.m1, self._m1_b), (s.m2, self._m2_b), (s.ids, self._ids_b)):
            wp.copy(dst, src)  # copy back, not swap: a captured graph holds these addresses
        from ...kernels import lists as kl

        wp.launch(kl.gather_reach, dim=n, inputs=[self._perm, s.reach], outputs=[s.reach_listed], device=dev)
        s.reach.zero_()
        self.rebins += 1
        return changed

    def replan(self, radius) -> bool:
        """Plan the levels for the current radii; returns whether the plan changed (the cell
        tables are then new)."""
        from ...field.gaussians import plan_bins_on_device, set_plan

        s = self.state
        plan = plan_bins_on_device(radius, self.shape_xyz)
        if plan == s.plan:
            return False
        s.plan = plan
        set_plan(s.prims, plan, s.device)
        return True

    def global_members(self) -> int:
        """Primitives binned in the last, global level (syncs; normally 0 after a re-plan)."""
        from ...kernels import field as kf

        s = self.state
        p = s.prims
        # one read-back a re-bin, not two: each one waits for the device (at 2048^3 on the host path
        # about 33 ms, scale/out_of_core2048_stagekernels_it600_h200.json)
        self._wp.launch(
            kf.cell_members, dim=1, inputs=[p.cell_start, p.cell_end, s.binned.total_cells - 1], outputs=[self._members], device=s.device
        )
        return int(self._members.numpy()[0])

    def slot_cells(self) -> None:
        """The cell of every slot, from the cell tables."""
        from ...kernels import field as kf

        s = self.state
        p = s.prims
        self._wp.launch(kf.slot_cells, dim=s.binned.total_cells, inputs=[p.cell_start, p.cell_end], outputs=[s.slot_cell], device=s.device)
