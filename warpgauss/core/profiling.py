"""Per-stage wall time and peak memory (host RSS and device pool) for the run report."""

from __future__ import annotations

import contextlib
import os
import resource
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

POLL_SECONDS = 0.01

# What each stage of an encode is, in the words its progress lines use: the stage codes (the run
# report's, the table --verbose prints) grouped by their longest matching prefix.
PHASES: tuple[tuple[str, str], ...] = (
    ("P", "read the volume"),
    ("Sh", "share the volume with the workers"),
    ("Su", "put the volume on the device"),
    ("Sb", "split the budget over the bricks"),
    ("B", "start a brick"),
    ("S1", "place the Gaussians"),
    ("S1-S2b", "encode the bricks (place and refine)"),
    ("S2", "refine"),
    ("S2s", "refit the seams between the bricks"),
    ("EV", "measure the accuracy"),
    ("S3", "write the model"),
    ("S4", "code the bounded residual"),
)


def phase_of(stage: str) -> str:
    """The plain words for a stage code (the longest prefix in :data:`PHASES`; the code itself
    when none matches)."""
    best = max((p for p in PHASES if stage.startswith(p[0])), key=lambda p: len(p[0]), default=None)
    return stage if best is None else best[1]


def _rss_bytes() -> int:
    """Current resident set size of this process."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:  # not Linux: fall back to the lifetime peak
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def peak_rss_bytes() -> int:
    """This process's own peak resident set size: /proc's VmHWM on Linux, else ru_maxrss. Not
    ru_maxrss on Linux: a process started by fork and exec (Dask's nannies start workers so) keeps
    its parent's peak there (a worker read its client's 35.9 GB at 2048^3; a spawned child of a
    parent that had touched 1 GiB reads 1 GiB against its own 28 MiB in VmHWM)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * (1 if sys.platform == "darwin" else 1024)


class _PeakSampler:
    """The peak RSS while a stage runs, sampled by one background thread for the whole process
    (started with the first stage; a thread per stage cost ~10 ms to start and join, which a
    short in situ encode of ~0.1 s felt)."""

    _lock = threading.Lock()
    _open: set = set()  # the samplers of the stages running now
    _thread: threading.Thread | None = None

    def __init__(self):
        self.peak = _rss_bytes()

    @classmethod
    def _run(cls):
        while True:
            time.sleep(POLL_SECONDS)
            with cls._lock:
                active = list(cls._open)
            if active:
                rss = _rss_bytes()
                for s in active:
                    s.peak = max(s.peak, rss)

    def __enter__(self):
        cls = type(self)
        with cls._lock:
            cls._open.add(self)
            if cls._thread is None or not cls._thread.is_alive():
                cls._thread = threading.Thread(target=cls._run, name="warpgauss-rss", daemon=True)
                cls._thread.start()
        return self

    def __exit__(self, *exc):
        with type(self)._lock:
            type(self)._open.discard(self)
        self.peak = max(self.peak, _rss_bytes())


@dataclass
class StageRecord:
    name: str
    title: str
    seconds: float = 0.0
    host_peak_bytes: int = 0
    device_peak_bytes: int | None = None


@dataclass
class StageRecorder:
    """Times named stages; ``device`` (a CUDA Warp device name) enables device-pool peaks.

    Device peaks are the high-water mark of Warp's CUDA memory pool up to the end of the stage
    (non-decreasing across stages). The pool keeps one mark for the whole process and offers no
    reset, so a peak is reported only where it rose above the mark when ``device`` was set: where
    an earlier encode in this process peaked higher, this one's peak is unknown (None), not that
    encode's.
    """

    device: str | None = None
    stages: list[StageRecord] = field(default_factory=list)
    on_stage: Callable[[str, str], None] | None = None  # optional callback(name, title) when a stage starts

    @contextlib.contextmanager
    def stage(self, name: str, title: str):
        if self.on_stage is not None:
            self.on_stage(name, title)
        rec = StageRecord(name, title)
        t0 = time.perf_counter()
        with _PeakSampler() as sampler:
            try:
                yield rec
            finally:
                self._sync()
        rec.seconds = time.perf_counter() - t0
        rec.host_peak_bytes = sampler.peak
        rec.device_peak_bytes = self._device_peak()
        self.stages.append(rec)

    def _sync(self):
        if self.device and self.device.startswith("cuda"):
            from .warp import warp

            warp().synchronize_device(self.device)

    def __setattr__(self, name, value) -> None:
        super().__setattr__(name, value)
        if name == "device":  # the pool's mark before this recorder's stages (see the class docstring)
            super().__setattr__("_high0", self._pool_high())

    def _pool_high(self) -> int | None:
        if not (self.device and self.device.startswith("cuda")):
            return None
        from .warp import warp

        try:
            return int(warp().get_mempool_used_mem_high(self.device))
        except (RuntimeError, ValueError):
            return None

    def _device_peak(self) -> int | None:
        high, before = self._pool_high(), getattr(self, "_high0", None)
        return None if high is None or (before is not None and high <= before) else high

    def seconds(self, name: str) -> float:
        return sum(s.seconds for s in self.stages if s.name == name)

    def to_list(self) -> list[dict]:
        return [
            {
                "stage": s.name,
                "title": s.title,
                "seconds": round(s.seconds, 6),
                "host_peak_bytes": s.host_peak_bytes,
                "device_peak_bytes": s.device_peak_bytes,
            }
            for s in self.stages
        ]
