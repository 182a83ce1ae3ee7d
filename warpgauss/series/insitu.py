"""In situ encoding: an :class:`Encoder` beside a running simulation.

A simulation hands a timestep to :meth:`Encoder.encode` (a file, a numpy array, or, without a host
copy, its own device array: Warp, CuPy, PyTorch ...) every k steps. The encoder keeps between
calls what the first one paid for: the compiled kernels and the binned-vs-dense self-test (once
per process and device), the device memory the field is normalised into, and the previous model,
from which the next timestep's refinement starts (a warm start: the same N, no allocation). A
``time_budget`` bounds the whole call, stage P to the stored model: refinement gets what is left
after the fixed costs, and the costs after refinement (evaluation, storing) are set aside as the
previous call measured them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..errors import WarpgaussError
from ..format.model import Model

FIRST_TAIL_SHARE = 0.1  # share of a first call's time budget set aside for evaluation and storing
TAIL_MARGIN = 1.25  # the measured tail of the previous call, with this margin


@dataclass
class Session:
    """What :func:`warpgauss.encode` takes from an Encoder (see its ``session`` argument)."""

    buffers: Any = None  # warpgauss.field.device.DeviceBuffers
    deadline: float | None = None
    cold_start_psnr: float | None = None  # start="auto": a warm start must score this (the last cold start's allocation)


@dataclass
class CallRecord:
    """One :meth:`Encoder.encode` call: wall seconds, refinement seconds and iterations, PSNR."""

    call: int
    warm_start: bool
    seconds: float
    refine_seconds: float
    iterations: int
    psnr_db: float | None
    time_budget: float | None
    stages: dict = field(default_factory=dict)


class Encoder:
    """Encodes timestep after timestep at one budget, each warm-started from the previous model.

    Args:
        budget: N, the number of Gaussians of every timestep; or give ``ratio`` (the first call
            resolves it to N, which later calls keep).
        ratio: Target compression ratio of the first timestep.
        time_budget: Seconds one call may take, all stages included (None: the configured
            iterations, however long they take); :meth:`encode` may override it per call.
        start: How a call after the first starts: "warm" (from the previous model), "cold" (from
            its own analytic allocation) or "auto" (the default): warm, unless the previous model,
            moved with the field, scores below, on the new timestep, what the last cold start's
            allocation scored on its own (the field moved too far for the old model to be a head start: a short time
            budget then gains more from a fresh allocation). The warm start is scored after its
            motion compensation (``motion``); the report's ``start_choice`` says what was measured.
        warm_iterations: Iterations of a warm-started call without a time budget (default: as
            configured; a time budget plans its own).
        device: Warp device (None: a device array's own, else CUDA when present, else CPU).
        **encode_kwargs: Passed to :func:`warpgauss.encode` on every call (seed, format,
            iterations, samples, evaluate, full_eval, read, allocation, refine ...).

    Example::

        enc = warpgauss.Encoder(budget=50_000, time_budget=0.5)  # start="auto"
        for step in range(steps):
            u = solver.step()              # a (z, y, x) Warp / CuPy / PyTorch array on the GPU
            if step % 10 == 0:
                m = enc.encode(u, output=f"u_{step:05d}.wgs")
                print(step, m.run_report["psnr_db"])
    """

    def __init__(
        self,
        budget: int | None = None,
        *,
        ratio: float | None = None,
        time_budget: float | None = None,
        start: str = "auto",
        warm_iterations: int | None = None,
        device: str | None = None,
        **encode_kwargs: Any,
    ):
        for name in ("warm_start", "session", "output", "force", "budget", "ratio", "time_budget", "bricks", "resume", "example"):
            if name in encode_kwargs:
                raise WarpgaussError(f"Encoder does not take {name}=: it is set per call or by the encoder itself")
        if budget is None and ratio is None:
            raise WarpgaussError("an Encoder needs budget= (N) or ratio=")
        from ..encoding.driver.config import EncodeConfig

        EncodeConfig.from_kwargs(**encode_kwargs)  # an unknown option is refused here, not at the first call
        _check_budget_seconds(time_budget)
        if warm_iterations is not None and warm_iterations < 0:
            raise WarpgaussError(f"warm iterations must be >= 0, got {warm_iterations}")
        from ..field.device import DeviceBuffers

        self.budget, self.ratio = budget, ratio
        self.time_budget = time_budget
        if start not in STARTS:
            raise WarpgaussError(f"start={start!r}: use one of {', '.join(STARTS)}")
        self.start = start
        self._cold_start_psnr: float | None = None  # the last cold call's allocation, scored on its timestep
        self.warm_iterations = warm_iterations
        self.device = device
        self.kwargs = encode_kwargs
        self.session = Session(buffers=DeviceBuffers())
        self.previous: Model | None = None
        self.calls: list[CallRecord] = []
        self._tail: float | None = None  # seconds the last call spent after refinement

    def prepare(self) -> str:
        """Load (compiling once per machine) every kernel module an encode uses on this encoder's
        device, so that no call's time budget pays for it; returns the device."""
        from ..core.warp import resolve_device, warp
        from ..kernels import analysis, backward, decode, field, ingest, motion, optim, sampling

        wp = warp()
        self.device = resolve_device(self.device)
        for module in (analysis, ingest, field, decode, motion, optim, backward, sampling):
            wp.load_module(module, device=self.device)
        from ..field.device import normalise_on_device

        tiny = wp.array(np.arange(8, dtype=np.float32).reshape(2, 2, 2), device=self.device)
        normalise_on_device(tiny)  # the float32 instance of the generic stage-P kernels
        return self.device

    def reset(self) -> None:
        """Forget the previous model: the next call starts cold (e.g. after a remesh)."""
        self.previous = None

    def encode(self, volume, *, output=None, force: bool = False, time_budget: float | None = None, **call_kwargs: Any) -> Model:
        """Encode one timestep; returns its model (``report["encoder"]`` tells this call's story).

        Args:
            volume: A path, a 3D numpy array, or a device array (z, y, x) on the encoder's device.
            output: If given, write the model there (atomic).
            force: Overwrite ``output``.
            time_budget: This call's seconds (default: the encoder's).
            call_kwargs: Further :func:`warpgauss.encode` arguments for this call only (e.g.
                ``on_progress``).
        """
        from ..encoding.entry import encode

        t0 = time.perf_counter()
        budget_s = self.time_budget if time_budget is None else time_budget
        _check_budget_seconds(budget_s)
        kw = {**self.kwargs, **call_kwargs}
        warm = self.previous is not None and self.start != "cold"
        if self.previous is None:
            kw.update(budget=self.budget, ratio=self.ratio)
        else:
            kw["budget"] = self.previous.n
        if warm:
            kw["warm_start"] = self.previous
            if self.warm_iterations is not None and budget_s is None:
                kw["iterations"] = self.warm_iterations
        self.session.deadline = None
        self.session.cold_start_psnr = self._cold_start_psnr if self.start == "auto" else None
        if budget_s is not None:
            tail = FIRST_TAIL_SHARE * budget_s if self._tail is None else TAIL_MARGIN * self._tail
            self.session.deadline = t0 + max(budget_s - tail, 0.0)
        device = self.device
        model = encode(volume, device=device, output=output, force=force, session=self.session, **kw)
        seconds = time.perf_counter() - t0
        rep = model.run_report
        warm = warm and rep.get("start_choice", {}).get("warm", True)
        start_eval = (rep.get("evaluation") or {}).get("analytic")
        if not warm and start_eval:
            self._cold_start_psnr = start_eval["psnr_db"]
        refinement = rep.get("refinement") or {}
        stages: dict[str, float] = {}
        for s in rep.get("stages", []):
            stages[s["stage"]] = stages.get(s["stage"], 0.0) + s["seconds"]
        after = sum(v for k, v in stages.items() if k in ("EV", "S3"))
        self._tail = after
        rec = CallRecord(
            call=len(self.calls),
            warm_start=warm,
            seconds=seconds,
            refine_seconds=float(refinement.get("seconds") or 0.0),
            iterations=int(refinement.get("iterations_done") or 0),
            psnr_db=rep.get("psnr_db"),
            time_budget=budget_s,
            stages=stages,
        )
        self.calls.append(rec)
        rep["encoder"] = {
            "call": rec.call,
            "warm_start": warm,
            "time_budget": budget_s,
            "seconds": seconds,
            "refine_seconds": rec.refine_seconds,
            "fixed_seconds": seconds - rec.refine_seconds,
            "iterations": rec.iterations,
        }
        if self.device is None:
            self.device = rep.get("device")  # later calls stay where the first ran
        self.previous = model
        return model


STARTS = ("auto", "warm", "cold")


def _check_budget_seconds(seconds) -> None:
    if seconds is not None and not seconds > 0:
        raise WarpgaussError(f"the time budget must be a positive number of seconds, got {seconds}")
