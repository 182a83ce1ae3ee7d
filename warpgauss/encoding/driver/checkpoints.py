"""Checkpoints of a refinement in progress (written every few minutes, resumed with --resume) and
the Ctrl-C guard that stops a run between two steps with a valid model.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..._version import __version__
from ...errors import WarpgaussError
from ..refine import RefineConfig
from .options import EncodeOptions


class Checkpoints:
    """When to write refinement checkpoints, and resuming from one (see :mod:`warpgauss.format.checkpoint`)."""

    def __init__(self, opts: EncodeOptions, params: np.ndarray, cfg: RefineConfig, device: str):
        from ...format.checkpoint import fingerprint

        self.path = None if opts.checkpoint is None else Path(opts.checkpoint)
        self.every = float(opts.checkpoint_every)
        settings = {k: v for k, v in cfg.to_dict().items() if k not in ("iterations", "samples")}
        settings.update({"requested_iterations": cfg.iterations, "requested_samples": cfg.samples, "seed": opts.seed})
        self.fingerprint = fingerprint(params, settings)
        self.device = device
        self.sessions: list[dict] = []
        self.start_iteration = 0
        self.written = 0
        self.last_iteration: int | None = None
        self.resumed_from: int | None = None

    def resume(self, refiner) -> None:
        from ...format.checkpoint import load as load_checkpoint

        if self.path is None:
            raise WarpgaussError("--resume needs a checkpoint path (--checkpoint PATH, or an output file)")
        arrays, meta = load_checkpoint(self.path)
        if meta.get("fingerprint") != self.fingerprint:
            raise WarpgaussError(
                f"{self.path} was written for another input, budget, seed or other refinement options; "
                "resume with the options of the interrupted run, or encode without --resume"
            )
        ids = arrays["ids"]
        if ids.shape[0] != refiner.n or not np.array_equal(np.sort(ids), np.arange(refiner.n)):
            raise WarpgaussError(f"{self.path} is damaged (its primitive ids are not a permutation); delete it")
        scalars = meta["refiner"]
        if arrays["cell_start"].shape[0] != int(scalars["plan"]["total_cells"]):
            raise WarpgaussError(f"{self.path} is damaged (cell table size); delete it")
        refiner.restore(arrays, scalars)
        self.sessions = list(meta.get("sessions", []))
        self.start_iteration = self.resumed_from = refiner.iteration

    def start(self, t0: float) -> None:
        self.t0 = self.last = t0

    def maybe_save(self, refiner) -> None:
        if self.path is not None and time.perf_counter() - self.last >= self.every:
            self.save(refiner)

    def save(self, refiner) -> None:
        from ...format.checkpoint import save as save_checkpoint

        if self.path is None:
            return
        now = time.perf_counter()
        arrays, scalars = refiner.state_arrays()
        session = {"from_iteration": self.start_iteration, "to_iteration": refiner.iteration, "seconds": now - self.t0}
        meta = {
            "fingerprint": self.fingerprint,
            "device": self.device,
            "iteration": refiner.iteration,
            "refiner": scalars,
            "sessions": self.sessions + [session],
            "warpgauss_version": __version__,
        }
        save_checkpoint(self.path, arrays, meta)
        self.last = time.perf_counter()
        self.written += 1
        self.last_iteration = refiner.iteration

    def report(self) -> dict | None:
        if self.path is None:
            return None
        return {
            "path": str(self.path),
            "every_seconds": self.every,
            "written": self.written,
            "last_iteration": self.last_iteration,
            "resumed_from_iteration": self.resumed_from,
        }


class stop_on_sigint:
    """While refining in the main thread, a first Ctrl-C asks the refiner to stop between steps
    (the state reached is then saved); a second one interrupts at once."""

    def __init__(self, refiner):
        self.refiner = refiner
        self.previous = None

    def __enter__(self):
        import signal
        import threading

        if threading.current_thread() is threading.main_thread():
            self.previous = signal.getsignal(signal.SIGINT)

            def handler(signum, frame):
                if self.refiner.stop_requested:
                    raise KeyboardInterrupt
                self.refiner.stop_requested = True

            signal.signal(signal.SIGINT, handler)
        return self

    def __exit__(self, *exc):
        import signal

        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
        return False
