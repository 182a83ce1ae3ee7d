"""The N primitives under training, on the device, in slot order.

Slot order is bin-cell order: :mod:`.bins` re-sorts every array here at each re-bin, and every
other unit reads and writes them by slot. ``ids`` maps a slot back to the primitive's index in
the model (the order the model is returned in).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from ...core.warp import warp

if TYPE_CHECKING:
    from ...field.gaussians import BinPlan


class Primitives:
    """Training parameters, Adam moments, prepared and binned primitives, pair-gradient buffers.

    Args:
        params: (N, 12) model parameters (weight in slot 11), primitive order.
        device: Warp device.
        scale_min, scale_cap: Scale range of the cap term (sigma in voxels).
        frozen: How many primitives, at the end of ``params``, are evaluated but never stepped.
    """

    def __init__(self, params: np.ndarray, device: str, scale_min: float, scale_cap: float, frozen: int = 0):
        from ...kernels import field as kf
        from ...kernels import optim as ko

        wp = self._wp = warp()
        self.device = dev = device
        self.n = n = int(params.shape[0])
        if not 0 <= frozen <= n:
            raise ValueError(f"frozen must be in [0, {n}], got {frozen}")
        self.n_train = n - int(frozen)
        model = wp.array(np.ascontiguousarray(params, np.float32), dtype=kf.vec12, device=dev)
        self.raw = wp.empty(n, dtype=kf.vec12, device=dev)  # training parameterisation (log-sigmas, weight logit)
        wp.launch(ko.to_raw, dim=n, inputs=[model], outputs=[self.raw], device=dev)
        self.ids = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=dev)
        self.log_min = math.log(scale_min)
        self.log_cap = math.log(scale_cap)
        self.m1 = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.m2 = wp.zeros(n, dtype=kf.vec12, device=dev)
        p = self.prims = kf.BinnedPrimitives()
        p.order = self.ids
        p.mu, p.rot, p.inv_s2, p.ext = (wp.empty(n, dtype=t, device=dev) for t in (wp.vec3, wp.mat33, wp.vec3, wp.vec3))
        p.a = wp.empty(n, dtype=float, device=dev)
        p.w = wp.empty(n, dtype=float, device=dev)
        p.conic = wp.empty(n, dtype=kf.vec6, device=dev)
        b = self.bounds = ko.SlotBounds()  # how far a slot may move before the next re-bin
        b.lo = wp.empty(n, dtype=wp.vec3, device=dev)
        b.hi = wp.empty(n, dtype=wp.vec3, device=dev)
        b.cell = wp.empty(n, dtype=float, device=dev)
        b.box_lo = wp.full(n, wp.vec3(-1.0e30, -1.0e30, -1.0e30), dtype=wp.vec3, device=dev)  # the cell lists narrow these
        b.box_hi = wp.full(n, wp.vec3(1.0e30, 1.0e30, 1.0e30), dtype=wp.vec3, device=dev)
        self.plan: BinPlan | None = None  # the bin levels, set by the first re-bin
        self.slot_cell = wp.zeros(n, dtype=int, device=dev)  # cell of each slot (pair pass)
        self.d_mu = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_ls = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_rot = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.d_a = wp.zeros(n, dtype=float, device=dev)
        self.d_w = wp.zeros(n, dtype=float, device=dev)
        self.clean = True  # the pair-gradient buffers are all zero
        self.grad = wp.zeros(n, dtype=kf.vec12, device=dev)  # full gradient (tests, losses)
        self.reg_loss = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.counts = wp.zeros(2, dtype=int, device=dev)  # (non-finite skips, deferred updates)
        self.reach = wp.zeros(n, dtype=float, device=dev)  # binning radius deferred steps ask for
        self.reach_listed = wp.zeros(n, dtype=float, device=dev)  # the same, new slot order, for the cell lists

    @property
    def binned(self) -> BinPlan:
        """The bin plan (:attr:`plan`), which the first re-bin sets."""
        if self.plan is None:
            raise RuntimeError("the primitives are used before their first re-bin")
        return self.plan

    @property
    def pair_grads(self) -> tuple:
        """The per-slot gradient buffers the pair pass writes (mu, log-sigma, R, a, w)."""
        return (self.d_mu, self.d_ls, self.d_rot, self.d_a, self.d_w)

    def zero_grads(self) -> None:
        for arr in self.pair_grads:
            arr.zero_()
        self.clean = True

    def to_primitive_order(self, arr) -> np.ndarray:
        """(N, 12) host copy of a per-slot vec12 array, in primitive order."""
        from ...kernels import optim as ko

        wp = self._wp
        out = wp.empty_like(arr)
        wp.launch(ko.ids_from_slots, dim=self.n, inputs=[arr, self.ids], outputs=[out], device=self.device)
        return out.numpy().reshape(self.n, 12)

    def model_params(self) -> np.ndarray:
        """Current primitives as model parameters (unit quaternion, weight in (0, 1)), primitive order."""
        from ...kernels import field as kf
        from ...kernels import optim as ko

        wp = self._wp
        out = wp.empty(self.n, dtype=kf.vec12, device=self.device)
        wp.launch(ko.to_model_slots, dim=self.n, inputs=[self.raw, self.ids], outputs=[out], device=self.device)
        return out.numpy().reshape(self.n, 12)
