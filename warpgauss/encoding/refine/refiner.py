"""The refiner: N primitives under refinement, one iteration as a sequence of stage units.

| stage | unit | module |
|---|---|---|
| schedule | :class:`.schedule.Schedule` (per-iteration scalars), :class:`.schedule.BudgetPlan`, :class:`.stop.StopRule` | ``schedule.py``, ``stop.py`` |
| draw | :class:`.draw.Sampler` | ``draw.py`` |
| forward, backward | :class:`.passes.PairPasses` | ``passes.py`` |
| update | :class:`.update.Update` | ``update.py`` |
| re-bin | :class:`.bins.Binner` | ``bins.py`` |
| relocate (off by default) | :class:`.relocate.Relocator` | ``relocate.py`` |

The units share one :class:`.state.Primitives` (the training state in slot order); this module
only sequences them, captures one iteration as a CUDA graph, and keeps checkpoints and reports.
``warpgauss bench kernels`` times each stage alone through :meth:`Refiner.sample`,
:meth:`Refiner.forward`, :meth:`Refiner.backward`, :meth:`Refiner.update` and :meth:`Refiner.rebin`.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Generator
from typing import Any

import numpy as np

from ...core.together import finish
from ...core.warp import warp
from ...errors import WarpgaussError
from ...field.analysis import DeviceVolume
from .bins import Binner
from .config import RefineConfig
from .draw import Sampler
from .passes import PairPasses, picks_split
from .persist import Checkpointed
from .probes import Probed
from .relocate import Relocator
from .replicas import Replicas
from .reports import Reported
from .schedule import MAX_BUDGET_ITERATIONS, BudgetPlan, Schedule, smooth_weight
from .state import Primitives
from .stop import VALIDATION_POINTS, StopRule
from .update import Update

SELF_TESTS: dict[str, dict] = {}  # device -> passed self-test result: once per process and device


def _quant_grid(bits: dict | None):
    """A :class:`warpgauss.kernels.optim.QuantGrid` of coded bit depths (off; all 0 for None)."""
    from ...kernels import optim as ko

    g = ko.QuantGrid()
    b = bits or {}
    g.on = 0
    g.geometry_only = 0
    g.mu, g.s, g.q, g.a, g.w = (int(b.get(k, 0)) for k in ("mu", "log_s", "q", "a", "w"))
    return g


def load_kernels(device: str) -> None:
    """Compile (or load from the cache) every kernel module refinement uses, so that no time
    budget pays for it."""
    from ...kernels import backward as kb
    from ...kernels import field as kf
    from ...kernels import lists as kl
    from ...kernels import optim as ko
    from ...kernels import sampling as ks
    from ...kernels import support as ksup

    wp = warp()
    for module in (kf, ko, kb, ks, ksup, kl):
        wp.load_module(module, device=device)


SILENT_LOGIT = 1.0e4  # sigmoid(-1e4) is exactly 0 in float32: a silenced (frozen) primitive's weight


class Refiner(Checkpointed, Reported, Probed):
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
        frozen: The last ``frozen`` rows of ``params`` are evaluated with the rest but never stepped
            (a bricked encode's finished neighbours).
    """

    def __init__(
        self,
        dv: DeviceVolume,
        params: np.ndarray,
        config: RefineConfig,
        seed: int,
        scale_min: float,
        scale_cap: float,
        frozen: int = 0,
        split_dense: bool = True,
    ):
        wp = self._wp = warp()
        load_kernels(dv.device)
        self._graphs: dict = {}  # captured iterations: one that takes a staged draw, one that draws (_take)
        self._take = False
        self.dv, self.cfg, self.seed = dv, config, seed
        dev = self.device = dv.device
        if config.samples < 1 or config.iterations < 0:
            raise WarpgaussError("--samples must be >= 1 and --iterations >= 0")
        self.state = Primitives(params, dev, scale_min, scale_cap, frozen)
        self.n = self.state.n
        self.quant = _quant_grid(config.quantise)
        self.binner = Binner(self.state, dv.field.shape_xyz, self.quant)
        self.sampler = Sampler(
            dv,
            config.uniform_support,
            config.weights.value_empty,
            config.partner_distance,
            config.jitter,
            config.importance,
            config.error_share,
            config.error_decay,
            config.rebin_every,
        )
        # split_cells None: the forward pass is re-chosen by the points an iteration in set_samples
        self._split_cuda = wp.get_device(dev).is_cuda if config.split_cells is None else None
        self._split_dense = bool(split_dense)  # False: a refiner stepping beside others (picks_split)
        # partners serve only the smoothness term: with its weight 0 they are not evaluated
        self.passes = PairPasses(self.state, self.sampler, dv.field.shape_xyz, bool(config.split_cells), config.weights.smooth > 0)
        self.passes.lists = bool(config.cell_lists)
        self.updater = Update(self.state, dv, config, self.quant)
        self.relocator = Relocator(self.state, self.sampler, dv, seed, config.relocate_weight, config.relocate_share)
        self.relocations: list[dict] = []  # {"iteration", "moved"} of every relocation that ran
        self.schedule = Schedule(dev, seed)
        self.stops = StopRule(dev)
        self._graph = None
        self._geometry_fixed = False
        self.use_graph = wp.get_device(dev).is_cuda and config.graph
        self.set_samples(config.samples)
        self.write_schedule(max(config.iterations, 1))
        self.iteration = 0
        self.touch_scale = 1.0  # learning-rate factor from the contact density (see touch_ref)
        self.silenced = 0  # primitives silence() took out (frozen, the model's last rows)
        self.contacts: float | None = None
        self.stop_requested = False
        self.interrupted = False
        self.graph_error: str | None = None
        self.captures = 0  # CUDA graphs captured so far (each re-plan, re-list or setting change re-captures)
        self.budget: dict[str, Any] | None = None
        self.replicas: Replicas | None = None  # the same model on other devices too (replicate)
        self._made = (params, scale_min, scale_cap)  # what a replica is made of (replicate)
        self.rebin(replan=True)

    def replicate(self, devices: list[str]) -> None:
        """Refine on ``devices`` too, each drawing its share of the samples (see :mod:`.replicas`)."""
        params, lo, cap = self._made
        if devices:
            self.replicas = Replicas(self, devices, lambda dv, cfg, seed: Refiner(dv, params, cfg, seed, lo, cap))

    # -- views of the units' state (tests, reports, the pipeline) ----------------------------

    prims = property(lambda self: self.state.prims)
    plan = property(lambda self: self.state.plan)
    raw = property(lambda self: self.state.raw)
    pair_grads = property(lambda self: self.state.pair_grads)
    rebins = property(lambda self: self.binner.rebins)
    m = property(lambda self: self.sampler.m)
    strata = property(lambda self: self.sampler.strata)
    n_high = property(lambda self: self.sampler.n_high)
    n_mid = property(lambda self: self.sampler.n_mid)
    high = property(lambda self: self.sampler.high)
    mid = property(lambda self: self.sampler.mid)
    uniform_occupied = property(lambda self: self.sampler.uniform_occupied)
    uniform_support = property(lambda self: self.sampler.uniform_support)
    points = property(lambda self: self.sampler.points)
    target = property(lambda self: self.sampler.target)
    weight = property(lambda self: self.sampler.weight)
    occupied = property(lambda self: self.sampler.occupied)
    value = property(lambda self: self.passes.value)
    density = property(lambda self: self.passes.density)
    pairs = property(lambda self: self.passes.pairs)
    back_pairs = property(lambda self: self.passes.back_pairs)
    point_loss = property(lambda self: self.passes.point_loss)
    n_points = property(lambda self: self.passes.n_points)
    checks = property(lambda self: self.stops.checks)
    stop_reason = property(lambda self: self.stops.reason)

    @property
    def split(self) -> bool:
        """Split-cell forward (one thread per point and neighbour cell) rather than point-major."""
        return self.passes.split

    @split.setter
    def split(self, value: bool) -> None:
        self.passes.split = bool(value)
        self.passes.invalidate()  # the partial-sum buffer exists only for the split pass
        self._graph = None

    @property
    def partners(self) -> bool:
        """Whether an iteration evaluates the partner points (the smoothness term needs them)."""
        return self.passes.partners

    @partners.setter
    def partners(self, value: bool) -> None:
        self.passes.partners = bool(value)
        self.passes.invalidate()
        self._graph = None

    # -- configuration -----------------------------------------------------------------------

    def set_samples(self, m: int) -> None:
        """(Re)allocate the per-sample buffers for ``m`` samples per iteration."""
        if m < 1:
            raise WarpgaussError("--samples must be >= 1")
        m = int(m)
        if self.cfg.samples != m:
            self.cfg = dataclasses.replace(self.cfg, samples=m)
        self.sampler.resize(m)
        if self._split_cuda is not None:
            self.passes.split = picks_split(self._split_cuda, self.passes.n_points, self.n, self._split_dense)
        self.passes.resize()
        self._graph = None

    def smooth_weight(self, it):
        """Smoothness weight annealed geometrically from strong to weak over the run."""
        return smooth_weight(self.cfg, it)

    def write_schedule(self, capacity: int | None = None) -> None:
        """Per-iteration (lr factor, smoothness weight, bc1, bc2) and RNG streams, on the device."""
        if self.schedule.write(self.cfg, capacity):
            self._graph = None

    def set_raw(self, raw: np.ndarray) -> None:
        """Replace the training parameters ((N, 12), primitive order) and reset Adam (tests)."""
        s = self.state
        s.raw.assign(np.ascontiguousarray(raw, np.float32))
        s.ids.assign(np.arange(self.n, dtype=np.int32))
        s.m1.zero_()
        s.m2.zero_()
        self.updater.reread_anchors()
        self.rebin(replan=True)

    # -- the stages --------------------------------------------------------------------------

    def rebin(self, replan: bool = False, refresh: bool = True) -> None:
        """Sort the training state into cell order (re-planning the levels with ``replan``), then
        re-mark the sampler's support and (``refresh``) re-draw its error quota."""
        if self.binner.rebin(replan):
            self.passes.invalidate()  # point grids and chunk buffers follow the plan
            self._graph = None
        if self.passes.relist():  # new list arrays, or the forward pass changed
            self._graph = None
        if not self.state.clean:
            self.state.zero_grads()
        if self.updater.refresh_anchors(self.binner.perm):
            self._graph = None
        self.sampler.mark_support(self.binner.prep[0], self.binner.prep[3])
        if refresh:
            self.sampler.refresh_errors()

    def sample(self, take: bool = False) -> None:
        """Draw this iteration's samples (without advancing); ``take``: copy in those drawn during
        the iteration before (Sampler.enable_ahead)."""
        self.schedule.begin()
        if take:
            self.sampler.take()
        else:
            self.sampler.draw(self.schedule.stream)
        self.passes.points_changed()

    def forward(self) -> None:
        """V~ and rho at the points, and the per-point loss gradients."""
        w = self.cfg.weights
        self.passes.forward(w.value_empty, w.density, self.schedule.now)

    def backward(self) -> None:
        """The pair pass: per-primitive gradients from the per-point ones."""
        self.passes.backward()

    def update(self) -> None:
        """Chain rule, regularisers and one Adam step."""
        self.updater.step(self.schedule.now)

    @property
    def _graph(self):
        return self._graphs.get(self._take)

    @_graph.setter
    def _graph(self, graph) -> None:
        if graph is None:  # every captured iteration dropped, and a staged draw with them
            self._graphs, self.sampler.staged = {}, None
        else:
            self._graphs[self._take] = graph

    def gradient_launches(self) -> None:
        """An iteration's launches up to its pair gradients: draw (and stage the next draw), forward, backward."""
        sampler = self.sampler
        self.sample(take=self._take)
        if sampler.ahead:
            sampler.stage(self.schedule.stream_next)
        self.forward()
        sampler.record_errors(self.passes.point_loss)
        self.backward()

    def update_launches(self) -> None:
        """The rest of an iteration's launches: the update, the schedule's step, the staged draw joined."""
        self.update()
        self.schedule.end()
        if self.sampler.ahead:
            self.sampler.join()

    def _iteration_launches(self) -> None:
        self.gradient_launches()
        self.update_launches()

    def step(self) -> None:
        """One iteration: (re-bin,) sample, forward, backward, fused chain rule + Adam + re-prepare
        (with :attr:`replicas`, on every device together: :meth:`.replicas.Replicas.step`)."""
        if self.replicas is not None:
            self.replicas.step()
            return
        wp = self._wp
        replan = self.begin_step()
        if self.use_graph and self._graph is None:
            self.passes.buffers()  # allocations and sort scratch before the capture
            try:
                with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                    self._iteration_launches()
                self._graph = capture.graph
                self.captures += 1
            except Exception as e:  # noqa: BLE001 - a driver without graph support: plain launches
                self.use_graph = False
                self.graph_error = f"{type(e).__name__}: {e}"
        if self.use_graph:
            wp.capture_launch(self._graph)
        else:
            self._iteration_launches()
        self.end_step(replan)

    def begin_step(self) -> bool:
        """What an iteration does before its launches (re-bin, re-plan, the coded grids' switch);
        whether it re-plans."""
        cfg, it = self.cfg, self.iteration
        replan = it % max(cfg.replan_every, 1) == 0
        relocating = self.relocating(it)
        if relocating:  # from the error map as this iteration's re-bin draws it, folded here instead
            self.sampler.refresh_errors()
            self.relocate(rebin=False)
        if it > 0 and (replan or it % max(cfg.rebin_every, 1) == 0 or relocating):
            self.rebin(replan=replan, refresh=not relocating)
        if self.quantising(it) and not self.quant.on and not self._geometry_fixed:
            if cfg.quantise_mode == "refit":  # fix the geometry on its grids, refit a and w to it
                self._fix_geometry()
            else:  # from here on, evaluate on the coded grids (straight-through)
                self.quant.on = 1
                self._graph = None  # the update kernel's arguments changed
                self.rebin()
        if not self.state.clean:
            self.state.zero_grads()
        self._take = self.sampler.can_take()
        return replan

    def end_step(self, replan: bool, contacts: float | None = None) -> None:
        """What an iteration does after its launches (``contacts``: the contact density where
        several replicas drew the samples; None: this refiner's own)."""
        cfg = self.cfg
        self.sampler.staged = self.sampler.version if self.sampler.ahead else None
        self.state.clean = True  # refine_update zeroed every slot it read
        if replan and cfg.touch_ref > 0:  # re-estimate the contact density with the bins
            self.contacts = float(self.pairs.numpy()[: self.m].astype(np.float64).sum()) / self.n if contacts is None else contacts
            self.touch_scale = min(1.0, math.sqrt(self.contacts / cfg.touch_ref))
            self.schedule.touch.fill_(self.touch_scale)
        self.iteration += 1

    def relocating(self, it: int) -> bool:
        """Whether iteration ``it`` starts with a relocation (``relocate_every``, before
        ``relocate_until`` of the iterations, never once the geometry is fixed on its grids). Such
        an iteration re-bins: at a re-bin iteration (``relocate_every`` a multiple of
        ``rebin_every``) the error map is folded and its quota drawn as the re-bin would, before
        the primitives move; elsewhere that adds a re-bin and a fold."""
        cfg = self.cfg
        every = cfg.relocate_every
        return every > 0 and it > 0 and it % every == 0 and it < cfg.relocate_until * cfg.iterations and not self._geometry_fixed

    def relocate(self, rebin: bool = True) -> int:
        """Move the dead primitives to where the error is now (:class:`.relocate.Relocator`),
        recorded in :attr:`relocations` as at the current iteration, then re-bin (``rebin``; the
        caller re-bins otherwise, before the next evaluation); the number moved (0 where the
        error stratum has no quota yet, which is not recorded)."""
        moved = self.relocator.move(self.iteration)
        if moved is None:
            return 0
        self.updater.reread_anchors()
        self.relocations.append({"iteration": self.iteration, "moved": moved})
        if moved and rebin:
            self.rebin()
        return moved

    def quantising(self, it: int | None = None) -> bool:
        """Whether iteration ``it`` (default: the next) refines on the coded grids."""
        cfg = self.cfg
        it = self.iteration if it is None else it
        return cfg.quantise is not None and it >= int(cfg.quantise_from * cfg.iterations)

    def _fix_geometry(self) -> None:
        """Move centres, scales and rotations onto the coded grids and stop stepping them."""
        from ...kernels import optim as ko

        g = _quant_grid(self.cfg.quantise)
        g.on, g.geometry_only = 1, 1
        self._wp.launch(ko.project_coded, dim=self.n, inputs=[self.state.raw, g], device=self.device)
        self._freeze_geometry()
        self.rebin()

    def _freeze_geometry(self) -> None:
        """Stop stepping centres, scales and rotations (their rates to 0; a and w keep theirs)."""
        from ...kernels import field as kf

        lr = self.updater.lr
        self.updater.lr = kf.vec12(*([0.0] * 10), lr[10], lr[11])
        self._geometry_fixed = True
        self._graph = None  # the update kernel's arguments changed

    def project(self) -> None:
        """Move every primitive onto the coded grids of ``config.quantise`` now (the parameters
        become what evaluation has read since the quantisation-aware phase began), and re-bin."""
        from ...kernels import optim as ko

        if self.cfg.quantise is None:
            raise WarpgaussError("no coded bit depths to project onto (RefineConfig.quantise is None)")
        g = _quant_grid(self.cfg.quantise)
        g.on = 1
        self._wp.launch(ko.project_coded, dim=self.n, inputs=[self.state.raw, g], device=self.device)
        self.rebin()
        for peer in [] if self.replicas is None else self.replicas.peers:
            peer.project()

    def model_params(self) -> np.ndarray:
        """Current primitives as model parameters (unit quaternion, weight in (0, 1)), primitive order."""
        return self.state.model_params()

    def silence(self, ids: np.ndarray) -> None:
        """:meth:`silence_here` (on every replica where :attr:`replicas` is set)."""
        if self.replicas is not None:
            self.replicas.silence(ids)
        else:
            self.silence_here(ids)

    def silence_here(self, ids: np.ndarray) -> None:
        """Take primitives (model indices) out of the model for the rest of the run: their weight
        becomes exactly 0 (a weight logit of -SILENT_LOGIT) and they are frozen (never stepped,
        so nothing brings them back), adding nothing to any value or density. The count stays N
        (the binned state is unchanged), but the model order changes: the primitives kept come
        first, in their order, the silenced ones last, and :attr:`n_live` counts the first, so
        ``model_params()[:n_live]`` is the model without them. It may be called again: ``ids`` are
        then indices among the first ``n_live`` (the primitives still in)."""
        s = self.state
        ids = np.unique(np.asarray(ids, np.int64))
        if ids.size == 0:
            return
        silenced = s.n - s.n_train  # taken out before: the rows after n_live
        if silenced != self.silenced:
            raise WarpgaussError("primitives can only be taken out of a run without frozen primitives")
        if ids[0] < 0 or ids[-1] >= s.n_train:
            raise WarpgaussError(f"primitive indices to take out must lie in 0..{s.n_train - 1} (those still in)")
        gone = np.zeros(s.n, bool)
        gone[ids] = True
        gone[s.n_train :] = True
        kept = s.n - int(gone.sum())
        label = np.empty(s.n, np.int64)  # old model index -> new: the kept in order, then the silenced
        label[~gone] = np.arange(kept)
        label[gone] = np.arange(kept, s.n)
        slot_ids = s.ids.numpy().astype(np.int64)
        slots = gone[slot_ids]
        raw = s.raw.numpy().reshape(s.n, 12)
        raw[slots, 11] = -SILENT_LOGIT
        s.raw.assign(raw)
        for moments in (s.m1, s.m2):
            arr = moments.numpy().reshape(s.n, 12)
            arr[slots] = 0.0
            moments.assign(arr)
        s.ids.assign(label[slot_ids].astype(np.int32))
        s.n_train = kept
        self.silenced = s.n - kept
        self.rebin(replan=True)
        self._graph = None

    @property
    def n_live(self) -> int:
        """The rows of :meth:`model_params` that are the model: the first ``n_live``; after them come
        the primitives :meth:`silence` took out, or a bricked run's frozen neighbours."""
        return self.state.n_train

    # -- validation (target PSNR, plateau) ---------------------------------------------------

    def set_validation(self, f, points: int = VALIDATION_POINTS) -> None:
        """Fix the voxel centres whose PSNR decides the target and plateau stops (see :class:`.stop.StopRule`)."""
        self.stops.set_validation(f, points)

    def validation_psnr(self) -> float:
        """PSNR of the current primitives at the validation voxels (syncs)."""
        return self.stops.psnr(self.prims)

    def support_share(self) -> float | None:
        """Share of the grid's voxels the uniform stratum is drawn from now (see :class:`.draw.Sampler`)."""
        return self.sampler.support_share()

    # -- the run -----------------------------------------------------------------------------

    def run(
        self, progress=None, log_every: int = 25, deadline: float | None = None, clock=time.perf_counter, after_step=None
    ) -> list[dict]:
        """Run the iterations (every step of :meth:`steps`); the logged loss records."""
        return finish(self.steps(progress, log_every, deadline, clock, after_step))

    def steps(
        self, progress=None, log_every: int = 25, deadline: float | None = None, clock=time.perf_counter, after_step=None
    ) -> Generator[None, None, list[dict]]:
        """The iterations, one per ``next()``: a caller can interleave several refiners on one
        device (:func:`warpgauss.core.together.run_together`); ``progress(it, total, losses)`` every
        ``log_every`` iterations.

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
            if self.replicas is not None:
                raise WarpgaussError("a time budget refines on one device; give one device")
            self.write_schedule(MAX_BUDGET_ITERATIONS)  # room for any resize, before capture
            plan = BudgetPlan(self, deadline, clock)
            self.budget = plan.report
        while self.iteration < self.cfg.iterations:
            if self.stop_requested:  # set from a signal handler: stop between two steps
                self.interrupted = True
                break
            if deadline is not None and not plan.before_step(it):
                break
            self.step()
            yield
            it += 1
            done = self.iteration
            if done % log_every == 0 or done == self.cfg.iterations:
                rec = {"iteration": done, **self.losses()}
                history.append(rec)
                if progress is not None:
                    progress(done, self.cfg.iterations, rec)
            if after_step is not None:
                after_step(self)
            if self.stops.check(self.cfg, self.iteration, self.prims):
                break
        if deadline is not None:
            plan.finish(it)
        if self.cfg.quantise is not None and not self.interrupted:
            self.project()  # the model ends on the grids it is stored on (a checkpoint keeps the run's state)
        return history

    def now(self, clock) -> float:
        """``clock()`` once the device has finished what was enqueued (a time budget's clock)."""
        self._wp.synchronize_device(self.device)
        return clock()
