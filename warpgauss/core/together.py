"""Several jobs on one device at once: each job a generator that does one small piece of GPU work per
``next()`` (a refinement iteration), the jobs resumed in turn, each under its own CUDA stream.

One refinement iteration of a small brick is latency-bound (a captured graph of short kernels that
leaves most of the GPU idle), so the bricks of one wave step side by side: while one job's
iteration runs on its stream, the host enqueues the next job's on another. A job's arrays are
made, used and dropped under its own stream, and the jobs share no buffer, so each job's result is
the one it gives alone, bit for bit (tested on the CPU, where the jobs simply take turns).
"""

from __future__ import annotations

import gc
from collections.abc import Callable, Generator, Sequence
from typing import Any, TypeVar

T = TypeVar("T")

Job = Generator[None, None, Any]


def finish(job: Generator[None, None, T]) -> T:
    """Run ``job`` to its end; its return value."""
    while True:
        try:
            next(job)
        except StopIteration as stop:
            return stop.value


def run_together(
    starts: Sequence[Callable[[], Job]],
    device: str,
    at_once: int,
    on_done: Callable[[int, Any], None] | None = None,
) -> list:
    """Every job's result, in order: ``starts[i]()`` makes job i; at most ``at_once`` run at a
    time (the rest start, in order, as running ones end). On a CUDA ``device`` each job runs
    under a stream of its own; on the CPU they take turns. ``on_done(i, result)`` as each ends."""
    from .warp import warp

    wp = warp()
    cuda = wp.get_device(device).is_cuda
    at_once = max(1, int(at_once))
    results: list = [None] * len(starts)
    waiting = list(range(len(starts)))
    running: list[tuple[int, Job, Any]] = []
    if cuda:
        wp.synchronize_device(device)  # what the caller enqueued is done before the jobs' streams start
    try:
        while waiting or running:
            while waiting and len(running) < at_once:
                i = waiting.pop(0)
                stream = wp.Stream(device) if cuda else None
                running.append((i, starts[i](), stream))  # a generator: its body runs at the first next()
            for entry in list(running):
                i, job, stream = entry
                with _on(wp, stream):
                    try:
                        next(job)
                        continue
                    except StopIteration as stop:
                        results[i] = stop.value
                    if stream is not None:
                        wp.synchronize_stream(stream)
                    gc.collect()  # what the job left in reference cycles is freed on its own stream
                running.remove(entry)
                if on_done is not None:
                    on_done(i, results[i])
    finally:
        for _, job, stream in running:
            with _on(wp, stream):
                job.close()
                if stream is not None:
                    wp.synchronize_stream(stream)
        running.clear()
        gc.collect()
    return results


class _on:
    """Make ``stream`` its device's current stream for a block (nothing on the CPU)."""

    def __init__(self, wp, stream) -> None:
        self.scope = None if stream is None else wp.ScopedStream(stream, sync_enter=False)

    def __enter__(self):
        if self.scope is not None:
            self.scope.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self.scope is not None:
            self.scope.__exit__(*exc)
