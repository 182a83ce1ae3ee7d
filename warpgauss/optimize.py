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
BUDGET_SAMPLE_STEPS = (1, 2, 4, 8, 16, 32, 64)  # sample-count multiples a time budget may choose
VALIDATION_POINTS = 65_536  # voxels whose PSNR decides the target and plateau stops
SELF_TESTS: dict[str, dict] = {}  # device -> passed self-test result: once per process and device


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
        rebin_every: Iterations between re-sorting the primitives into their bin cells.
        graph: Capture one iteration as a CUDA graph and replay it (CUDA devices only).
        auto_samples: Raise ``samples`` for large budgets: one batch of ``samples`` per
            :data:`AUTO_BATCH_PRIMITIVES` primitives (see :meth:`for_budget`); off in the named
            presets and when samples were set explicitly.
        uniform_support: Draw the uniform 25 % of the samples over the model's support (the 4^3
            bricks some primitive's 5-sigma box, widened by 2 voxels, reaches, re-marked at every
            re-bin) rather than the whole grid; outside every 5-sigma box a sample scores exactly 0
            with no gradient.
        budget_samples: In time-budget mode, spend time the schedule does not need on more
            samples per iteration (see :meth:`Refiner.run`); off when samples were set explicitly.
        budget_min_iterations: Iterations a time budget secures before it raises the samples.
        target_psnr: Stop once the validation PSNR (see :meth:`Refiner.set_validation`),
            checked every ``check_every`` iterations, reaches this many dB.
        plateau_db: Stop once the validation PSNR gained less than this over the last
            ``plateau_window`` iterations.
        partner_distance: Range of the partner offset in voxels.
        split_cells: Forward pass with one thread per (point, neighbour cell) instead of per
            point, the partial sums stored and added in a fixed order; None picks it on CUDA
            devices (one thread per sample leaves a GPU idle) and not on the CPU (where it only
            adds work). Either way reruns are bit-identical. Above
            :data:`PARTIAL_MAX_ENTRIES` partials the point-major pass is used.
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
    rebin_every: int = 10
    graph: bool = True
    partner_distance: tuple[float, float] = (0.5, 1.5)
    split_cells: bool | None = None
    budget_samples: bool = True
    auto_samples: bool = True
    uniform_support: bool = True
    budget_min_iterations: int = 1500
    target_psnr: float | None = None
    plateau_db: float | None = None
    check_every: int = 100
    plateau_window: int = 300
    weights: LossWeights = field(default_factory=LossWeights)

    def to_dict(self) -> dict:
        return asdict(self)

    def for_budget(self, n: int) -> RefineConfig:
        """The settings for ``n`` primitives: with ``auto_samples``, ``samples`` x ceil(n /
        :data:`AUTO_BATCH_PRIMITIVES`) samples per iteration (at most :data:`AUTO_MAX_BATCHES` x).

        Measured on an H100 with 1.4M Gaussians (``benchmarks/results/tradeoff_*_h100.json``):
        1,500 x 3,072 samples touch each primitive about 0.25 times an iteration and score below
        128,000 Gaussians on smooth fields (vortex 1024^3: 53.4 against 59.6 dB); 4x the samples
        (12,288, what this rule gives at 1.4M) reach 60.1 dB, +1.8 to +8.9 dB on the four example
        fields at 512^3 and 1024^3, for 1.5-2.0x the refinement time.
        """
        if not self.auto_samples or self.iterations == 0:
            return self
        k = min(AUTO_MAX_BATCHES, max(1, -(-int(n) // AUTO_BATCH_PRIMITIVES)))
        return self if k == 1 else dataclasses.replace(self, samples=self.samples * k)

    def validate(self) -> None:
        """Refuse settings that would diverge or fail late, naming the option."""

        def finite(x) -> bool:
            return isinstance(x, (int, float)) and math.isfinite(x)

        positive = ("lr", "lr_position", "lr_scale", "lr_rotation", "lr_value", "lr_weight", "lr_decay", "eps")
        for name in positive:
            v = getattr(self, name)
            if not (finite(v) and v > 0):
                raise WarpgaussError(f"{name} must be a positive finite number, got {v}")
        for name in ("beta1", "beta2"):
            v = getattr(self, name)
            if not (finite(v) and 0 <= v < 1):
                raise WarpgaussError(f"{name} must be in [0, 1), got {v}")
        for name in ("touch_ref",):
            v = getattr(self, name)
            if not (finite(v) and v >= 0):
                raise WarpgaussError(f"{name} must be >= 0, got {v}")
        for name in ("replan_every", "rebin_every", "check_every", "plateau_window", "budget_min_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise WarpgaussError(f"{name} must be a positive integer, got {v}")
        lo, hi = self.partner_distance
        if not (finite(lo) and finite(hi) and 0 <= lo <= hi):
            raise WarpgaussError(f"partner_distance must be 0 <= min <= max, got {self.partner_distance}")
        for name, v in asdict(self.weights).items():
            if not (finite(v) and v >= 0):
                raise WarpgaussError(f"loss weight {name} must be a finite number >= 0, got {v} (--w-{name.replace('_', '-')})")


MIN_CHUNK = 128  # candidate points per chunk of the backward pass at least
# chunks of one primitive at most: its partials are summed by one thread, serially (H100, N 2,000
# x 307,200 samples: about 600 chunks each took 1.6 ms to sum, a quarter of the pass)
MAX_CHUNKS = 128


def chunk_capacity(n_points: int) -> int:
    """Chunks the backward pass may use beyond one per primitive: enough for chunks of
    :data:`MIN_CHUNK` at about 250 candidates per point, at most 2^21 (then chunks grow)."""
    return max(1024, min(1 << 21, 2 * int(n_points)))


PARTIAL_MAX_ENTRIES = 1 << 24  # (point, neighbour cell) partial sums of the split forward pass (192 MiB)

# quality: measured on the H100 (benchmarks/results/quality_grid_h100.json, vortex and interface
# at 128^3 with 20,000 Gaussians, split-cell kernels): 1,500 x 12,288 gives +2.7 / +1.0 dB over
# the paper configuration in 7.1 / 4.7 s of refinement (paper: 2.2 / 1.7 s); doubling the samples
# again adds only 0.3-0.6 dB for twice the time, and doubling iterations instead gains the same.
PRESETS = {  # exactly these settings: no sample count raised for large budgets
    "paper": {"iterations": 1500, "samples": 3072, "auto_samples": False},
    "fast": {"iterations": 300, "samples": 3072, "auto_samples": False},
    "quality": {"iterations": 1500, "samples": 12288, "auto_samples": False},
}
AUTO_BATCH_PRIMITIVES = 350_000  # the default raises the samples by one batch per this many primitives
AUTO_MAX_BATCHES = 16


def stratum_counts(m: int, n_high: int, n_mid: int) -> tuple[int, int, int]:
    """Samples per stratum (high, mid, uniform): 35/40/25, an empty stratum's share going to the rest."""
    shares = [STRATA[0] if n_high else 0.0, STRATA[1] if n_mid else 0.0, STRATA[2]]
    total = sum(shares)
    m_high = int(round(m * shares[0] / total))
    m_mid = int(round(m * shares[1] / total))
    return m_high, m_mid, m - m_high - m_mid


def load_kernels(device: str) -> None:
    """Compile (or load from the cache) every kernel module refinement uses, so that no time
    budget pays for it."""
    from ._warp import warp
    from .kernels import backward as kb
    from .kernels import field as kf
    from .kernels import optim as ko
    from .kernels import sampling as ks

    wp = warp()
    for module in (kf, ko, kb, ks):
        wp.load_module(module, device=device)


class Refiner:
    """N primitives under refinement on one device.

    The training state (raw parameters, Adam moments, prepared primitives) lives in *slot order*,
    sorted by bin cell. Every ``rebin_every`` iterations it is re-sorted (and every
    ``replan_every`` the cell levels re-planned); in between, an iteration only touches the
    primitives its samples reach, updating them in place, and a step that would carry a primitive
    out of reach of its cell waits for the next re-bin (see
    :class:`warpgauss.kernels.optim.SlotBounds`), so evaluation stays exact. Per-iteration
    scalars (learning-rate factor, smoothness weight, bias corrections, RNG stream) are read on
    the device from a precomputed schedule, so that on CUDA one iteration is captured once as a
    graph and replayed.

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
        from .kernels import backward as kb
        from .kernels import field as kf
        from .kernels import optim as ko
        from .kernels import sampling as ks

        wp = warp()
        self._wp = wp
        load_kernels(dv.device)
        self.dv, self.cfg, self.seed = dv, config, seed
        dev = self.device = dv.device
        if config.samples < 1 or config.iterations < 0:
            raise WarpgaussError("--samples must be >= 1 and --iterations >= 0")
        self.n = n = int(params.shape[0])
        model = wp.array(np.ascontiguousarray(params, np.float32), dtype=kf.vec12, device=dev)
        self.raw = wp.empty(n, dtype=kf.vec12, device=dev)
        wp.launch(ko.to_raw, dim=n, inputs=[model], outputs=[self.raw], device=dev)
        self.ids = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=dev)
        self.log_min = math.log(scale_min)
        self.log_cap = math.log(scale_cap)
        self.m1 = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.m2 = wp.zeros(n, dtype=kf.vec12, device=dev)
        # re-bin scratch: the state in the old slot order, and its permutation
        self._raw_b = wp.empty_like(self.raw)
        self._m1_b = wp.empty_like(self.m1)
        self._m2_b = wp.empty_like(self.m2)
        self._ids_b = wp.empty_like(self.ids)
        self._prep = [wp.empty(n, dtype=t, device=dev) for t in (wp.vec3, wp.mat33, wp.vec3, wp.vec3, float, float, float)]
        self._keys = wp.empty(2 * n, dtype=int, device=dev)
        self._perm = wp.empty(2 * n, dtype=int, device=dev)
        p = self.prims = kf.BinnedPrimitives()
        p.order = self.ids
        p.mu, p.rot, p.inv_s2, p.ext = (wp.empty(n, dtype=t, device=dev) for t in (wp.vec3, wp.mat33, wp.vec3, wp.vec3))
        p.a = wp.empty(n, dtype=float, device=dev)
        p.w = wp.empty(n, dtype=float, device=dev)
        b = self.bounds = ko.SlotBounds()
        b.lo = wp.empty(n, dtype=wp.vec3, device=dev)
        b.hi = wp.empty(n, dtype=wp.vec3, device=dev)
        b.cell = wp.empty(n, dtype=float, device=dev)
        self.plan = None
        self.grad = wp.zeros(n, dtype=kf.vec12, device=dev)
        self.d_mu = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_ls = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.d_rot = wp.zeros(n, dtype=wp.mat33, device=dev)
        self.d_a = wp.zeros(n, dtype=float, device=dev)
        self.d_w = wp.zeros(n, dtype=float, device=dev)
        self._clean = True  # the pair-gradient buffers are all zero
        self.reg_loss = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.counts = wp.zeros(2, dtype=int, device=dev)  # (non-finite skips, deferred updates)
        self.reach = wp.zeros(n, dtype=float, device=dev)  # binning radius deferred steps ask for
        self.slot_cell = wp.zeros(n, dtype=int, device=dev)  # cell of each sorted slot (pair pass)
        self._pbuf: dict | None = None  # per-iteration point binning buffers (see _point_buffers)
        self._graph = None
        self._split = wp.get_device(dev).is_cuda if config.split_cells is None else bool(config.split_cells)
        self.use_graph = wp.get_device(dev).is_cuda and config.graph
        self._build_strata()
        # with no value loss on empty samples, one where V <= 0.02 adds nothing to any term: draw
        # the uniform stratum among the occupied voxels instead of the whole grid
        self.uniform_occupied = config.weights.value_empty == 0 and self.n_high + self.n_mid > 0
        # otherwise over the model's support (see kernels.sampling.mark_support)
        self.uniform_support = config.uniform_support and not self.uniform_occupied
        self._support_marks = None
        if self.uniform_support:
            bshape = self._bricks
            self._support_marks = (wp.zeros(bshape, dtype=int, device=dev), wp.zeros(1, dtype=int, device=dev), wp.zeros(bshape, dtype=int, device=dev))
            self._support = wp.zeros(int(np.prod(bshape)), dtype=int, device=dev)
        else:
            self._support = wp.zeros(1, dtype=int, device=dev)  # unused by the sampler
        # partners serve only the smoothness term: with its weight 0 they are not evaluated
        self._partners = config.weights.smooth > 0
        self.set_samples(config.samples)
        w = config
        self.lr = kf.vec12(
            *([w.lr * w.lr_position] * 3),
            *([w.lr * w.lr_scale] * 3),
            *([w.lr * w.lr_rotation] * 4),
            w.lr * w.lr_value,
            w.lr * w.lr_weight,
        )
        self.counter = wp.zeros(1, dtype=int, device=dev)
        self.touch = wp.array([1.0], dtype=float, device=dev)
        self.now = wp.zeros(1, dtype=wp.vec4, device=dev)
        self.stream = wp.zeros(1, dtype=int, device=dev)
        self.schedule = self.streams = None
        self._write_schedule(max(config.iterations, 1))
        self.iteration = 0
        self.touch_scale = 1.0  # learning-rate factor from the contact density (see touch_ref)
        self.contacts = None
        self.rebins = 0
        self.stop_requested = False
        self.interrupted = False
        self.graph_error = None
        self.val_points = None
        self.checks: list[dict] = []
        self.stop_reason: str | None = None
        self.rebin(replan=True)

    def set_samples(self, m: int) -> None:
        """(Re)allocate the per-sample buffers for ``m`` samples per iteration."""
        wp, dev = self._wp, self.device
        if m < 1:
            raise WarpgaussError("--samples must be >= 1")
        self.m = m = int(m)
        if self.cfg.samples != m:
            self.cfg = dataclasses.replace(self.cfg, samples=m)
        self.points = wp.zeros(2 * m, dtype=wp.vec3, device=dev)
        self.target, self.weight, self.occupied = (wp.zeros(m, dtype=float, device=dev) for _ in range(3))
        self.value, self.density, self.g_value, self.g_density = (wp.zeros(2 * m, dtype=float, device=dev) for _ in range(4))
        self.pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.back_pairs = wp.zeros(2 * m, dtype=int, device=dev)
        self.point_loss = wp.zeros(m, dtype=wp.vec3, device=dev)
        self.strata = stratum_counts(m, self.n_high, self.n_mid)
        self._pbuf = None
        self._graph = None

    @property
    def split(self) -> bool:
        """Split-cell kernels (one thread per point and neighbour cell) rather than point-major."""
        return self._split

    @split.setter
    def split(self, value: bool) -> None:
        self._split = bool(value)
        self._graph = None
        self._pbuf = None  # the partial-sum buffer exists only for the split pass

    def _build_strata(self) -> None:
        """Prefix sums of per-brick stratum counts: the index the sampler draws stratum voxels from."""
        from .kernels import sampling as ks

        wp, dv, dev = self._wp, self.dv, self.device
        nz, ny, nx = dv.values.shape
        b = ks.BRICK
        self._bricks = bshape = (-(-nz // b), -(-ny // b), -(-nx // b))  # 4^3 bricks (the strata's and the support's)
        counts = [wp.empty(bshape, dtype=int, device=dev) for _ in range(2)]
        wp.launch(ks.brick_counts, dim=bshape, inputs=[dv.values, dv.mask, dv.has_mask], outputs=counts, device=dev)
        self.high, self.mid = (wp.empty(int(np.prod(bshape)), dtype=int, device=dev) for _ in range(2))
        for c, cum in zip(counts, (self.high, self.mid)):
            wp.utils.array_scan(c.flatten(), cum, inclusive=True)
        last = int(np.prod(bshape)) - 1
        self.n_high, self.n_mid = (int(cum[last:].numpy()[0]) for cum in (self.high, self.mid))

    def smooth_weight(self, it):
        """Smoothness weight annealed geometrically from strong to weak over the run."""
        w = self.cfg.weights
        if w.smooth <= 0.0:
            return 0.0 * np.asarray(it, np.float64)
        t = np.asarray(it, np.float64) / max(self.cfg.iterations - 1, 1)
        return w.smooth * (max(w.smooth_final, 1e-12) / w.smooth) ** t

    def _write_schedule(self, capacity: int | None = None) -> None:
        """Per-iteration (lr factor, smoothness weight, bc1, bc2) and RNG streams, on the device."""
        wp, cfg, dev = self._wp, self.cfg, self.device
        t_total = max(cfg.iterations, 1)
        capacity = max(capacity or 0, t_total, 0 if self.schedule is None else self.schedule.shape[0])
        if self.schedule is None or self.schedule.shape[0] < capacity:
            self.schedule = wp.zeros(capacity, dtype=wp.vec4, device=dev)
            self.streams = wp.zeros(capacity, dtype=int, device=dev)
            self._graph = None
        it = np.arange(capacity, dtype=np.float64)
        sched = np.stack(
            [
                cfg.lr_decay ** (np.minimum(it, t_total - 1) / max(t_total - 1, 1)),
                self.smooth_weight(np.minimum(it, t_total - 1)),
                1.0 - cfg.beta1 ** (it + 1),
                1.0 - cfg.beta2 ** (it + 1),
            ],
            axis=1,
        )
        streams = np.array([rng_stream(self.seed, i, salt=SAMPLER_SALT) for i in range(capacity)], np.int64)
        self.schedule.assign(sched.astype(np.float32))
        self.streams.assign(streams.astype(np.int32))

    # -- binning -----------------------------------------------------------------------------

    def rebin(self, replan: bool = False) -> None:
        """Sort the training state into cell order (re-planning the levels with ``replan``)."""
        from .field import sort_into_cells
        from .kernels import field as kf
        from .kernels import optim as ko

        wp, dev, n, p = self._wp, self.device, self.n, self.prims
        mu, radius = self._prep[0], self._prep[4]
        wp.launch(kf.prepare_primitives, dim=n, inputs=[self.raw, 1], outputs=self._prep, device=dev)
        wp.launch(ko.effective_radius, dim=n, inputs=[radius, self.reach], device=dev)
        if replan or self.plan is None:
            self._replan(radius)
        sort_into_cells(p, self._prep, self._keys, self._perm, dev)
        # a primitive that outgrew the planned levels sits in the global level, where one thread
        # of the primitive-major pair pass would visit every point: re-plan instead
        if not replan and self._global_members() > 0 and self._replan(radius):
            sort_into_cells(p, self._prep, self._keys, self._perm, dev)
        self._slot_cells()
        wp.launch(
            ko.permute_slots,
            dim=n,
            inputs=[self._perm, self.raw, self.m1, self.m2, self.ids, mu, radius, p.level_size, p.level_dims],
            outputs=[self._raw_b, self._m1_b, self._m2_b, self._ids_b, self.bounds],
            device=dev,
        )
        for dst, src in ((self.raw, self._raw_b), (self.m1, self._m1_b), (self.m2, self._m2_b), (self.ids, self._ids_b)):
            wp.copy(dst, src)  # copy back, not swap: a captured graph holds these addresses
        self.reach.zero_()
        if not self._clean:
            self._zero_grads()
        if self.uniform_support:
            self._mark_support()
        self.rebins += 1

    def _mark_support(self) -> None:
        """Re-mark the support bricks the uniform stratum is drawn from (after a re-bin)."""
        from .kernels import sampling as ks

        wp, dev = self._wp, self.device
        marks, everything, _ = self._support_marks
        marks.zero_()
        everything.zero_()
        mu, ext = self._prep[0], self._prep[3]  # prepared at this re-bin (old slot order: any order will do)
        wp.launch(ks.mark_support, dim=self.n, inputs=[mu, ext], outputs=[marks, everything], device=dev)
        bz, by, bx = marks.shape
        wp.launch(ks.prefix_sum_x, dim=(bz, by), inputs=[marks], device=dev)
        wp.launch(ks.prefix_sum_y, dim=(bz, bx), inputs=[marks], device=dev)
        wp.launch(ks.prefix_sum_z, dim=(by, bx), inputs=[marks], device=dev)
        self._index_support()

    def _index_support(self) -> None:
        """Prefix sums of the supported voxels per brick, the index the sampler draws from."""
        from .kernels import sampling as ks

        marks, everything, counts = self._support_marks
        nz, ny, nx = self.dv.values.shape
        self._wp.launch(ks.support_counts, dim=marks.shape, inputs=[marks, everything, nz, ny, nx], outputs=[counts], device=self.device)
        self._wp.utils.array_scan(counts.flatten(), self._support, inclusive=True)

    def support_share(self) -> float | None:
        """Share of the grid's voxels the uniform stratum is drawn from now (None: whole grid or
        occupied voxels, see ``uniform_support``); reads back from the device."""
        if not self.uniform_support:
            return None
        return float(self._support[-1:].numpy()[0]) / float(self.dv.values.size)

    def _replan(self, radius) -> bool:
        """Plan the levels for the current radii; returns whether the plan changed (then the cell
        tables, point buffers and captured graph are rebuilt)."""
        from .field import plan_bins_on_device, set_plan

        plan = plan_bins_on_device(radius, self.dv.field.shape_xyz)
        if plan == self.plan:
            return False
        self.plan = plan
        set_plan(self.prims, plan, self.device)
        self._graph = None
        self._pbuf = None
        return True

    def _global_members(self) -> int:
        """Primitives binned in the last, global level (syncs; normally 0 after a re-plan)."""
        c = self.plan.total_cells - 1
        p = self.prims
        return int(p.cell_end[c:].numpy()[0] - p.cell_start[c:].numpy()[0])

    def _slot_cells(self) -> None:
        from .kernels import field as kf

        p = self.prims
        self._wp.launch(kf.slot_cells, dim=self.plan.total_cells, inputs=[p.cell_start, p.cell_end], outputs=[self.slot_cell], device=self.device)

    def set_raw(self, raw: np.ndarray) -> None:
        """Replace the training parameters ((N, 12), primitive order) and reset Adam (tests)."""
        self.raw.assign(np.ascontiguousarray(raw, np.float32))
        self.ids.assign(np.arange(self.n, dtype=np.int32))
        self.m1.zero_()
        self.m2.zero_()
        self.rebin(replan=True)

    # -- one iteration -----------------------------------------------------------------------

    def _begin(self) -> None:
        from .kernels import optim as ko

        wp = self._wp
        wp.launch(
            ko.begin_iteration,
            dim=1,
            inputs=[self.counter, self.schedule, self.streams, self.touch],
            outputs=[self.now, self.stream],
            device=self.device,
        )

    def _draw(self) -> None:
        from .kernels import sampling as ks

        wp, dv = self._wp, self.dv
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
                self.n_high,
                self.n_high + self.n_mid if self.uniform_occupied else 0,
                self._support,
                int(self.uniform_support),
                self.stream,
                float(pmin),
                float(pmax),
            ],
            outputs=[self.points, self.target, self.weight, self.occupied],
            device=self.device,
        )

    def _point_buffers(self) -> dict:
        """Buffers that bin the points of an iteration on every level's point grid and split the
        pair pass into chunks (allocated outside any graph capture; the sort's scratch is
        reserved for the largest sort this refiner runs)."""
        if self._pbuf is None:
            from .field import plan_arrays, plan_point_grids
            from .kernels import backward as kb

            wp, dev, n = self._wp, self.device, self.n
            levels, p2 = len(self.plan.sizes), self.n_points
            k = levels * p2
            gp = plan_point_grids(self.plan, p2, self.dv.field.shape_xyz, self.n_high + self.n_mid)
            grid = kb.PointGrid()
            grid.size, grid.dims, grid.offset = plan_arrays(gp, dev)
            grid.start = wp.zeros(gp.total_cells + 1, dtype=int, device=dev)
            cell_counts = wp.zeros(gp.total_cells + 1, dtype=int, device=dev)
            cap = chunk_capacity(p2)
            b = {
                "grid_plan": gp,
                "grid": grid,
                "cell_counts": cell_counts,
                "keys": wp.empty(2 * k, dtype=int, device=dev),
                "order": wp.empty(2 * k, dtype=int, device=dev),
                "fkeys": wp.empty(2 * p2, dtype=int, device=dev),
                "forder": wp.empty(2 * p2, dtype=int, device=dev),
                "pos": wp.empty(k, dtype=wp.vec3, device=dev),
                "state": wp.empty(k, dtype=wp.vec4, device=dev),
                "part": wp.empty((p2, 27 * levels), dtype=wp.vec3, device=dev) if self._use_partials() else None,
                "capacity": cap,
                "work": wp.empty(n, dtype=wp.int64, device=dev),
                "work_cum": wp.empty(n, dtype=wp.int64, device=dev),
                "chunks": wp.empty(n, dtype=int, device=dev),
                "chunk_cum": wp.empty(n, dtype=int, device=dev),
                "chunk_size": wp.zeros(1, dtype=int, device=dev),
                "owner": wp.empty(n + cap, dtype=int, device=dev),
                "parts": (
                    wp.empty(n + cap, dtype=wp.vec3, device=dev),
                    wp.empty(n + cap, dtype=wp.vec3, device=dev),
                    wp.empty(n + cap, dtype=wp.mat33, device=dev),
                    wp.empty(n + cap, dtype=wp.vec2, device=dev),
                ),
            }
            # CUB keeps one scratch buffer per context and re-allocates it for a larger sort: sort
            # the largest count now, so that a captured graph never refers to a freed buffer
            big = max(k, self.n)
            scratch = [wp.zeros(2 * big, dtype=int, device=dev) for _ in range(2)]
            wp.utils.radix_sort_pairs(scratch[0], scratch[1], big)
            self._pbuf = b
        return self._pbuf

    def _use_partials(self) -> bool:
        return self.split and self.n_points * 27 * len(self.plan.sizes) <= PARTIAL_MAX_ENTRIES

    @property
    def partners(self) -> bool:
        """Whether an iteration evaluates the partner points (the smoothness term needs them)."""
        return self._partners

    @partners.setter
    def partners(self, value: bool) -> None:
        self._partners = bool(value)
        self._pbuf = None
        self._graph = None

    @property
    def n_points(self) -> int:
        """Points evaluated per iteration: the samples and, for the smoothness term, their partners."""
        return 2 * self.m if self.partners else self.m

    def _sort_points(self, count: int) -> None:
        """Bin the first ``count`` points on every level's point grid and sort them by cell
        (stable: the order within a cell is the point index, so the pair pass sums in a fixed
        order), with the dense cell start table."""
        from .field import cell_starts
        from .kernels import field as kf

        wp, dev, b = self._wp, self.device, self._point_buffers()
        grid, cells = b["grid"], b["grid_plan"].total_cells
        k = len(self.plan.sizes) * count
        wp.launch(kf.point_keys, dim=k, inputs=[self.points, count, grid.size, grid.dims, grid.offset], outputs=[b["keys"], b["order"]], device=dev)
        wp.utils.radix_sort_pairs(b["keys"], b["order"], k, 0, max(1, (cells - 1).bit_length()))
        cell_starts(b["keys"], k, b["cell_counts"], grid.start, dev)

    def _order_points(self, count: int) -> None:
        """Sort the first ``count`` points by their cell on the primitives' first level (stable),
        the order the forward pass visits them in: neighbouring threads then share a cell, and
        so the same candidate ranges on every level (the levels' cells nest)."""
        from .kernels import field as kf

        wp, dev, p, b = self._wp, self.device, self.prims, self._point_buffers()
        wp.launch(kf.point_keys, dim=count, inputs=[self.points, count, p.level_size, p.level_dims, p.level_offset], outputs=[b["fkeys"], b["forder"]], device=dev)
        wp.utils.radix_sort_pairs(b["fkeys"], b["forder"], count, 0, max(1, (self.plan.total_cells - 1).bit_length()))

    def _forward(self) -> None:
        """Order the points by cell, evaluate V~ and rho at them, and the per-point loss gradients."""
        from .kernels import backward as kb
        from .kernels import field as kf

        wp, dev, w, m2 = self._wp, self.device, self.cfg.weights, self.n_points
        self._order_points(m2)
        b = self._pbuf
        order = b["forder"]
        if self._use_partials():
            wp.launch(kf.eval_points_partial, dim=b["part"].shape, inputs=[self.points, order, self.prims], outputs=[b["part"]], device=dev)
            wp.launch(kf.finish_partials, dim=m2, inputs=[order, b["part"]], outputs=[self.value, self.density, self.pairs], device=dev)
        else:
            wp.launch(kf.eval_points_ordered, dim=m2, inputs=[self.points, order, self.prims], outputs=[self.value, self.density, self.pairs], device=dev)
        wp.launch(
            kb.point_grads,
            dim=self.m,
            inputs=[self.value, self.density, self.target, self.weight, self.occupied, self.m, w.value_empty, w.density, self.now],
            outputs=[self.g_value, self.g_density, self.point_loss],
            device=dev,
        )

    def _backward(self, count: int | None = None, count_pairs: bool = False) -> None:
        """Primitive-major pair pass over the first ``count`` points (all by default), balanced
        by chunks: overwrites the pair-gradient buffers, no float atomics (bit-identical reruns).

        Each primitive's candidate points are the point-grid rows its 5-sigma box reaches; they
        are split into chunks of at least :data:`MIN_CHUNK` candidates (more when the load
        exceeds the chunk capacity), one thread per chunk, and the chunks' partial gradients are
        summed per primitive in chunk order. The cost follows the candidates, not the largest
        primitive's point count.
        """
        from .kernels import backward as kb

        wp, dev, b, n = self._wp, self.device, self._point_buffers(), self.n
        count = self.n_points if count is None else int(count)
        self._sort_points(count)
        k = len(self.plan.sizes) * count
        wp.launch(
            kb.gather_point_state,
            dim=k,
            inputs=[b["order"], self.points, self.value, self.density, self.g_value, self.g_density],
            outputs=[b["pos"], b["state"]],
            device=dev,
        )
        if count_pairs:
            self.back_pairs.zero_()
        grid, cap = b["grid"], b["capacity"]
        wp.launch(kb.pair_work, dim=n, inputs=[self.slot_cell, self.prims, grid], outputs=[b["work"]], device=dev)
        wp.utils.array_scan(b["work"], b["work_cum"], inclusive=True)
        wp.launch(kb.pair_chunks, dim=n, inputs=[b["work"], b["work_cum"], cap, MIN_CHUNK, MAX_CHUNKS], outputs=[b["chunks"], b["chunk_size"]], device=dev)
        wp.utils.array_scan(b["chunks"], b["chunk_cum"], inclusive=True)
        wp.launch(kb.chunk_owner, dim=n, inputs=[b["chunks"], b["chunk_cum"]], outputs=[b["owner"]], device=dev)
        wp.launch(
            kb.pair_grad_chunks,
            dim=n + cap,
            inputs=[b["owner"], b["chunks"], b["chunk_cum"], self.slot_cell, self.prims, grid, b["pos"], b["state"], b["order"], int(count_pairs)],
            outputs=[self.back_pairs, *b["parts"]],
            device=dev,
        )
        wp.launch(kb.reduce_chunks, dim=n, inputs=[b["chunks"], b["chunk_cum"], self.prims, *b["parts"]], outputs=list(self.pair_grads), device=dev)
        self._clean = False

    def pair_pass_stats(self) -> dict:
        """The last backward pass's load (syncs): candidate points, chunks and chunk size, and
        the point grids' cell edges."""
        b = self._point_buffers()
        return {
            "candidates": int(b["work_cum"][self.n - 1 :].numpy()[0]),
            "chunks": int(b["chunk_cum"][self.n - 1 :].numpy()[0]),
            "chunk_size": int(b["chunk_size"].numpy()[0]),
            "chunk_capacity": self.n + b["capacity"],
            "point_cells": list(b["grid_plan"].sizes[:-1]),
        }

    def _pairs(self, kernel, count: int) -> None:
        """A point-major pair kernel (atomics; the references of tests and the self-test)."""
        wp = self._wp
        wp.launch(
            kernel,
            dim=count,
            inputs=[self.points, self.value, self.density, self.g_value, self.g_density, self.prims],
            outputs=[*self.pair_grads, self.back_pairs],
            device=self.device,
        )
        self._clean = False

    def _update(self) -> None:
        from .kernels import optim as ko

        wp, cfg, w = self._wp, self.cfg, self.cfg.weights
        wp.launch(
            ko.refine_update,
            dim=self.n,
            inputs=[
                self.raw,
                self.m1,
                self.m2,
                *self.pair_grads,
                self.dv.values,
                w.anchor,
                w.aniso,
                w.cap,
                math.log(3.0),
                self.log_cap,
                self.log_min,
                self.lr,
                self.now,
                cfg.beta1,
                cfg.beta2,
                cfg.eps,
                self.log_min - math.log(4.0),  # the cap term acts first; hard bounds catch runaways
                self.log_cap + math.log(4.0),
                self.bounds,
                self.prims,
            ],
            outputs=[self.counts, self.reach],
            device=self.device,
        )

    def _iteration_launches(self) -> None:
        from .kernels import optim as ko

        self._begin()
        self._draw()
        self._forward()
        self._backward()
        self._update()
        self._wp.launch(ko.end_iteration, dim=1, inputs=[self.counter], device=self.device)

    def step(self) -> None:
        """One iteration: (re-bin,) sample, forward, backward, fused chain rule + Adam + re-prepare."""
        wp, cfg, it = self._wp, self.cfg, self.iteration
        replan = it % max(cfg.replan_every, 1) == 0
        if it > 0 and (replan or it % max(cfg.rebin_every, 1) == 0):
            self.rebin(replan=replan)
        if not self._clean:
            self._zero_grads()
        if self.use_graph and self._graph is None:
            self._point_buffers()  # allocations and sort scratch before the capture
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                    self._iteration_launches()
                self._graph = capture.graph
            except Exception as e:  # noqa: BLE001 - a driver without graph support: plain launches
                self.use_graph = False
                self.graph_error = f"{type(e).__name__}: {e}"
        if self.use_graph:
            wp.capture_launch(self._graph)
        else:
            self._iteration_launches()
        self._clean = True  # refine_update zeroed every slot it read
        if replan and cfg.touch_ref > 0:  # re-estimate the contact density with the bins
            self.contacts = float(self.pairs.numpy()[: self.m].astype(np.float64).sum()) / self.n
            self.touch_scale = min(1.0, math.sqrt(self.contacts / cfg.touch_ref))
            self.touch.fill_(self.touch_scale)
        self.iteration += 1

    # -- pieces for tests and the self-test -------------------------------------------------

    def sample(self) -> None:
        """Draw this iteration's samples (without advancing)."""
        self._begin()
        self._draw()

    def forward_backward(self) -> None:
        """Forward values, per-point gradients and the pair scatter at the current samples."""
        self._begin()
        self._forward()
        self.accumulate()

    @property
    def pair_grads(self) -> tuple:
        """The per-primitive (slot order) gradient buffers the pair pass accumulates into."""
        return (self.d_mu, self.d_ls, self.d_rot, self.d_a, self.d_w)

    def _zero_grads(self) -> None:
        for arr in self.pair_grads:
            arr.zero_()
        self._clean = True

    def accumulate(self, kernel=None, count: int | None = None) -> None:
        """Gradients of the first ``count`` points (all by default), with the pairs counted.

        Args:
            kernel: A point-major pair kernel (the dense reference in the self-test); None for
                the refiner's own primitive-major pass.
            count: Points to gather from, the first ``count`` of the buffers.
        """
        self._zero_grads()
        self.back_pairs.zero_()
        if kernel is None:
            self._backward(count, count_pairs=True)
        else:
            self._pairs(kernel, self.n_points if count is None else count)

    def _finish(self) -> None:
        from .kernels import backward as kb

        w = self.cfg.weights
        self._wp.launch(
            kb.finish_grads,
            dim=self.n,
            inputs=[self.raw, *self.pair_grads, self.dv.values, w.anchor, w.aniso, w.cap, math.log(3.0), self.log_cap, self.log_min],
            outputs=[self.grad, self.reg_loss],
            device=self.device,
        )

    def _to_primitive_order(self, arr) -> np.ndarray:
        from .kernels import optim as ko

        wp = self._wp
        out = wp.empty_like(arr)
        wp.launch(ko.ids_from_slots, dim=self.n, inputs=[arr, self.ids], outputs=[out], device=self.device)
        return out.numpy().reshape(self.n, 12)

    def gradient(self) -> np.ndarray:
        """(N, 12) gradient of the loss w.r.t. the raw parameters, primitive order (after
        :meth:`forward_backward`)."""
        self._finish()
        return self._to_primitive_order(self.grad)

    def raw_params(self) -> np.ndarray:
        """(N, 12) training parameters in primitive order."""
        return self._to_primitive_order(self.raw)

    # -- validation (target PSNR, plateau) ---------------------------------------------------

    def set_validation(self, f, points: int = VALIDATION_POINTS) -> None:
        """Fix the voxel centres whose PSNR decides the target and plateau stops.

        Up to ``points`` valid voxels drawn uniformly with a fixed seed (all of them on small
        grids); PSNR as stage EV defines it, on normalised values.
        """
        from .evaluate import EVAL_SEED

        wp = self._wp
        n = f.n_voxels
        idx = np.arange(n, dtype=np.int64) if n <= points else np.random.default_rng(EVAL_SEED + 1).integers(0, n, points, dtype=np.int64)
        if f.mask is not None:
            idx = idx[f.mask.reshape(-1)[idx]]
        nz, ny, nx = f.values.shape
        pts = np.stack([idx % nx, (idx // nx) % ny, idx // (nx * ny)], axis=1).astype(np.float32)
        self.val_truth = f.values.reshape(-1)[idx].astype(np.float64)
        self.val_points = wp.array(pts, dtype=wp.vec3, device=self.device)
        self._val_out = [wp.empty(len(idx), dtype=t, device=self.device) for t in (float, float, int)]

    def validation_psnr(self) -> float:
        """PSNR of the current primitives at the validation voxels (syncs)."""
        from .evaluate import psnr_from_mse
        from .kernels import field as kf

        if self.val_points is None or self.val_points.shape[0] == 0:
            raise WarpgaussError("no validation voxels: call set_validation first")
        self._wp.launch(kf.eval_points_binned, dim=self.val_points.shape[0], inputs=[self.val_points, self.prims], outputs=self._val_out, device=self.device)
        err = self._val_out[0].numpy().astype(np.float64) - self.val_truth
        return psnr_from_mse(float(np.mean(err * err)))

    def _check_stop(self) -> bool:
        """At check iterations: record the validation PSNR; True if a target or plateau stop applies."""
        cfg, done = self.cfg, self.iteration
        if (cfg.target_psnr is None and cfg.plateau_db is None) or self.val_points is None or done % max(cfg.check_every, 1):
            return False
        psnr = self.validation_psnr()
        self.checks.append({"iteration": done, "psnr_db": psnr})
        if cfg.target_psnr is not None and psnr >= cfg.target_psnr:
            self.stop_reason = f"target PSNR {cfg.target_psnr:g} dB reached ({psnr:.2f} dB)"
            return True
        if cfg.plateau_db is not None:
            then = [c for c in self.checks if c["iteration"] <= done - cfg.plateau_window]
            if then and psnr - then[-1]["psnr_db"] < cfg.plateau_db:
                self.stop_reason = f"plateau: +{psnr - then[-1]['psnr_db']:.3f} dB over {done - then[-1]['iteration']} iterations (< {cfg.plateau_db:g} dB)"
                return True
        return False

    # -- checkpoints -------------------------------------------------------------------------

    def state(self) -> tuple[dict, dict]:
        """Everything the next iterations depend on, between two steps: (arrays, scalars).

        Arrays are in slot order with the bins as they stand (cells, slot bounds), so that
        :meth:`restore` continues bit-identically on the same device; the prepared primitives
        are not stored, since they are a function of the raw parameters.
        """
        b, p = self.bounds, self.prims
        arrays = {
            "raw": self.raw.numpy(),
            "m1": self.m1.numpy(),
            "m2": self.m2.numpy(),
            "ids": self.ids.numpy(),
            "bounds_lo": b.lo.numpy(),
            "bounds_hi": b.hi.numpy(),
            "bounds_cell": b.cell.numpy(),
            "cell_start": p.cell_start.numpy(),
            "cell_end": p.cell_end.numpy(),
            "counts": self.counts.numpy(),
            "reach": self.reach.numpy(),
            # the support as marked at the last re-bin, not as the current primitives would mark it
            "support": (self._support_marks[0].numpy().reshape(-1) != 0).astype(np.uint8) if self.uniform_support else np.zeros(0, np.uint8),
        }
        scalars = {
            "n": self.n,
            "iteration": self.iteration,
            "iterations": self.cfg.iterations,
            "samples": self.m,
            "touch_scale": self.touch_scale,
            "contacts": self.contacts,
            "rebins": self.rebins,
            "split": self.split,
            "support_everything": int(self._support_marks[1].numpy()[0]) if self.uniform_support else 0,
            "plan": {"sizes": list(self.plan.sizes), "dims": [list(d) for d in self.plan.dims], "offsets": list(self.plan.offsets), "total_cells": self.plan.total_cells},
        }
        return {k: np.ascontiguousarray(v) for k, v in arrays.items()}, scalars

    def restore(self, arrays: dict, scalars: dict) -> None:
        """Continue from :meth:`state` (same primitives count; shapes checked by the caller)."""
        from .field import BinPlan, set_plan
        from .kernels import field as kf

        wp, dev, p, b = self._wp, self.device, self.prims, self.bounds
        if int(scalars["n"]) != self.n:
            raise WarpgaussError(f"checkpoint holds {scalars['n']} primitives, this run has {self.n}")
        pl = scalars["plan"]
        plan = BinPlan(tuple(float(x) for x in pl["sizes"]), tuple(tuple(int(v) for v in d) for d in pl["dims"]), tuple(int(x) for x in pl["offsets"]), int(pl["total_cells"]))
        self.plan = plan
        set_plan(p, plan, dev, arrays["cell_start"], arrays["cell_end"])
        self._slot_cells()
        self._pbuf = None
        for dst, key in ((self.raw, "raw"), (self.m1, "m1"), (self.m2, "m2"), (self.ids, "ids"), (b.lo, "bounds_lo"), (b.hi, "bounds_hi"), (b.cell, "bounds_cell"), (self.counts, "counts"), (self.reach, "reach")):
            dst.assign(arrays[key])
        radius = self._prep[4]  # scratch: the prepared primitives go straight into slot order
        wp.launch(kf.prepare_primitives, dim=self.n, inputs=[self.raw, 1], outputs=[p.mu, p.rot, p.inv_s2, p.ext, radius, p.a, p.w], device=dev)
        self._zero_grads()
        if self.uniform_support:
            marks, everything, _ = self._support_marks
            if arrays["support"].size != marks.size:
                raise WarpgaussError(f"checkpoint holds {arrays['support'].size} support bricks, this run has {marks.size}")
            marks.assign(arrays["support"].reshape(marks.shape).astype(np.int32))
            everything.fill_(int(scalars.get("support_everything", 0)))
            self._index_support()
        if int(scalars["samples"]) != self.m:
            self.set_samples(int(scalars["samples"]))
        if int(scalars["iterations"]) != self.cfg.iterations:
            self.cfg = dataclasses.replace(self.cfg, iterations=int(scalars["iterations"]))
            self._write_schedule()
        self.split = bool(scalars["split"])
        self.iteration = int(scalars["iteration"])
        self.counter.assign(np.array([self.iteration], np.int32))
        self.touch_scale = float(scalars["touch_scale"])
        self.touch.fill_(self.touch_scale)
        self.contacts = scalars["contacts"]
        self.rebins = int(scalars["rebins"])
        self._graph = None

    # -- reports -----------------------------------------------------------------------------

    def losses(self) -> dict:
        """Loss terms of the last iteration and a running PSNR estimate over its samples (syncs)."""
        if self._clean:
            self._finish()  # per-primitive terms of the current parameters (pair buffers are zero)
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
        """Current primitives as model parameters (unit quaternion, weight in (0, 1)), primitive order."""
        from .kernels import field as kf
        from .kernels import optim as ko

        wp = self._wp
        out = wp.empty(self.n, dtype=kf.vec12, device=self.device)
        wp.launch(ko.to_model_slots, dim=self.n, inputs=[self.raw, self.ids], outputs=[out], device=self.device)
        return out.numpy().reshape(self.n, 12)

    def skipped_steps(self) -> int:
        """Primitive updates skipped because their gradient or result was not finite, so far."""
        return int(self.counts.numpy()[0])

    def deferred_steps(self) -> int:
        """Primitive updates deferred to the next re-bin (they would have left their cell's reach)."""
        return int(self.counts.numpy()[1])

    def run(
        self,
        progress=None,
        log_every: int = 25,
        deadline: float | None = None,
        clock=time.perf_counter,
        after_step=None,
    ) -> list[dict]:
        """Run the iterations; ``progress(it, total, losses)`` every ``log_every`` iterations.

        Args:
            progress: Optional callback.
            log_every: Iterations between loss records.
            deadline: A ``clock()`` time by which refinement must have ended (time-budget mode).
                The first :data:`BUDGET_PROBE` iterations measure the cost of one; with
                ``budget_samples`` the next :data:`BUDGET_PROBE` run at 4x the samples, which
                gives the cost as fixed + per-sample parts, and the samples are set to the
                largest of :data:`BUDGET_SAMPLE_STEPS` x the configured count that still leaves
                ``budget_min_iterations`` (more samples per iteration gain as much as more
                iterations past that, and are what a large N needs to touch every primitive).
                The schedule (learning-rate decay, smoothness anneal) is then resized to the
                iterations that fit, and no iteration starts that is expected to end past the
                deadline. The primitives are valid after every step, so stopping anywhere leaves a
                valid model.
            clock: Time source (seconds); the device is synchronised before each reading.
            after_step: Optional callback(refiner) after every step (checkpoints). Setting
                :attr:`stop_requested` (e.g. from a SIGINT handler) ends the run between two
                steps, with :attr:`interrupted` set.

        Returns:
            The logged loss records.
        """
        history: list[dict] = []
        it = 0  # steps taken by this call (a resumed run starts past 0)
        self.budget = None
        self.interrupted = False
        if deadline is not None:
            self._write_schedule(MAX_BUDGET_ITERATIONS)  # room for any resize, before capture
            plan = _BudgetPlan(self, deadline, clock)
            self.budget = plan.report
        while self.iteration < self.cfg.iterations:
            if self.stop_requested:  # set from a signal handler: stop between two steps
                self.interrupted = True
                break
            if deadline is not None and not plan.before_step(it):
                break
            self.step()
            it += 1
            done = self.iteration
            if done % log_every == 0 or done == self.cfg.iterations:
                rec = {"iteration": done, **self.losses()}
                history.append(rec)
                if progress is not None:
                    progress(done, self.cfg.iterations, rec)
            if after_step is not None:
                after_step(self)
            if self._check_stop():
                break
        if deadline is not None:
            plan.finish(it)
        return history

    def _now(self, clock) -> float:
        self._wp.synchronize_device(self.device)
        return clock()


class _BudgetPlan:
    """Sizes a time-budgeted run from timed probe iterations (see :meth:`Refiner.run`)."""

    def __init__(self, refiner: Refiner, deadline: float, clock):
        self.r, self.deadline, self.clock = refiner, deadline, clock
        self.t0 = self.last = refiner._now(clock)
        self.slowest = 0.0
        self.per_it: float | None = None
        self.base_m = refiner.m
        self.phase = "probe"
        self.mark: tuple[int, float] | None = None  # (iteration, time) where the current probe began
        self.report = {"seconds": deadline - self.t0, "planned_iterations": None, "stopped_early": False, "samples": refiner.m}

    def _remaining_iterations(self, now: float, cost: float) -> int:
        return int(max(self.deadline - now, 0.0) / max(cost, 1e-9) * BUDGET_SAFETY)

    def before_step(self, it: int) -> bool:
        """Whether iteration ``it`` may start; re-plans at the end of each probe."""
        r, cfg = self.r, self.r.cfg
        now = self.r._now(self.clock)
        self.slowest, self.last = max(self.slowest, now - self.last), now
        if self.mark is None:
            self.mark = (it, now)
        if self.phase != "run" and it == self.mark[0] + BUDGET_PROBE:
            cost = (now - self.mark[1]) / BUDGET_PROBE
            if self.phase == "probe":
                self.report["ms_per_iteration_probe"] = 1000 * cost
                self.per_it = cost
                wide = 4 * self.base_m
                enough = self._remaining_iterations(now, cost) >= cfg.budget_min_iterations + 4 * BUDGET_PROBE
                if cfg.budget_samples and enough:
                    self.phase, self.mark = "probe4", (it, now)
                    r.set_samples(wide)
                    self.slowest = 0.0
                    return True
                self._plan(it, now, cost)
            else:  # cost = a + b m from the two probes
                c1 = self.per_it
                b = max((cost - c1) / (3 * self.base_m), 0.0)
                a = max(c1 - b * self.base_m, 0.0)
                self.report["ms_per_iteration_probe4"] = 1000 * cost
                self.report["cost_model_ms"] = {"fixed": 1000 * a, "per_1000_samples": 1e6 * b}
                m = self.base_m
                for k in BUDGET_SAMPLE_STEPS:
                    if it + self._remaining_iterations(now, a + b * k * self.base_m) >= cfg.budget_min_iterations:
                        m = k * self.base_m
                if m != r.m:
                    r.set_samples(m)
                self.per_it = a + b * m
                self.slowest = 0.0
                self._plan(it, now, self.per_it)
            if it >= r.cfg.iterations:
                return False
        if now + max(self.slowest, self.per_it or 0.0) > self.deadline:  # the next step would end too late
            self.report["stopped_early"] = True
            return False
        return True

    def _plan(self, it: int, now: float, cost: float) -> None:
        r = self.r
        planned = max(it, min(it + self._remaining_iterations(now, cost), MAX_BUDGET_ITERATIONS))
        r.cfg = dataclasses.replace(r.cfg, iterations=planned)
        r._write_schedule()
        self.phase = "run"
        self.report["planned_iterations"] = planned
        self.report["samples"] = r.m

    def finish(self, it: int) -> None:
        self.report["iterations_done"] = it
        self.report["ms_per_iteration"] = None if self.per_it is None else 1000 * self.per_it


def self_test(refiner: Refiner, points: int = 64) -> dict:
    """The paper's pre-run check: binned vs dense values and gradients on a few samples.

    Draws samples, evaluates them through the training path (bins, split or point-major kernels)
    and against every primitive, and compares V~, rho, the contributing pairs (forward and
    backward) and every accumulated gradient, on the refiner's current primitives.

    Returns:
        The worst differences; raises :class:`WarpgaussError` if the two paths disagree.
    """
    from .field import GaussianField
    from .kernels import backward as kb

    k = min(points, refiner.m)
    refiner.sample()  # the training state is left as it was (samples are redrawn by the next step)
    refiner.forward_backward()
    v = refiner.value.numpy()[:k].copy()
    d = refiner.density.numpy()[:k].copy()
    c = refiner.pairs.numpy()[:k].copy()
    refiner.accumulate(count=k)
    binned = [a.numpy().copy() for a in refiner.pair_grads]
    pairs_b = refiner.back_pairs.numpy()[:k].copy()
    refiner.accumulate(kb.accumulate_pairs_dense, count=k)
    dense = [a.numpy().copy() for a in refiner.pair_grads]
    pairs_d = refiner.back_pairs.numpy()[:k].copy()
    refiner._zero_grads()
    pts = refiner.points.numpy()[:k]
    vd, dd, cd = GaussianField(refiner.model_params(), refiner.dv.field.shape_xyz, refiner.device).evaluate_dense(pts)
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
