"""A volume of more than 2^31 voxels encoded with the volume in host memory (``--volume-on-host``):
a float32 raw file of ``--size``^3 voxels written slab by slab (a separable field, half of it empty),
then ``warpgauss.encode(path, volume_on_host=True)`` from its memory map. Reports the stages'
seconds, PSNR (500,000 sampled voxels), the primitives' z range (seeds over every slice) and the
host memory: the process's peak RSS (which counts the memory-mapped file's pages it touched) and the
machine's peak used memory over its level before the encode (anonymous memory: the pinned volume,
normalised straight into it, and stage P's passes).

    python benchmarks/bricked/host_large.py --size 2048 --budget 100000 --iterations 40 \\
        --path /tmp/field2048.raw --out $OUT/host_large2048_h200.json
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.warp import resolve_device
from warpgauss.encoding.bench import result_header


def write_field(path: Path, n: int) -> None:
    """max(0, sin(x / 61) cos(y / 97) sin(z / 43)) as float32, 32 slices at a time."""
    x = np.arange(n, dtype=np.float32)
    plane = np.sin(x / 61.0)[None, :] * np.cos(x / 97.0)[:, None]  # (y, x)
    with open(path, "wb") as fh:
        for z in range(0, n, 32):
            sz = np.sin(np.arange(z, min(n, z + 32), dtype=np.float32) / 43.0)[:, None, None]
            fh.write(np.maximum(plane[None] * sz, 0.0).astype(np.float32).tobytes())


class MemoryWatch:
    """Peak RSS of this process and peak used memory of the machine over its level at the start,
    sampled every 0.2 s (psutil, where installed)."""

    def __init__(self):
        import psutil

        self.psutil, self.proc = psutil, psutil.Process()
        self.base = psutil.virtual_memory().used
        self.rss = self.used = 0
        self.done = False
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while not self.done:
            self.rss = max(self.rss, self.proc.memory_info().rss)
            self.used = max(self.used, self.psutil.virtual_memory().used - self.base)
            time.sleep(0.2)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", type=int, default=2048)
    ap.add_argument("--budget", type=int, default=100_000)
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--path", default=None, help="the raw file (default: a temporary name, removed after)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    device = resolve_device(a.device)
    n = a.size
    path = Path(a.path or f"/tmp/host_large_{os.getpid()}_{n}x{n}x{n}_float32.raw")
    if not path.name.endswith(f"_{n}x{n}x{n}_float32.raw"):
        path = path.with_name(f"{path.stem}_{n}x{n}x{n}_float32.raw")
    t = time.perf_counter()
    write_field(path, n)
    written = time.perf_counter() - t
    watch = None
    try:
        watch = MemoryWatch()
    except ImportError:
        pass
    stages: list = []
    t = time.perf_counter()
    try:
        m = warpgauss.encode(
            str(path),
            budget=a.budget,
            iterations=a.iterations,
            device=device,
            volume_on_host=True,
            seed=3,
            progress=False,
            on_stage=lambda name, what: stages.append([name, time.perf_counter() - t]),
        )
    finally:
        if a.path is None:
            path.unlink(missing_ok=True)
    seconds = time.perf_counter() - t
    if watch is not None:
        watch.done = True
    mu = np.asarray(m.params)[:, 2]
    result = {
        **result_header("host_large", __file__, argv, device),
        "voxels": n**3,
        "past_int32": n**3 > 2**31 - 1,
        "write_seconds": written,
        "encode_seconds": seconds,
        "stage_starts_s": stages,
        "n": int(m.n),
        "psnr_db": m.report.get("psnr_db"),
        "mu_z_range": [float(mu.min()), float(mu.max())],
        "volume_memory": m.report.get("volume_memory"),
        "peak_rss_gib": None if watch is None else watch.rss / 2**30,
        "peak_used_over_start_gib": None if watch is None else watch.used / 2**30,
    }
    text = json.dumps(result, indent=1, default=str)
    if a.out:
        Path(a.out).write_text(text)
    print(text)
    return result


if __name__ == "__main__":
    main()
