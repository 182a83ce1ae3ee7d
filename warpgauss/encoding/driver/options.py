"""The options of one encode (:class:`EncodeOptions`), the file format it writes, the refinement
settings from a preset, and the model header an encode starts from.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field

import numpy as np

from ...errors import WarpgaussError
from ...field.analysis import Field
from ...format.model import make_header
from ..allocate import AllocationConfig
from ..refine import PRESETS, RefineConfig

DEFAULT_RATIO = 20.0  # used when neither a budget nor a ratio is given
MAX_SAMPLES = 1 << 24  # samples per iteration: 16.8M is 1.7 GB of per-sample buffers and 64x the largest preset


@dataclass
class EncodeOptions:
    """Everything that defines an encoding besides the source (stored in the model header)."""

    budget: int | None = None
    ratio: float | None = None
    seed: int = 0
    compact: bool = False
    allocation: AllocationConfig = field(default_factory=AllocationConfig)
    stride: int = 1
    refine: RefineConfig = field(default_factory=RefineConfig)
    self_test: bool = True
    time_budget: float | None = None
    checkpoint: str | os.PathLike | None = None
    checkpoint_every: float = 60.0
    resume: bool = False
    format: str | None = None  # "float32", "compact96" or "coded"; None: compact96 if compact else float32
    bytes: int | None = None  # file size budget (header included), instead of budget or ratio
    init: np.ndarray | None = None  # warm start: (N, 12) parameters of the previous timestep's model
    deadline: float | None = None  # a time.perf_counter() by which refinement ends (an Encoder's call budget)
    budget_start: float | None = None  # the time.perf_counter() the call began: a time_budget counts from it
    evaluate_start: bool = True  # EV also scores the starting model (a warm start's: the previous timestep's)
    motion: bool = True  # a warm start's primitives first follow the motion to the new timestep (warpgauss.encoding.motion)
    cold_start_psnr: float | None = None  # warm only if the (moved) start scores at least this, else allocate


DEFAULT_FORMAT = "coded"


def encoding_of(opts: EncodeOptions) -> str:
    """The file format of an encoding: ``format`` ("full" = float32, "compact" = compact96), else
    compact96 with ``compact``, else :data:`DEFAULT_FORMAT`."""
    from ...format.wgs import resolve_encoding

    if opts.format is None and not opts.compact:
        return DEFAULT_FORMAT
    return resolve_encoding(opts.compact, opts.format)


def with_stop_rules(refine: RefineConfig, target_psnr: float | None, plateau_db: float | None) -> RefineConfig:
    """``--target-psnr`` and ``--plateau`` (each a positive number of dB, or None) in the refinement settings."""
    for name, value in (("--target-psnr", target_psnr), ("--plateau", plateau_db)):
        if value is not None and not value > 0:
            raise WarpgaussError(f"{name} must be a positive number of dB, got {value}")
    return dataclasses.replace(refine, target_psnr=target_psnr, plateau_db=plateau_db)


def resolve_refine(refine: RefineConfig | None, preset: str | None, iterations: int | None, samples: int | None) -> RefineConfig:
    """Refinement settings from a preset, overridden by explicit iterations / samples."""
    cfg = refine or RefineConfig()
    if preset is not None:
        if preset not in PRESETS:
            raise WarpgaussError(f"unknown preset {preset!r}; use one of {', '.join(PRESETS)}")
        fields = dict(PRESETS[preset])
        weights = fields.pop("weights", None)  # loss weights the preset sets, the others kept
        cfg = dataclasses.replace(cfg, **fields)
        if weights:
            cfg = dataclasses.replace(cfg, weights=dataclasses.replace(cfg.weights, **weights))
    if iterations is not None:
        if iterations < 0:
            raise WarpgaussError(f"--iterations must be >= 0, got {iterations}")
        cfg = dataclasses.replace(cfg, iterations=int(iterations))
    if samples is not None:
        if samples < 1 or samples > MAX_SAMPLES:
            raise WarpgaussError(f"--samples must be between 1 and {MAX_SAMPLES:,} (about 100 bytes of buffers per sample), got {samples}")
        cfg = dataclasses.replace(cfg, samples=int(samples), budget_samples=False, auto_samples=False)  # the user's count stays
    cfg.validate()
    return cfg


def header_for(f: Field, opts: EncodeOptions) -> dict:
    header = base_header(f, opts)
    if encoding_of(opts) == "coded":  # every byte counts: the default LUT is regenerated from its colormap and opacity
        header["transfer_function"] = {k: v for k, v in header["transfer_function"].items() if k != "lut_rgba8"}
    return header


def base_header(f: Field, opts: EncodeOptions) -> dict:
    encoding = {
        "method": "fixed-budget anisotropic Gaussians: analytic allocation + refinement",
        "iterations": opts.refine.iterations,
        "samples": opts.refine.samples,
        "stride": opts.stride,
        "allocation": opts.allocation.to_dict(f.shape_xyz),
        "refinement": opts.refine.to_dict() if opts.refine.iterations > 0 else None,
        "rho0": 0.05,
        "truncation_sigma": 5.0,
    }
    return make_header(
        shape_xyz=f.shape_xyz,
        spacing=f.spacing,
        origin=f.origin,
        vmin=f.vmin,
        vmax=f.vmax,
        source_dtype=f.source_dtype,
        source_itemsize=f.source_itemsize,
        name=f.name,
        encoding=encoding,
        seed=opts.seed,
    )
