"""The float32 models prune_order.py and bit_order.py measure: one per volume (example fields
generated, files of ``../shared/data``), ``warpgauss.encode(..., format="full", budget=N,
iterations=I)``, with the full-grid PSNR of any parameters decoded against the source."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.format.model import Model
from warpgauss.readers import read_volume
from warpgauss.readers.synthetic import generate

DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"


def add_arguments(ap: argparse.ArgumentParser) -> None:
    """The volumes, N and iterations of the models (and the device)."""
    ap.add_argument("--fields", default="vortex,interface")
    ap.add_argument("--size", type=int, default=96)
    ap.add_argument("--budget", type=int, default=20000, help="N of the example fields' models")
    ap.add_argument("--real", default="", help="FILE:N comma list, files in --data-dir")
    ap.add_argument("--data-dir", type=Path, default=DATA_DIR)
    ap.add_argument("--iterations", type=int, default=400)
    ap.add_argument("--device", default="cpu")


def float_models(args) -> Iterator[tuple[str, Model, Callable[[np.ndarray], float], float]]:
    """Per volume: its label, the float32 model, ``psnr(params)`` (full grid, over the source's
    value range) and the encode's seconds."""
    jobs = [(f"{name} {args.size}^3", lambda name=name: generate(name, args.size), args.budget) for name in args.fields.split(",") if name]
    for item in (x for x in args.real.split(",") if x):
        fname, n = item.rsplit(":", 1)
        jobs.append((fname, lambda fname=fname: np.asarray(read_volume(args.data_dir / fname).data), int(n)))
    for label, load, n in jobs:
        vol = load()
        t0 = time.perf_counter()
        m = warpgauss.encode(vol, budget=n, format="full", iterations=args.iterations, device=args.device, self_test=False)
        seconds = time.perf_counter() - t0
        ref = vol.astype(np.float64)
        span = float(ref.max() - ref.min())

        def psnr(params: np.ndarray, m: Model = m, ref: np.ndarray = ref, span: float = span) -> float:
            d = Model(params, m.header).decode(device=args.device).astype(np.float64)
            return float(10 * np.log10(span**2 / np.mean((d - ref) ** 2)))

        yield label, m, psnr, seconds
