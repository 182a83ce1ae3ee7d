"""Stage "schedule": per-iteration scalars on the device, and how long a run goes.

Learning-rate factor, smoothness weight, Adam bias corrections and the sampler's RNG stream of
every iteration are written once (:class:`Schedule`), so that on CUDA one iteration is captured
as a graph and replayed: a kernel reads the current iteration's row on the device
(:func:`warpgauss.kernels.optim.begin_iteration`). :class:`BudgetPlan` sizes a time-budgeted run
from timed probe iterations.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from ...core.warp import warp
from ..allocate import RNG_MODULUS, RNG_TAG_STEP, rng_stream
from .config import RefineConfig

SAMPLER_SALT = 99_991  # keeps the sampler's RNG streams apart from the allocation's
BUDGET_PROBE = 5  # iterations timed to size a time-budgeted run
BUDGET_SAFETY = 0.9  # share of the remaining budget planned as iterations
MAX_BUDGET_ITERATIONS = 20_000  # more iterations than this gain nothing measurable
BUDGET_SAMPLE_STEPS = (1, 2, 4, 8, 16, 32, 64)  # sample-count multiples a time budget may choose


def smooth_weight(cfg: RefineConfig, it):
    """Smoothness weight at iteration(s) ``it``, annealed geometrically from strong to weak."""
    w = cfg.weights
    if w.smooth <= 0.0:
        return 0.0 * np.asarray(it, np.float64)
    t = np.asarray(it, np.float64) / max(cfg.iterations - 1, 1)
    return w.smooth * (max(w.smooth_final, 1e-12) / w.smooth) ** t


class Schedule:
    """The device-side schedule and the iteration counter (see module docstring).

    Attributes:
        now: [1] vec4 (lr factor x touch scale, smoothness weight, bc1, bc2) of the current iteration.
        stream: [1] the current iteration's RNG stream id.
        stream_next: [1] the next iteration's (a draw made one iteration ahead).
        touch: [1] learning-rate factor from the contact density (see ``RefineConfig.touch_ref``).
    """

    def __init__(self, device: str, seed: int):
        wp = self._wp = warp()
        self.device, self.seed = device, seed
        self.counter = wp.zeros(1, dtype=int, device=device)
        self.touch = wp.array([1.0], dtype=float, device=device)
        self.now = wp.zeros(1, dtype=wp.vec4, device=device)
        self._streams_now = wp.zeros(2, dtype=int, device=device)  # begin(): this iteration's, the next one's
        self.stream, self.stream_next = self._streams_now[0:1], self._streams_now[1:2]
        # Warp arrays of the rows (vec4 factors, int streams), allocated by write()
        self.table: Any = None
        self.streams: Any = None

    def write(self, cfg: RefineConfig, capacity: int | None = None) -> bool:
        """Write the rows of ``cfg``'s iterations (at least ``capacity`` rows); returns whether the
        arrays were re-allocated (a captured graph then holds stale addresses)."""
        wp, dev = self._wp, self.device
        t_total = max(cfg.iterations, 1)
        capacity = max(capacity or 0, t_total, 0 if self.table is None else self.table.shape[0])
        grown = self.table is None or self.table.shape[0] < capacity
        if grown:
            self.table = wp.zeros(capacity, dtype=wp.vec4, device=dev)
            self.streams = wp.zeros(capacity, dtype=int, device=dev)
        it = np.arange(capacity, dtype=np.float64)
        sched = np.stack(
            [
                cfg.lr_decay ** (np.minimum(it, t_total - 1) / max(t_total - 1, 1)),
                smooth_weight(cfg, np.minimum(it, t_total - 1)),
                1.0 - cfg.beta1 ** (it + 1),
                1.0 - cfg.beta2 ** (it + 1),
            ],
            axis=1,
        )
        base = rng_stream(self.seed, 0, salt=SAMPLER_SALT)  # rng_stream(seed, i) for every i at once
        streams = (base + np.arange(capacity, dtype=np.int64) * RNG_TAG_STEP) % RNG_MODULUS
        self.table.assign(sched.astype(np.float32))
        self.streams.assign(streams.astype(np.int32))
        return grown

    def begin(self) -> None:
        """Read the current iteration's row into :attr:`now` and :attr:`stream`."""
        from ...kernels import optim as ko

        self._wp.launch(
            ko.begin_iteration,
            dim=1,
            inputs=[self.counter, self.table, self.streams, self.touch],
            outputs=[self.now, self._streams_now],
            device=self.device,
        )

    def end(self) -> None:
        """Advance the device's iteration counter."""
        from ...kernels import optim as ko

        self._wp.launch(ko.end_iteration, dim=1, inputs=[self.counter], device=self.device)

    def set_iteration(self, it: int) -> None:
        self.counter.assign(np.array([it], np.int32))


class BudgetPlan:
    """Sizes a time-budgeted run from timed probe iterations (see :meth:`Refiner.run`)."""

    def __init__(self, refiner, deadline: float, clock):
        self.r, self.deadline, self.clock = refiner, deadline, clock
        self.t0 = self.last = refiner.now(clock)
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
        now = self.r.now(self.clock)
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
        r.write_schedule()
        self.phase = "run"
        self.report["planned_iterations"] = planned
        self.report["samples"] = r.m

    def finish(self, it: int) -> None:
        self.report["iterations_done"] = it
        self.report["ms_per_iteration"] = None if self.per_it is None else 1000 * self.per_it
