"""The staged encoder driver: P, S1a-S1e, S1x, (S2), S3, EV, each timed and memory-profiled.

    model = warpgauss.encode("scan.nii.gz", ratio=100)          # or an array, or example="vortex"
    model.save("scan.wgs"); model.report["evaluation"]["final"]["psnr_db"]

Everything up to the budget check runs without Warp, so an impossible request is refused at once.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._version import __version__
from .allocate import AllocationConfig, allocate
from .analysis import Field, budget_from_bytes, check_budget, normalise, seed_limit
from .devicefield import device_array, is_device_array, normalise_on_device
from .errors import WarpgaussError
from .io import ReadOptions  # noqa: F401 - part of this module's API (stage P's options)
from .model import Model, make_header
from .optimize import PRESETS, RefineConfig
from .profiling import StageRecorder
from .readers.timesteps import TimeStep

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
    evaluate_start: bool = True  # EV also scores the starting model (a warm start's: the previous timestep's)
    motion: bool = True  # a warm start's primitives first follow the motion to the new timestep (warpgauss.motion)
    cold_start_psnr: float | None = None  # warm only if the (moved) start scores at least this, else allocate


def _available_memory() -> int | None:
    """Bytes of physical memory available now (Linux), or None where that cannot be read."""
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def load_field(
    source,
    read: ReadOptions | None = None,
    *,
    example: str | None = None,
    example_size: int | tuple[int, int, int] = 64,
    lazy: bool = False,
    buffers=None,
) -> tuple[Field, dict]:
    """Stage P: read (or generate) the volume, apply the stride, mask and normalise it (``lazy``:
    a file the format lets us leave where it is is read on demand, see :mod:`warpgauss.lazy`).

    Args:
        source: A path, a 3D numpy array (nz, ny, nx), a device array (Warp, or DLPack /
            ``__cuda_array_interface__``: normalised where it is, see :mod:`warpgauss.devicefield`),
            or None with ``example``.
        read: Reader options for a path (and stride / fill value for any source).
        example: Name of a built-in example volume (see :mod:`warpgauss.synthetic`).
        buffers: A device array's normalised values go there (:class:`warpgauss.devicefield.DeviceBuffers`).

    Returns:
        (normalised field, description of the input for the report)
    """
    read = read or ReadOptions()
    if read.stride < 1:
        raise WarpgaussError(f"--stride must be a positive integer, got {read.stride}")
    s = read.stride
    fill = read.fill_value
    if example is not None:
        from .analysis import MAX_VOXELS
        from .synthetic import generate

        dims = (example_size,) * 3 if isinstance(example_size, (int, np.integer)) else tuple(example_size)
        voxels = int(np.prod([int(d) for d in dims], dtype=object))
        if voxels > MAX_VOXELS:
            largest = int(round(MAX_VOXELS ** (1 / 3))) - 1
            raise WarpgaussError(
                f"--size {example_size} gives {voxels:,} voxels, more than the {MAX_VOXELS:,} warpgauss indexes; use --size {largest} or less"
            )
        free = _available_memory()
        if free is not None and 3 * 4 * voxels > free:  # the float32 field and generation temporaries
            raise WarpgaussError(
                f"--size {example_size} needs about {3 * 4 * voxels / 2**30:.1f} GiB to generate, more than the "
                f"{free / 2**30:.1f} GiB available; use a smaller --size"
            )
        data = generate(example, example_size, seed=0)[::s, ::s, ::s]
        name, spacing, origin, dtype, path = example, (float(s),) * 3, (0.0, 0.0, 0.0), "float32", None
    elif is_device_array(source):  # stays where it is: stage P runs on its device
        arr = device_array(source)
        f = normalise_on_device(arr[::s, ::s, ::s] if s > 1 else arr, fill_value=fill, spacing=(float(s),) * 3, buffers=buffers)
        info = {"read_lazily": False, "name": "array", "path": None, "example": None, "on_device": str(arr.device)}
        return f, {**info, **_field_facts(f, s, fill)}
    elif isinstance(source, TimeStep):  # one timestep of a file with a time axis, with its attributes
        data = source.read()[::s, ::s, ::s]
        (sx, sy, sz), origin, declared_fill = source.meta()
        spacing = (sx * s, sy * s, sz * s)
        name, dtype, path = f"{Path(source.path).name}:{source.key}[{source.t}]", str(data.dtype), str(source)
        if fill is None:
            fill = declared_fill
    elif isinstance(source, np.ndarray):
        if source.ndim != 3:
            raise WarpgaussError(f"the array is {source.ndim}D (shape {source.shape}); warpgauss encodes 3D volumes")
        data = source[::s, ::s, ::s]
        name, spacing, origin, dtype, path = "array", (float(s),) * 3, (0.0, 0.0, 0.0), str(source.dtype), None
    elif isinstance(source, (str, os.PathLike)):
        vol = read.read(source, lazy=lazy)
        data, name, spacing, origin = vol.data, vol.name, vol.spacing, vol.origin
        dtype, path = vol.source_dtype or str(vol.data.dtype), str(source)
        if fill is None and getattr(vol, "fill_value", None) is not None:
            fill = vol.fill_value
    else:
        raise WarpgaussError("give a file path, a 3D numpy or device array (Warp, CuPy, PyTorch), or example=NAME as the source")
    from .lazy import source_of

    lazy = lazy and source_of(data) is not None
    f = normalise(data, fill_value=fill, spacing=spacing, origin=origin, name=name, source_dtype=dtype, lazy=lazy)
    info = {"read_lazily": lazy, "name": name, "path": path, "example": example}
    return f, {**info, **_field_facts(f, s, fill)}


def _field_facts(f: Field, stride: int, fill) -> dict:
    """The input description of a normalised field (the report's ``input``)."""
    return {
        "shape_xyz": list(f.shape_xyz),
        "source_dtype": f.source_dtype,
        "source_bytes": f.source_bytes,
        "stride": stride,
        "fill_value": fill,
        "value_min": f.vmin,
        "value_max": f.vmax,
        "masked_voxels": f.n_voxels - f.n_valid,
        "notes": list(f.notes),
    }


CODED_BPP_SIZING = 12  # bytes per primitive a coded file needs at most in practice (the "no room" check)
CODED_BPP_FLOOR = 4  # and at least: bounds N before its coded size is measured
# coded bytes per primitive of a refined model over its analytic allocation's: 1.19 / 1.22 / 1.22 /
# 1.34 on mni_icbm152 / inia19 / mean_reg2mean / nAChR water (benchmarks/results/i18_coded_cpu.json).
# N is sized a little below the median, so that a file rather comes out a few per cent over its
# budget, which pruning the least important primitives trims to within a primitive of it, than
# under it, which nothing after refinement can fill (coded.fit_bytes)
CODED_REFINE_GROWTH = 1.15
# refinement's gain over the analytic model, at least (full-grid PSNR, ratio 100, H100: vortex 512^3
# +18.9 dB, the three head MRIs +13.7 to +18.3 dB): the pilot sizes N for the bit depths a model
# that accurate needs (coded.bits_for_psnr), since an accurate model that must drop bits to fit
# loses more than the primitives cost. Measured on vortex 512^3 at ratio 100: N sized for the
# default depths (907,190) refined to 70.2 dB in float and 55.9 dB once fitted (mu at 0 bits);
# the float model at half that N scores 71.2 dB (benchmarks/results/i18_sizing_h100.json)
CODED_REFINE_GAIN_DB = 12.0
# a refined model pruned to fit its byte budget (coded.fit_bytes) may be refined again, the rest
# filling what the pruned ones carried: for this share of the iterations (at least
# REFIT_MIN_ITERATIONS), at REFIT_LR x the learning rate, when more than REFIT_MIN_PRUNED of the
# primitives went; then fitted once more. Off (0): measured on an H100 (benchmarks/results/accuracy/),
# a refit from fresh Adam moments moves every parameter by about the learning rate in its first
# steps and wrecks an accurate model (vortex 256^3 at ratio 300: 68.6 dB coded without, 43.6 with
# a refit at 0.3x, 47.7 at 0.02x); dropping bits beyond a 3 % excess (coded.PRUNE_SHARE) paid more
REFIT_SHARE = 0.0
# a coded byte budget's N is re-planned once the model's accuracy is known: after this share of the
# iterations the model is coded at the depths its expected final sample PSNR needs (extrapolated
# from the sample PSNR half-way there and now, at least REPLAN_REST_GAIN_DB more); where that,
# times REPLAN_GROWTH (how much larger the model codes by the end), exceeds the budget by more
# than REPLAN_TOLERANCE, the least important primitives are taken out and the rest refine on. The pilot's N (CODED_REFINE_GAIN_DB) under-predicts the depths
# of a model trained at voxel centres by 1-4 bits: refined models coded 1.2-2.3x their budget and
# lost 1-13 dB to the bits the rate control then dropped (benchmarks/results/accuracy/rd_*.json)
REPLAN_AT = 0.25
REPLAN_REST_GAIN_DB = 2.0
# the sample PSNR grows faster than linearly in log(iterations) as the learning rate decays: from
# K = T / 4 to T it gained 1.4-7.5x its gain from K / 2 to K (median 2.8, three MRIs at CR 10-1000,
# H100), on vortex and interface 256^3 about 2x (rd_*_replan_h100.json): 1.25 x log2(T / K)
REPLAN_EXTRAPOLATE = 1.25
REPLAN_MAX_GAIN_DB = 30.0
REPLAN_GROWTH = 1.05
REPLAN_TOLERANCE = 0.01
REPLAN_MIN_ITERATIONS = 100
# the bit depths a refined model is coded at: "accuracy" (bits_for_psnr of its sample PSNR) or
# "sizing" (those N was sized for; more only where the budget leaves room)
REFINED_BITS = "accuracy"
REFIT_MIN_ITERATIONS = 30
REFIT_LR = 0.3
REFIT_MIN_PRUNED = 0.01


DEFAULT_FORMAT = "coded"


def encoding_of(opts: EncodeOptions) -> str:
    """The file format of an encoding: ``format`` ("full" = float32, "compact" = compact96), else
    compact96 with ``compact``, else :data:`DEFAULT_FORMAT`."""
    from .wgs import _encoding

    if opts.format is None and not opts.compact:
        return DEFAULT_FORMAT
    return _encoding(opts.compact, opts.format)


def sizing_bpp(encoding: str) -> int:
    """Bytes per primitive a --ratio budget is sized with."""
    from .wgs import ENCODINGS

    return ENCODINGS[encoding] or CODED_BPP_SIZING


def target_bytes(f: Field, opts: EncodeOptions) -> int | None:
    """The file size budget of --bytes or --ratio (floor(S_src / R)); None with --budget."""
    given = [k for k, v in (("--budget", opts.budget), ("--ratio", opts.ratio), ("--bytes", opts.bytes)) if v is not None]
    if len(given) > 1:
        raise WarpgaussError(f"give one of --budget, --ratio and --bytes, not {' and '.join(given)}")
    if opts.budget is not None:
        return None
    if opts.bytes is not None:
        if isinstance(opts.bytes, bool) or not isinstance(opts.bytes, (int, np.integer)) or opts.bytes < 1:
            raise WarpgaussError(f"--bytes must be a positive whole number of bytes, got {opts.bytes!r}")
        return int(opts.bytes)
    ratio = opts.ratio or DEFAULT_RATIO
    if not ratio > 0:
        raise WarpgaussError(f"--ratio must be positive, got {ratio}")
    return int(f.source_bytes // ratio)


def resolve_budget(f: Field, opts: EncodeOptions, header_bytes: int) -> int:
    """N from --budget, --ratio or --bytes (SPEC section 4), validated against the seed limit:
    floor((bytes - H) / bytes per primitive), for the coded format an upper bound that
    :func:`coded_budget` refines once the volume is analysed."""
    bpp = sizing_bpp(encoding_of(opts))
    total = target_bytes(f, opts)
    if total is None:
        n = int(opts.budget)
    else:
        n = budget_from_bytes(total, f.source_bytes, header_bytes, bpp)
    if encoding_of(opts) == "coded" and total is not None:
        # a bound: the coded N is measured once the volume is analysed (coded_budget), at most N_max
        n_max = seed_limit(f.eligible, f.occupied)
        n = max(1, min(n_max, int((total - header_bytes) // CODED_BPP_FLOOR)))
        check_budget(f, n, header_bytes, bpp)
        return n
    check_budget(f, n, header_bytes, bpp)
    return n


def coded_budget(dv, f: Field, opts: EncodeOptions, header: dict, total: int, n_bound: int) -> tuple[int, dict]:
    """N for a coded file of ``total`` bytes: a pilot allocation's coded size per primitive, times
    the growth refinement brings (:data:`CODED_REFINE_GROWTH`; 1 without refinement), at the bit
    depths the expected accuracy needs (the pilot's PSNR plus :data:`CODED_REFINE_GAIN_DB` when
    refining, see :func:`warpgauss.coded.bits_for_psnr`)."""
    from .coded import bits_for_psnr
    from .evaluate import evaluate_field
    from .wgs import header_size, payload_size, wgs_bytes

    pilot = max(1, min(n_bound, (total - header_size(header, n_bound, encoding="coded")) // 8))
    params, _ = allocate(dv, pilot, opts.seed, opts.allocation, StageRecorder())
    refining = opts.refine.iterations > 0
    pilot_db = evaluate_field(Model(params, header).field(dv.device), f)["psnr_db"]
    expected = pilot_db + (CODED_REFINE_GAIN_DB if refining else 0.0)
    bits, extra = bits_for_psnr(expected)
    data = wgs_bytes(params, header, encoding="coded", bits=bits)
    payload = payload_size(data)
    bpp = payload / pilot
    # the pilot's own header (the reserved bound is a few hundred bytes wider: at small budgets
    # that is a good share of the payload)
    head = len(data) - payload + 32
    growth = CODED_REFINE_GROWTH if refining else 1.0
    n = max(1, min(n_bound, int((total - head) // (bpp * growth))))
    return n, {
        "pilot_n": pilot,
        "pilot_psnr_db": pilot_db,
        "expected_psnr_db": expected,
        "bits": bits,
        "bits_added": extra,
        "pilot_bytes_per_primitive": bpp,
        "header_bytes": head,
        "refine_growth": growth,
        "n": n,
    }


def _coded_choice(sizing: dict | None, fit: dict | None, note: dict | None, replan: dict | None = None) -> str | None:
    """One sentence on how a coded file met its budget: primitives against precision."""
    if sizing is None and note is None:
        return None
    parts = []
    if sizing is not None:
        grids = (
            f"{sizing['bits_added']} bit(s) over the default grids, for the {sizing['expected_psnr_db']:.1f} dB expected "
            f"(pilot {sizing['pilot_psnr_db']:.1f} dB + refinement), since an accurate model that drops bits to fit loses more than "
            "the Gaussians cost (benchmarks/results/i18_sizing_h100.json)"
            if sizing["bits_added"]
            else "the default grids, since each of their bits costs less PSNR than the Gaussians its bytes would buy "
            "(benchmarks/results/i18_coded_cpu.json)"
        )
        parts.append(
            f"N {sizing['n']:,} from a pilot of {sizing['pilot_n']:,} at {sizing['pilot_bytes_per_primitive']:.2f} B x "
            f"{sizing['refine_growth']:.2f} (refined models code larger); {grids}"
        )
    if replan is not None:
        took = replan["n_before"] - replan["n_after"]
        parts.append(
            f"at iteration {replan['iteration']} the model scored {replan['sample_psnr_db']:.1f} dB on its samples and "
            + (
                f"would code at {replan['predicted_bytes']:,.0f} bytes on the grids that accuracy needs: its {took:,} least "
                "important Gaussians were taken out and the rest refined on"
                if took
                else "fitted its budget on the grids that accuracy needs"
            )
        )
    if note is not None and note["bits_added"]:
        parts.append(f"{note['bits_added']} bit(s) more on every attribute for a {note['sample_psnr_db']:.1f} dB model")
    if fit is not None:
        did = ", ".join(fit["steps"]) or "no depth changed"
        pruned = f"{fit['pruned']:,} least important Gaussians pruned"
        if fit.get("refit"):
            pruned += f", the rest refined again for {fit['refit']['iterations']} iterations"
        parts.append(
            f"rate control: {did}; {pruned} (an excess up to {fit.get('prune_share', 0):.0%} is pruned, beyond it bits "
            "are dropped first: a pruned model keeps holes that cost more, benchmarks/results/accuracy/)"
        )
    return "; ".join(parts)


def resolve_refine(refine: RefineConfig | None, preset: str | None, iterations: int | None, samples: int | None) -> RefineConfig:
    """Refinement settings from a preset, overridden by explicit iterations / samples."""
    cfg = refine or RefineConfig()
    if preset is not None:
        if preset not in PRESETS:
            raise WarpgaussError(f"unknown preset {preset!r}; use one of {', '.join(PRESETS)}")
        cfg = dataclasses.replace(cfg, **PRESETS[preset])
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


def _header_for(f: Field, opts: EncodeOptions) -> dict:
    header = _base_header(f, opts)
    if encoding_of(opts) == "coded":  # every byte counts: the default LUT is regenerated from its colormap and opacity
        header["transfer_function"] = {k: v for k, v in header["transfer_function"].items() if k != "lut_rgba8"}
    return header


def _base_header(f: Field, opts: EncodeOptions) -> dict:
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


def encode_field(
    f: Field,
    opts: EncodeOptions,
    *,
    device: str | None = None,
    timer: StageRecorder | None = None,
    input_info: dict | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    on_stats: Callable[[dict], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
    log_every: int = 25,
    analytic_output=None,
    force: bool = False,
    cache: dict | None = None,
) -> Model:
    """Stages S1a-S1e, S1x, S2 and EV on a normalised field; returns the model with its report.

    The body is the paper's stage table; each stage is a method of :class:`_EncodeRun`, which
    also holds the skip decisions (the report's ``skipped`` list) and assembles the report.

    Args:
        f: Output of stage P.
        opts: Encoding options (budget or ratio, seed, allocation knobs).
        device: Warp device (None: CUDA when present, else CPU).
        timer: Stage recorder (stage P may already be in it).
        input_info: Input description for the report.
        evaluate: Run stage EV.
        full_eval: Evaluate on the full grid instead of 500,000 sampled voxels.
        on_stats: Optional callback(stats dict), called as soon as the structure statistics exist.
        on_progress: Optional callback(iteration, total, losses) during refinement.
        log_every: Iterations between loss records (and progress calls).
        analytic_output: If given, also write the analytic (pre-refinement) model there (S1x).
        force: Overwrite ``analytic_output`` if it exists.
        cache: A dict shared by encodes of the same field on the same device (a budget ladder):
            the device volume and structure statistics of the first are reused (S1a skipped).
    """
    run = _EncodeRun(f, opts, device, timer, evaluate, full_eval, analytic_output)
    run.analyse(cache, on_stats)  # S1a   occupancy, gradients, structure statistics
    run.size_coded()  # S1p   coded size pilot (a coded byte budget only)
    run.allocate()  # S1b-e seeds, shapes, values and weights
    run.analytic_model(force)  # S1x   the analytic model (and --save-analytic)
    run.check_target()  # EVa   --target-psnr: is refinement needed at all?
    run.refine(on_progress, log_every)  # S2    refinement
    run.evaluate()  # EV    PSNR; keep the better of the two models
    return run.result(input_info)  # the model, its file size and its report


class _EncodeRun:
    """One encode's state between the stages of :func:`encode_field`, the skip decisions (each
    recorded in ``skipped`` with why) and the report assembly."""

    def __init__(self, f: Field, opts: EncodeOptions, device, timer, evaluate: bool, full_eval: bool, analytic_output):
        from ._warp import resolve_device, warp
        from .wgs import header_size

        self.f = f
        self.enc = encoding_of(opts)
        self.budget_bytes = target_bytes(f, opts)  # the file size budget, or None for an explicit N
        self.header = _header_for(f, opts)
        self.n = resolve_budget(f, opts, header_size(self.header, 1 << 40, encoding=self.enc))
        self.wp = warp()
        self.dev = resolve_device(device)
        self.voxels = int(np.prod(f.shape_xyz))
        self.base_refine = opts.refine
        scaled = opts.refine.for_budget(self.n, self.voxels, self.dev)
        if scaled is not opts.refine:  # more samples for a large budget or a GPU: the header says so
            opts = dataclasses.replace(opts, refine=scaled)
            self.header = _header_for(f, opts)
            self.n = resolve_budget(f, opts, header_size(self.header, 1 << 40, encoding=self.enc))
        self.opts = opts
        self.timer = timer or StageRecorder()
        self.timer.device = self.dev
        self.skipped: list[dict] = []
        self.do_evaluate, self.full_eval = evaluate, full_eval
        self.sizing: dict | None = None
        self.analytic_fit: dict | None = None
        self.refined_fit: dict | None = None
        self.coded_bits_note: dict | None = None
        self.refinement: dict = {"iterations": 0}
        self.replan: dict | None = None  # the re-plan of N during refinement (coded byte budgets)
        self.replan_half: float | None = None  # the sample PSNR half-way to the re-plan
        self.early_eval: dict | None = None
        self.start_eval: dict | None = None  # a warm start scored before refinement (to choose warm or cold)
        self.start_choice: dict | None = None
        self.evaluation: dict = {}
        # a coded byte budget fits the analytic model (several codings) only where it may be the
        # result: no refinement, an --analytic-output file, or a refined model that scores below it
        self.fit_later = self.enc == "coded" and self.budget_bytes is not None and opts.refine.iterations > 0 and analytic_output is None
        self.analytic_output = analytic_output

    def skip(self, what: str, why: str, **facts) -> None:
        self.skipped.append({"what": what, "why": why, **facts})

    def stored(self, m: Model) -> tuple[Model, dict | None]:
        """The model as the file will hold it (coded: fitted to the byte budget)."""
        if self.enc == "coded" and self.budget_bytes is not None:
            return m.fit_bytes(self.budget_bytes)
        m = m.stored(self.enc)
        m.format = self.enc
        return m, None

    def _evaluate(self, m: Model) -> dict:
        from .evaluate import evaluate_field

        return evaluate_field(m.field(self.dev), self.f, full=self.full_eval)

    # -- S1a ---------------------------------------------------------------------------------
    def analyse(self, cache: dict | None, on_stats) -> None:
        from .analysis import DeviceVolume, structure_stats

        f, dev = self.f, self.dev
        if cache is not None and cache.get("device") == dev and cache.get("field") is f:
            self.dv, self.stats = cache["dv"], cache["stats"]
            self.skip("S1a", "device volume and statistics reused from the previous budget of the ladder", seconds_saved=cache["seconds"])
        elif self.opts.init is not None or self.opts.deadline is not None:
            # a warm start allocates nothing, and an Encoder call on a time budget spends nothing on
            # figures only the report would show: the statistics are skipped
            with self.timer.stage("S1a", "the field on the device"):
                self.dv = DeviceVolume(f, dev)
            self.stats = None
            why = (
                "warm start: no allocation needs them"
                if self.opts.init is not None
                else "an Encoder call on a time budget: only the report would show them"
            )
            self.skip("S1a structure statistics", why)
            return
        else:
            t0 = time.perf_counter()
            with self.timer.stage("S1a", "occupancy, gradients, structure statistics"):
                self.dv = DeviceVolume(f, dev)
                self.stats = structure_stats(self.dv)
            if cache is not None:
                cache.update({"device": dev, "field": f, "dv": self.dv, "stats": self.stats, "seconds": time.perf_counter() - t0})
        if on_stats is not None:
            on_stats(self.stats)

    # -- S1p ---------------------------------------------------------------------------------
    def size_coded(self) -> None:
        if self.enc != "coded" or self.budget_bytes is None:
            return
        with self.timer.stage("S1p", "coded size pilot"):
            self.n, self.sizing = coded_budget(self.dv, self.f, self.opts, self.header, self.budget_bytes, self.n)
            scaled = self.base_refine.for_budget(self.n, self.voxels, self.dev)
            if scaled != self.opts.refine:  # the samples follow the measured N, not its bound
                self.opts = dataclasses.replace(self.opts, refine=scaled)
                self.header = _header_for(self.f, self.opts)

    # -- S1b-S1e -----------------------------------------------------------------------------
    def allocate(self) -> None:
        init = self.opts.init
        if init is None:
            self.params, self.facts = allocate(self.dv, self.n, self.opts.seed, self.opts.allocation, self.timer)
            return
        if init.shape != (self.n, 12):
            raise WarpgaussError(
                f"a warm start needs a model of the same budget: the previous model has {init.shape[0]:,} Gaussians, this encode {self.n:,}; "
                "give --budget N of the previous model (or encode cold)"
            )
        self.params = np.array(init, np.float32, copy=True)
        self.facts = {"warm_start": True, "n": self.n}
        self.skip("S1b-S1e allocation", "warm start: the previous timestep's model is the starting point")
        as_given = self.opts
        if self.opts.motion:
            from .motion import WARM_LR_SCALE, compensate

            with self.timer.stage("S1m", "motion compensation of the warm start"):
                self.params, self.facts["motion"] = compensate(self.params, self.dv)
            # the rate of the refinement that follows (see WARM_LR_SCALE for what was measured)
            if WARM_LR_SCALE != 1.0:
                cfg = self.opts.refine
                self.opts = dataclasses.replace(self.opts, refine=dataclasses.replace(cfg, lr=cfg.lr * WARM_LR_SCALE))
                self.header = _header_for(self.f, self.opts)  # the file says which rates refined it
            self.facts["motion"]["lr_scale"] = WARM_LR_SCALE
        else:
            self.skip("S1m motion compensation", "motion=False: the previous model starts where it was")
        ref = self.opts.cold_start_psnr
        if ref is None:
            return
        with self.timer.stage("S1w", "warm or cold: score the warm start"):
            self.start_eval = self._evaluate(Model(self.params, self.header))
        start = self.start_eval["psnr_db"]
        warm = start >= ref
        self.start_choice = {
            "warm": warm,
            "warm_start_psnr_db": start,
            "last_cold_start_psnr_db": ref,
            "why": "the warm start scores at least what the last cold start's allocation did"
            if warm
            else "the warm start scores below what the last cold start's allocation did: the field changed too much",
        }
        if not warm:  # allocate afresh (the warm start's score is not the start model's any more)
            self.start_eval = None
            self.skipped = [x for x in self.skipped if x["what"] != "S1b-S1e allocation"]
            self.opts = dataclasses.replace(as_given, init=None, evaluate_start=True)
            self.header = _header_for(self.f, self.opts)
            self.params, self.facts = allocate(self.dv, self.n, self.opts.seed, self.opts.allocation, self.timer)

    # -- S1x ---------------------------------------------------------------------------------
    def analytic_model(self, force: bool) -> None:
        with self.timer.stage("S1x", "analytic model"):
            analytic = Model(self.params, self.header)
            analytic.coded_bits = None if self.sizing is None else self.sizing["bits"]  # the depths N was sized for
            self.analytic, self.analytic_fit = (analytic, None) if self.fit_later else self.stored(analytic)
            if self.analytic_output is not None:
                self.analytic.save(self.analytic_output, encoding=self.enc, force=force)
        if self.fit_later:
            self.skip(
                "S1x rate control of the analytic model",
                "it is fitted to the byte budget only if the refined model scores below it; until then it is evaluated as allocated",
            )
        self.model = self.analytic

    # -- EVa: --target-psnr ------------------------------------------------------------------
    def check_target(self) -> None:
        cfg = self.opts.refine
        if not (cfg.iterations > 0 and cfg.target_psnr is not None and self.do_evaluate):
            return
        with self.timer.stage("EVa", "analytic model evaluation (for --target-psnr)"):
            self.early_eval = self._evaluate(self.analytic)
        if self.early_eval["psnr_db"] < cfg.target_psnr:
            return
        self.skip(
            "S2 refinement", f"the analytic model already reaches the target ({self.early_eval['psnr_db']:.2f} >= {cfg.target_psnr:g} dB)"
        )
        self.refinement = {
            "iterations": 0,
            "stop": {"reason": "target PSNR reached by the analytic model", "iterations_skipped": cfg.iterations},
        }
        if self.fit_later:  # it is the result: fitted to the budget and scored as stored
            self.analytic, self.analytic_fit = self.stored(self.analytic)
            self.model = self.analytic
            self.early_eval = self._evaluate(self.analytic)

    # -- S2 ----------------------------------------------------------------------------------
    def refine(self, on_progress, log_every: int) -> None:
        if self.opts.refine.iterations == 0:
            self.skip("S2 refinement", "iterations = 0: the analytic model is the result")
            return
        if self.refinement.get("stop"):
            return
        from .refine import Refiner, load_kernels

        opts, cfg, dev, refinement = self.opts, self.opts.refine, self.dev, self.refinement
        cap = opts.allocation.resolved_cap(self.f.shape_xyz)
        with self.timer.stage("S2", "refinement"):
            load_kernels(dev)
            stage_start = time.perf_counter()  # the time budget starts with compiled kernels
            refiner = Refiner(self.dv, self.params, cfg, opts.seed, opts.allocation.scale_min, cap)
            self._sampling_skips(refiner)
            ckpt = _Checkpoints(opts, self.params, cfg, dev)
            if opts.resume:
                ckpt.resume(refiner)
            self._self_test(refiner)
            if cfg.target_psnr is not None or cfg.plateau_db is not None:
                refiner.set_validation(self.f)
            t0 = time.perf_counter()
            deadline = opts.deadline
            if opts.time_budget is not None and not opts.resume:  # 5 % reserve for the export
                deadline = stage_start + 0.95 * opts.time_budget
            ckpt.start(t0)
            after_step = ckpt.maybe_save
            replan_at = self._replan_iteration(deadline)
            if replan_at is not None:

                def after_step(r, save=ckpt.maybe_save, at=replan_at):
                    if r.iteration == at // 2:
                        self.replan_half = float(r.losses()["sample_psnr_db"])
                    elif r.iteration == at:
                        self._replan(r)
                    save(r)

            with _stop_on_sigint(refiner):
                history = refiner.run(progress=on_progress, log_every=log_every, deadline=deadline, after_step=after_step)
            seconds = time.perf_counter() - t0
            if refiner.interrupted:
                ckpt.save(refiner)
            params = refiner.model_params()
            refined = Model(params[: refiner.n_live], self.header)  # without those the re-plan took out
            if REFINED_BITS == "sizing" and self.sizing is not None:  # the depths N was sized for
                refined.coded_bits = dict(self.sizing["bits"])
            elif self.enc == "coded" and history:
                from .coded import bits_for_psnr  # finer grids for a more accurate model

                refined.coded_bits, extra = bits_for_psnr(history[-1].get("sample_psnr_db"))
                self.coded_bits_note = {
                    "sample_psnr_db": history[-1].get("sample_psnr_db"),
                    "bits_added": extra,
                    "bits": refined.coded_bits,
                }
            self.model, self.refined_fit = self.stored(refined)
            if self.refined_fit is not None and not refiner.interrupted:
                self._refit(refined, cap, deadline)
        sessions = ckpt.sessions + [{"from_iteration": ckpt.start_iteration, "to_iteration": refiner.iteration, "seconds": seconds}]
        total = sum(x["seconds"] for x in sessions)
        refinement.update(
            {
                "time_budget": refiner.budget,
                "iterations": refiner.cfg.iterations,
                "samples": refiner.m,
                "samples_rule": self.base_refine.samples_rule(self.n, self.voxels, dev)[1],
                "seconds": total,
                "sessions": sessions,
                "iterations_done": refiner.iteration,
                "interrupted": refiner.interrupted,
                "checkpoint": ckpt.report(),
                "contacts_per_primitive": refiner.contacts,
                "lr_touch_scale": refiner.touch_scale,
                "ms_per_iteration": 1000 * total / max(refiner.iteration, 1),
                "skipped_nonfinite_updates": refiner.skipped_steps(),
                "deferred_updates": refiner.deferred_steps(),
                "rebins": refiner.rebins,
                "cuda_graph": refiner.use_graph,
                "cuda_graph_error": refiner.graph_error,
                "strata_samples": dict(zip(("high", "mid", "uniform"), refiner.strata)),
                "uniform_support_share": refiner.support_share(),
                "loss_history": history,
            }
        )
        if refiner.stop_reason is not None:
            left = refiner.cfg.iterations - refiner.iteration
            refinement["stop"] = {
                "reason": refiner.stop_reason,
                "at_iteration": refiner.iteration,
                "iterations_skipped": left,
                "seconds_saved_estimate": left * total / max(refiner.iteration, 1),
                "checks": refiner.checks,
            }
            self.skip(
                f"S2 iterations {refiner.iteration}-{refiner.cfg.iterations}",
                refiner.stop_reason,
                seconds_saved=refinement["stop"]["seconds_saved_estimate"],
            )
        elif refiner.checks:
            refinement["checks"] = refiner.checks
        if refiner.interrupted:
            self.do_evaluate = False
            self.skip("EV evaluation", f"interrupted at iteration {refiner.iteration}")

    def _replan_iteration(self, deadline: float | None) -> int | None:
        """The iteration after which a coded byte budget's N is re-planned (see :data:`REPLAN_AT`),
        or None where it is not: no coded byte budget, a warm start, a time budget."""
        cfg = self.opts.refine
        if self.enc != "coded" or self.budget_bytes is None or REPLAN_AT <= 0 or self.opts.init is not None:
            return None
        if deadline is not None or cfg.iterations < REPLAN_MIN_ITERATIONS:
            return None
        return max(1, int(round(REPLAN_AT * cfg.iterations)))

    def _replan(self, refiner) -> None:
        """N for the bit depths the model's accuracy needs: at :data:`REPLAN_AT` of the iterations
        the current model is coded at the depths of its expected final sample PSNR;
        where that (times :data:`REPLAN_GROWTH`) exceeds the budget, the least important
        primitives are taken out (:meth:`Refiner.silence`) and the others refine on to fill in."""
        from .coded import bits_for_psnr, importance
        from .wgs import payload_size, wgs_bytes

        assert self.budget_bytes is not None
        at = float(refiner.losses()["sample_psnr_db"])
        # the sample PSNR grows about linearly in log(iterations): what it gained from K/2 to K,
        # times log2(T / K), is what the rest of the run adds (at least REPLAN_REST_GAIN_DB)
        half = self.replan_half if self.replan_half is not None and math.isfinite(self.replan_half) else at
        t_total, k = self.opts.refine.iterations, refiner.iteration
        rest = max(REPLAN_REST_GAIN_DB, (at - half) * REPLAN_EXTRAPOLATE * math.log2(t_total / k))
        expected = at + min(rest, REPLAN_MAX_GAIN_DB)
        bits, extra = bits_for_psnr(expected)
        params = refiner.model_params()
        n = len(params)
        data = wgs_bytes(params, self.header, encoding="coded", bits=bits)
        payload = payload_size(data)
        head = len(data) - payload
        predicted = head + payload * REPLAN_GROWTH
        keep = n
        if predicted > self.budget_bytes * (1.0 + REPLAN_TOLERANCE):
            keep = max(1, int(n * (self.budget_bytes - head) / (payload * REPLAN_GROWTH)))
            order = np.argsort(importance(params), kind="stable")  # least important first
            refiner.silence(order[: n - keep])
        self.replan = {
            "iteration": refiner.iteration,
            "sample_psnr_db": at,
            "sample_psnr_db_at_half": half,
            "expected_psnr_db": expected,
            "bits": bits,
            "bits_added": extra,
            "coded_bytes_now": len(data),
            "predicted_bytes": predicted,
            "n_before": n,
            "n_after": keep,
        }

    def _refit(self, refined: Model, cap: float, deadline: float | None) -> None:
        """A model pruned to its byte budget, refined again briefly without the pruned primitives
        (see :data:`REFIT_SHARE`) and fitted once more; the report's ``coded_fit.refit`` says so."""
        from .refine import Refiner

        fit, kept = self.refined_fit, self.model.kept_rows
        assert fit is not None
        cfg = self.opts.refine
        if kept is None or fit["pruned"] <= REFIT_MIN_PRUNED * refined.n or REFIT_SHARE <= 0:
            return
        if deadline is not None and time.perf_counter() >= deadline:
            self.skip("refit of the pruned model", "the time budget is spent", pruned=fit["pruned"])
            return
        iterations = max(REFIT_MIN_ITERATIONS, int(round(REFIT_SHARE * cfg.iterations)))
        rcfg = dataclasses.replace(
            cfg, iterations=iterations, lr=cfg.lr * REFIT_LR, target_psnr=None, plateau_db=None, budget_samples=False
        )
        t0 = time.perf_counter()
        refiner = Refiner(self.dv, refined.params[kept], rcfg, self.opts.seed, self.opts.allocation.scale_min, cap)
        history = refiner.run(log_every=max(iterations, 1), deadline=deadline)
        again = Model(refiner.model_params(), self.header)
        again.coded_bits = fit["bits"]
        self.model, refit = self.stored(again)
        assert refit is not None
        first = {k: fit[k] for k in ("steps", "pruned", "bytes", "first_bytes", "bits")}
        self.refined_fit = {
            **refit,
            "pruned": fit["pruned"] + refit["pruned"],
            "steps": fit["steps"] + refit["steps"],
            "first_bytes": fit["first_bytes"],
            "refit": {
                "iterations": refiner.iteration,
                "lr_scale": REFIT_LR,
                "seconds": time.perf_counter() - t0,
                "first_fit": first,
                "pruned_after": refit["pruned"],
                "sample_psnr_db": history[-1].get("sample_psnr_db") if history else None,
            },
        }

    def _sampling_skips(self, refiner) -> None:
        """Where the refiner draws no samples, and why (recorded before it runs)."""
        if refiner.uniform_occupied:
            occ = refiner.n_high + refiner.n_mid
            self.skip(
                "uniform samples in empty space",
                f"value_empty = 0: a sample where V <= 0.02 adds no loss; the uniform stratum is drawn among the {occ:,} occupied voxels",
                uniform_samples_moved_share=1.0 - occ / self.dv.field.values.size,
            )
        elif refiner.uniform_support:
            share = refiner.support_share()
            if share < 1.0:
                self.skip(
                    "uniform samples outside the model's support",
                    "no Gaussian's 5-sigma box (+2 voxels) reaches there: a sample would score 0 with no gradient; "
                    "the uniform stratum is drawn over the 4^3 bricks the boxes reach, re-marked at every re-bin",
                    share_skipped_at_start=1.0 - share,
                )
        if not refiner.partners:
            self.skip(
                "partner points",
                "smoothness weight 0: the partners serve only that term, so each iteration evaluates the samples alone (half the points)",
            )

    def _self_test(self, refiner) -> None:
        """The binned-vs-dense self-test: once per process and device (the kernels cannot change)."""
        from .refine import SELF_TESTS, self_test

        dev = self.dev
        if self.opts.self_test and dev in SELF_TESTS:
            self.refinement["self_test"] = {**SELF_TESTS[dev], "reused": True, "seconds": 0.0}
            self.skip("self-test", "passed earlier in this process on this device", seconds_saved=SELF_TESTS[dev]["seconds"])
        elif self.opts.self_test:  # the self-test leaves the training state as it was
            t0 = time.perf_counter()
            self.refinement["self_test"] = self_test(refiner)
            self.refinement["self_test"]["seconds"] = time.perf_counter() - t0
            SELF_TESTS[dev] = dict(self.refinement["self_test"])
        else:
            self.skip("self-test", "--no-self-test")

    # -- EV ----------------------------------------------------------------------------------
    def evaluate(self) -> None:
        if not self.do_evaluate:
            if not self.refinement.get("interrupted"):
                self.skip("EV evaluation", "disabled by the caller")
            return
        evaluation = self.evaluation
        if self.opts.init is not None and not self.opts.evaluate_start and self.model is not self.analytic:
            with self.timer.stage("EV", "evaluation"):
                evaluation["analytic"] = self.start_eval
                evaluation["final"] = self._evaluate(self.model)
            evaluation["gain_db"] = None if self.start_eval is None else evaluation["final"]["psnr_db"] - self.start_eval["psnr_db"]
            if self.start_eval is None:
                self.skip("EV of the starting model", "an Encoder call on a time budget scores only the model it returns")
            return
        with self.timer.stage("EV", "evaluation"):
            evaluation["analytic"] = self.early_eval or self.start_eval or self._evaluate(self.analytic)
            if self.model is self.analytic:
                evaluation["final"] = evaluation["analytic"]
            else:
                t0 = time.perf_counter()
                evaluation["final"] = self._evaluate(self.model)
                share = evaluation["final"].get("bricks_evaluated_share")
                if share is not None and 0.0 < share < 1.0:
                    self.skip(
                        "empty 8^3 bricks in the full-grid evaluation",
                        "no Gaussian's 5-sigma box reaches them: written 0 without evaluation (exactly the model's value)",
                        share_skipped=1.0 - share,
                        seconds_saved_estimate=(time.perf_counter() - t0) * (1.0 - share) / share,
                    )
                self._keep_the_better(evaluation)
        evaluation["gain_db"] = evaluation["final"]["psnr_db"] - evaluation["analytic"]["psnr_db"]

    def _keep_the_better(self, evaluation: dict) -> None:
        """A refinement that scores below the analytic model (e.g. too few iterations for a large
        N) is discarded, the analytic model compared as it would be stored."""
        refined_db, analytic_db = evaluation["final"]["psnr_db"], evaluation["analytic"]["psnr_db"]
        if refined_db < analytic_db and self.fit_later:
            self.analytic, self.analytic_fit = self.stored(self.analytic)
            evaluation["analytic"] = self._evaluate(self.analytic)
            analytic_db = evaluation["analytic"]["psnr_db"]
        if refined_db < analytic_db:
            evaluation["discarded_refined"] = evaluation["final"]
            evaluation["final"] = evaluation["analytic"]
            self.model = self.analytic
            self.skip(
                "refined model",
                f"it scored {refined_db:.2f} dB, below the analytic model's {analytic_db:.2f} dB: the analytic model is the result",
            )

    # -- the report --------------------------------------------------------------------------
    def result(self, input_info: dict | None) -> Model:
        from ._warp import device_name

        f, opts, model, dev = self.f, self.opts, self.model, self.dev
        is_analytic = model is self.analytic
        size, payload = model.file_sizes(encoding=self.enc)  # one coding of a coded model gives both
        fit = self.analytic_fit if is_analytic else self.refined_fit
        note = None if is_analytic else self.coded_bits_note
        model.report = {
            "warpgauss_version": __version__,
            "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "device": dev,
            "device_name": device_name(dev),
            "warp_version": self.wp.config.version,
            "host": platform.node(),
            "input": input_info or {"name": f.name, "shape_xyz": list(f.shape_xyz)},
            "budget": {
                "n": model.n,
                "requested_budget": opts.budget,
                "requested_ratio": opts.ratio if opts.budget is None and opts.bytes is None else None,
                "requested_bytes": self.budget_bytes,
                "budget_used": None if self.budget_bytes is None else size / self.budget_bytes,
                "coded_sizing": self.sizing,
                "coded_replan": self.replan,
                "coded_fit": fit,
                "coded_bits_from_accuracy": note,
                "coded_choice": _coded_choice(self.sizing, fit, note, None if is_analytic else self.replan),
                "n_max": seed_limit(f.eligible, f.occupied),
                "format": self.enc,
                "bytes": size,
                "bytes_per_primitive": payload / model.n,
                "compression_ratio": model.source_bytes / size,
                "full_precision_bytes": model.file_size(False),
                "compact_bytes": model.file_size(True),
            },
            "seed": opts.seed,
            "structure": self.stats,
            "allocation": self.facts,
            "refinement": self.refinement,
            "evaluation": self.evaluation,
            "psnr_db": self.evaluation.get("final", {}).get("psnr_db"),
            "interrupted": bool(self.refinement.get("interrupted")),
            "skipped": self.skipped,
        }
        if self.start_choice is not None:
            model.report["start_choice"] = self.start_choice
        return model


class _Checkpoints:
    """When to write refinement checkpoints, and resuming from one (see :mod:`warpgauss.checkpoint`)."""

    def __init__(self, opts: EncodeOptions, params: np.ndarray, cfg: RefineConfig, device: str):
        from .checkpoint import fingerprint

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
        from .checkpoint import load as load_checkpoint

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
        from .checkpoint import save as save_checkpoint

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


class _stop_on_sigint:
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


def encode_bricked(
    f: Field,
    opts: EncodeOptions,
    bricks,
    *,
    halo: int | None = None,
    device: str | None = None,
    client=None,
    timer: StageRecorder | None = None,
    input_info: dict | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    on_progress: Callable[[int, int], None] | None = None,
    max_device_memory: int | None = None,
) -> Model:
    """The bricked encode (see :mod:`warpgauss.bricked`): the budget split over ``bricks`` (counts
    x, y, z) before any refinement, each brick encoded in this process (``client`` None) or on a
    Dask cluster, the primitives merged into one model of exactly N (then stored in the format,
    coded budgets fitted as in the monolithic encode).
    """
    from ._warp import device_name, resolve_device, warp
    from .analysis import DeviceVolume
    from .bricked import brick_cap, brick_tasks, default_halo, parse_bricks, plan_bricks, run_bricks, split_bricks
    from .wgs import header_size

    counts_xyz = parse_bricks(bricks)
    if opts.resume or opts.time_budget is not None or opts.refine.target_psnr is not None or opts.refine.plateau_db is not None:
        raise WarpgaussError("--bricks does not combine with --resume, --time-budget, --target-psnr or --plateau yet")
    enc = encoding_of(opts)
    budget_bytes = target_bytes(f, opts)
    header = _header_for(f, opts)
    n = resolve_budget(f, opts, header_size(header, 1 << 40, encoding=enc))
    plan_bricks(f.shape_xyz, counts_xyz, 0 if halo is None else halo)  # a bad bricking is refused before the device starts
    wp = warp()
    dev = resolve_device(device)
    timer = timer or StageRecorder()
    timer.device = dev
    sizing = None
    dv = None
    if enc == "coded" and budget_bytes is not None:
        from .lazy import is_lazy

        if is_lazy(f.values):
            raise WarpgaussError(
                "a volume read brick by brick takes its budget as --budget N (the coded size pilot of --bytes/--ratio needs the whole volume on the device)"
            )
        with timer.stage("S1p", "coded size pilot"):
            dv = DeviceVolume(f, dev)
            n, sizing = coded_budget(dv, f, opts, header, budget_bytes, n)
    allocation = dataclasses.replace(opts.allocation, scale_cap=brick_cap(opts.allocation.resolved_cap(f.shape_xyz), f.shape_xyz, n))
    halo = default_halo(allocation.scale_cap) if halo is None else int(halo)
    plan = plan_bricks(f.shape_xyz, counts_xyz, halo)
    with timer.stage("Sb", "budget split over the bricks"):
        counts, stats = split_bricks(f, plan, n)
    tasks = brick_tasks(f, plan, stats, opts.seed, allocation, opts.refine, None if client is not None else dev, n)
    t0 = time.perf_counter()
    with timer.stage("S1-S2b", f"{len(plan)} bricks: allocation and refinement"):
        results = run_bricks(tasks, client, on_progress, limit=max_device_memory)
    wall = time.perf_counter() - t0
    params = np.concatenate([r["params"] for r in results]) if results else np.zeros((0, 12), np.float32)
    merged = Model(params, header)
    merged.coded_bits = None if sizing is None else sizing["bits"]
    fit = None
    if enc == "coded" and budget_bytes is not None:
        model, fit = merged.fit_bytes(budget_bytes)
    else:
        model = merged.stored(enc)
        model.format = enc
    evaluation: dict = {}
    if evaluate:
        from .evaluate import evaluate_field

        with timer.stage("EV", "evaluation"):
            evaluation["final"] = evaluate_field(model.field(dev), f, full=full_eval)
    size, payload = model.file_sizes(encoding=enc)
    bricks_report = [
        {
            "index": list(b.index),
            "interior_zyx": [list(x) for x in b.interior],
            "box_zyx": [list(x) for x in b.box],
            **st,
            "seconds": r["seconds"],
            "device": r["device"],
            "iterations": r["iterations"],
            "samples": r["samples"],
            "stand_ins": r["stand_ins"],
            "frozen": r["frozen"],
            "at_once": r.get("at_once", 1),
            "setup_seconds": r.get("setup_seconds"),
            "refine_seconds": r.get("refine_seconds"),
        }
        for b, st, r in zip(plan, stats, results)
    ]
    model.report = {
        "warpgauss_version": __version__,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "device": dev,
        "device_name": device_name(dev),
        "warp_version": wp.config.version,
        "host": platform.node(),
        "input": input_info or {"name": f.name, "shape_xyz": list(f.shape_xyz)},
        "budget": {
            "n": model.n,
            "requested_budget": opts.budget,
            "requested_ratio": opts.ratio if opts.budget is None and opts.bytes is None else None,
            "requested_bytes": budget_bytes,
            "budget_used": None if budget_bytes is None else size / budget_bytes,
            "coded_sizing": sizing,
            "coded_fit": fit,
            "n_max": seed_limit(f.eligible, f.occupied),
            "format": enc,
            "bytes": size,
            "bytes_per_primitive": payload / max(model.n, 1),
            "compression_ratio": model.source_bytes / size,
        },
        "bricking": {
            "bricks_xyz": list(counts_xyz),
            "halo": halo,
            "scale_cap": allocation.scale_cap,
            "scheduler": "this process" if client is None else str(client.scheduler.address),
            "wall_seconds": wall,
            "bricks": bricks_report,
            "rule": "detail share by interior sum of |grad V|, coverage share by occupied voxels, largest remainders, seed limits",
        },
        "seed": opts.seed,
        "refinement": {"iterations": opts.refine.iterations, "per_brick": True},
        "evaluation": evaluation,
        "psnr_db": evaluation.get("final", {}).get("psnr_db"),
        "interrupted": False,
        "skipped": [],
    }
    return model


AUTO_BRICK_FLOOR = 2 * 2**30  # an encode estimated below this is never bricked by the default limit
LAZY_SUFFIXES = (".raw", ".bin", ".npy", ".h5", ".hdf5", ".hdf", ".nc", ".cdf", ".zarr")


def _bricking(source, read, example, bricks, halo, budget, device, max_device_memory, max_host_memory=None):
    """(bricks, read lazily, device limit, bricks chosen here) of an encode: given bricks are kept;
    otherwise a file whose monolithic encode would not fit the device or host limit (or the
    kernels' voxel index) is bricked by :func:`~warpgauss.bricked.choose_bricks`. Only a format
    that can be read on demand is looked at before it is read."""
    from ._warp import resolve_device
    from .bricked import HOST_SHARE, brick_cap, brick_device_bytes, choose_bricks, default_device_limit, default_halo, parse_memory

    limit = None if max_device_memory is None else parse_memory(max_device_memory, "--max-device-memory")
    host = None if max_host_memory is None else parse_memory(max_host_memory, "--max-host-memory", 2**20)
    is_file = example is None and isinstance(source, (str, os.PathLike)) and str(source).lower().endswith(LAZY_SUFFIXES)
    if bricks is not None or not is_file:
        return bricks, bricks is not None and is_file, limit, False
    vol = (read or ReadOptions()).read(source, lazy=True)  # the header: nothing is read yet
    shape_xyz = tuple(int(v) for v in vol.data.shape[::-1])
    voxels = int(np.prod(shape_xyz, dtype=np.int64))
    if host is None:
        free = _available_memory()
        host = None if free is None else int(HOST_SHARE * free)
    if limit is None and brick_device_bytes(voxels, int(budget or 0)) > AUTO_BRICK_FLOOR:
        limit = default_device_limit(resolve_device(device))  # None on the CPU
    if halo is None:  # as the bricked encode will choose it (without a budget: for 1 Gaussian per 300 voxels)
        n_guess = int(budget) if budget else max(1, voxels // 300)
        halo = default_halo(brick_cap(max(2.0, max(shape_xyz) / 16.0), shape_xyz, n_guess))
    counts = choose_bricks(shape_xyz, int(budget or 0), limit, int(halo), host)
    if counts == (1, 1, 1):
        return None, False, limit, False
    return counts, True, limit, True


def _array_device(arr, device: str | None) -> str:
    """The device that encodes a device array: its own (``device`` must name it, if given)."""
    from ._warp import resolve_device

    own = str(arr.device)
    if device not in (None, "", "auto") and resolve_device(device) != own:
        raise WarpgaussError(
            f"the array lives on {own}, the encode was asked to run on {device}; pass device={own!r} (or a copy of the array there)"
        )
    return own


def _warm_params(warm_start) -> np.ndarray | None:
    """The (N, 12) float32 parameters of a warm start (a Model or an array), or None."""
    if warm_start is None:
        return None
    p = np.asarray(warm_start.params if isinstance(warm_start, Model) else warm_start, np.float32)
    if p.ndim != 2 or p.shape[1] != 12 or not np.isfinite(p).all():
        raise WarpgaussError(f"a warm start is a model or finite (N, 12) parameters, got an array of shape {p.shape}")
    return p


def finish_report(model: Model, timer: StageRecorder) -> dict:
    """Put the stage table and totals into the model's report."""
    rep = model.report
    rep["stages"] = timer.to_list()
    rep["total_seconds"] = round(sum(s.seconds for s in timer.stages), 6)
    host = [s.host_peak_bytes for s in timer.stages]
    dev = [s.device_peak_bytes for s in timer.stages if s.device_peak_bytes is not None]
    rep["peak_host_bytes"] = max(host) if host else None
    rep["peak_device_bytes"] = max(dev) if dev else None
    return rep


def encode(
    source: str | os.PathLike | np.ndarray | None = None,
    *,
    budget: int | None = None,
    ratio: float | None = None,
    file_bytes: int | None = None,
    seed: int = 0,
    device: str | None = None,
    iterations: int | None = None,
    samples: int | None = None,
    preset: str | None = None,
    refine: RefineConfig | None = None,
    self_test: bool = True,
    time_budget: float | None = None,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: float = 60.0,
    resume: bool = False,
    target_psnr: float | None = None,
    plateau_db: float | None = None,
    compact: bool = False,
    format: str | None = None,
    example: str | None = None,
    example_size: int | tuple[int, int, int] = 64,
    read: ReadOptions | None = None,
    allocation: AllocationConfig | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    output: str | os.PathLike | None = None,
    force: bool = False,
    analytic_output: str | os.PathLike | None = None,
    on_stage: Callable[[str, str], None] | None = None,
    on_stats: Callable[[dict], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
    bricks=None,
    halo: int | None = None,
    client=None,
    on_bricks: Callable[[int, int], None] | None = None,
    max_device_memory: int | str | None = None,
    max_host_memory: int | str | None = None,
    warm_start=None,
    motion: bool = True,
    session=None,
) -> Model:
    """Encode a volume into a fixed budget of Gaussians.

    Args:
        source: File path, 3D numpy array (nz, ny, nx), or a device array: a Warp array or any
            DLPack / ``__cuda_array_interface__`` producer (CuPy, PyTorch, JAX), any real dtype
            and strides, normalised and encoded on its device with no host copy of its voxels
            (``device`` None: the array's own); None with ``example``.
        budget: Number of primitives N (exact); or give ``ratio``.
        ratio: Target compression ratio: the file holds at most floor(S_src / R) bytes; N =
            floor((S_src / R - H) / 48) (12 with ``compact``; measured for ``format="coded"``).
        file_bytes: The file size budget in bytes instead (header included). A coded file is
            never larger and uses at least 95 % of it where bit depths allow (see
            :func:`warpgauss.coded.fit_bytes`; the report's ``budget`` says what was done).
        seed: Encoding seed; same seed and device give the same model.
        device: Warp device; None picks CUDA when present, else CPU.
        iterations: Refinement iterations (default 1,500, the paper's; 0: analytic model only).
        samples: Samples per iteration (default 3,072, the paper's, times ceil(N / 350,000) for
            large budgets, 12,288 at 1.4M; on a GPU at least one per 128 voxels as a power of two
            within 16,384-131,072; see :meth:`RefineConfig.samples_rule`; the report's
            ``refinement.samples_rule`` says what was chosen).
        preset: "paper" (1,500 x 3,072 whatever N), "fast" (300 x 3,072, the paper's time-budget
            mode) or "quality" (1,500 x 12,288); explicit ``iterations``/``samples`` override it.
        refine: Learning rates, loss weights and schedule (:class:`warpgauss.optimize.RefineConfig`).
        self_test: Run the binned-vs-dense self-test before refining.
        time_budget: Seconds refinement may take once its kernels are compiled (set-up, self-test and
            iterations); spare time goes to more samples per iteration (unless ``samples`` is
            given) once 1,500 iterations fit, then to iterations (up to 20,000); refinement ends
            within it, with a valid model at any stop.
        checkpoint: Where refinement writes checkpoints (atomically, every ``checkpoint_every``
            seconds and on Ctrl-C); None: ``OUTPUT.ckpt`` when ``output`` is given, else none.
            Deleted once the model is written.
        checkpoint_every: Seconds between checkpoints.
        resume: Continue from the checkpoint (same input and options; the result is the model an
            uninterrupted run gives, bit-identical on the same CPU). Overwrites ``output``.
        target_psnr: Skip refinement if the analytic model reaches this PSNR (dB), else stop it
            once a 65,536-voxel validation PSNR, checked every 100 iterations, does.
        plateau_db: Stop refinement once that validation PSNR gained less than this (dB) over
            the last 300 iterations.
        compact: Size the budget (and the report) for the compact 12-byte format.
        format: The file format: "coded" (the default: quantised and entropy-coded, about
            7.5-8.2 B/primitive on real volumes; the returned model is the stored one), "float32"
            (alias "full", 48 B) or "compact96" (alias "compact", 12 B). Overrides ``compact``.
        example: Built-in example volume name instead of ``source``.
        example_size: Size of the example volume.
        read: Reader options (shape, dtype, endian, dataset, variable, stride, fill value).
        allocation: Allocation knobs.
        evaluate: Run stage EV (PSNR).
        full_eval: EV on the full grid instead of 500,000 sampled voxels.
        output: If given, write the model there (stage S3; atomic).
        force: Overwrite ``output`` if it exists.
        on_stage: Optional callback(name, title) as each stage starts (progress display).
        on_stats: Optional callback(stats) once the structure statistics exist (before allocation).
        on_progress: Optional callback(iteration, total, losses) during refinement.
        analytic_output: Also write the analytic (pre-refinement) model there.

        bricks: Split the grid into bricks (``"2x2x2"``, counts x, y, z) with a halo, the budget
            over them before refinement, and encode each on its own (see :mod:`warpgauss.bricked`).
        halo: Voxels of halo around each brick (default :func:`warpgauss.bricked.default_halo`: 4, 16 at 512^3).
        client: A ``distributed.Client``: the bricks run on its cluster (None: in this process).
        on_bricks: Optional callback(bricks done, bricks) during a bricked encode.
        max_device_memory: Bytes (or ``"24GiB"``) one encode may use on the device; default: 90 %
            of what a CUDA device has free (none on the CPU). Without ``bricks``, a volume whose
            monolithic encode would not fit it, or that has more voxels than the kernels index, is
            bricked (:func:`warpgauss.bricked.choose_bricks`), and a file read on demand.
        max_host_memory: The same for this machine's memory (default: half of what is available
            now); a bricked encode of a file keeps one brick's box in memory at a time.
        warm_start: A :class:`Model` (or its ``(N, 12)`` parameters) of the previous timestep of
            the same grid and budget: refinement starts from it instead of the analytic
            allocation (stage S1b-S1e is skipped; the report's ``evaluation.analytic`` is the
            starting model on this timestep).
        motion: With ``warm_start``, first move every primitive with the motion from the
            previous model to this timestep (block Lucas-Kanade on a pyramid, see
            :mod:`warpgauss.motion`; stage S1m); False: start where the previous model was.
        session: The state a :class:`warpgauss.Encoder` keeps between its calls (device buffers
            and this call's deadline); not for direct use.

    Returns:
        The :class:`Model`, with ``model.report`` holding the run report.
    """
    from ._fs import check_writable

    if output is not None:
        check_writable(output, force=force or resume)  # a resume replaces its interrupted model
    if analytic_output is not None:
        check_writable(analytic_output, force=force or resume)
    if checkpoint is None and output is not None:
        checkpoint = Path(str(output) + ".ckpt")
    if resume and (checkpoint is None or not Path(checkpoint).is_file()):
        raise WarpgaussError(f"--resume: no checkpoint at {checkpoint}; encode without --resume")
    if not checkpoint_every >= 0:
        raise WarpgaussError(f"--checkpoint-every must be >= 0 seconds, got {checkpoint_every}")
    refine = resolve_refine(refine, preset, iterations, samples)
    for name, value in (("--target-psnr", target_psnr), ("--plateau", plateau_db)):
        if value is not None and not value > 0:
            raise WarpgaussError(f"{name} must be a positive number of dB, got {value}")
    refine = dataclasses.replace(refine, target_psnr=target_psnr, plateau_db=plateau_db)
    if time_budget is not None and not time_budget > 0:
        raise WarpgaussError(f"--time-budget must be a positive number of seconds, got {time_budget}")
    opts = EncodeOptions(
        budget,
        ratio,
        seed,
        compact,
        allocation or AllocationConfig(),
        stride=(read or ReadOptions()).stride,
        refine=refine,
        self_test=self_test,
        time_budget=time_budget,
        checkpoint=checkpoint,
        checkpoint_every=checkpoint_every,
        resume=resume,
        format=format,
        bytes=file_bytes,
        init=_warm_params(warm_start),
        motion=motion,
    )
    if opts.init is not None and (bricks is not None or resume):
        raise WarpgaussError("a warm start does not combine with --bricks or --resume")
    if session is not None:
        opts.deadline = session.deadline
        opts.evaluate_start = session.deadline is None  # a call on a time budget scores only its result
        opts.cold_start_psnr = session.cold_start_psnr
    if is_device_array(source):
        if bricks is not None:
            raise WarpgaussError("a device array is encoded whole; --bricks takes a file")
        source = device_array(source, None if device in (None, "", "auto") else device)
        device = _array_device(source, device)
    encoding_of(opts)  # an unknown format is refused before any work
    timer = StageRecorder(on_stage=on_stage)
    bricks, lazy, limit, auto = _bricking(source, read, example, bricks, halo, budget, device, max_device_memory, max_host_memory)
    with timer.stage("P", "load and normalise"):
        buffers = None if session is None else session.buffers
        f, info = load_field(source, read, example=example, example_size=example_size, lazy=lazy, buffers=buffers)
    if isinstance(warm_start, Model) and tuple(warm_start.shape_xyz) != tuple(f.shape_xyz):
        raise WarpgaussError(
            f"the warm-start model is on a {'x'.join(map(str, warm_start.shape_xyz))} grid, this volume {'x'.join(map(str, f.shape_xyz))}; encode cold"
        )
    if bricks is not None:
        if analytic_output is not None:
            raise WarpgaussError("--bricks does not write an analytic model (--save-analytic)")
        model = encode_bricked(
            f,
            opts,
            bricks,
            halo=halo,
            device=device,
            client=client,
            timer=timer,
            input_info=info,
            evaluate=evaluate,
            full_eval=full_eval,
            on_progress=on_bricks,
            max_device_memory=limit,
        )
        model.report["bricking"].update(
            chosen="by the device and host limits" if auto else "given",
            max_device_memory=limit,
            read_lazily=bool(info.get("read_lazily")),
        )
    else:
        model = encode_field(
            f,
            opts,
            device=device,
            timer=timer,
            input_info=info,
            evaluate=evaluate,
            full_eval=full_eval,
            on_stats=on_stats,
            on_progress=on_progress,
            analytic_output=analytic_output,
            force=force or resume,
        )
    if output is not None:
        with timer.stage("S3", "export"):
            model.save(output, encoding=encoding_of(opts), force=True if resume else force)
        model.report["output"] = str(Path(output))
    if checkpoint is not None and not model.report.get("interrupted") and Path(checkpoint).is_file():
        Path(checkpoint).unlink()  # the run finished: its model replaces the checkpoint
    finish_report(model, timer)
    return model


def encode_ladder(
    source: str | os.PathLike | np.ndarray | None = None,
    *,
    budgets: Sequence[int],
    output_pattern: str | None = None,
    force: bool = False,
    seed: int = 0,
    device: str | None = None,
    iterations: int | None = None,
    samples: int | None = None,
    preset: str | None = None,
    refine: RefineConfig | None = None,
    self_test: bool = True,
    compact: bool = False,
    format: str | None = None,
    example: str | None = None,
    example_size: int | tuple[int, int, int] = 64,
    read: ReadOptions | None = None,
    allocation: AllocationConfig | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    on_stage: Callable[[str, str], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
) -> list[Model]:
    """Encode one volume at several budgets, reading and analysing it once (the paper's ladders).

    Args:
        budgets: Primitive counts; all are checked against the seed limit before any encoding.
        evaluate: Run stage EV for each model (benchmarks that measure PSNR their own way skip it).
        output_pattern: If given, each model is written to ``output_pattern.format(n=N)``.

    The other arguments are those of :func:`encode`.

    Returns:
        One model per budget (ascending), each with its report; ``report["ladder"]`` says what
        was shared.
    """
    from ._fs import check_writable

    ladder = sorted({int(b) for b in budgets})
    if not ladder or ladder[0] < 1:
        raise WarpgaussError(f"--ladder needs positive budgets, got {list(budgets)}")
    paths: list[Path | None] = [None] * len(ladder)
    if output_pattern is not None:
        paths = [Path(output_pattern.format(n=n)) for n in ladder]
        for p in paths:
            check_writable(p, force=force)
    refine = resolve_refine(refine, preset, iterations, samples)
    first = StageRecorder(on_stage=on_stage)
    with first.stage("P", "load and normalise"):
        f, info = load_field(source, read, example=example, example_size=example_size)
    load_seconds = first.seconds("P")
    from .wgs import header_size

    probe = EncodeOptions(budget=ladder[-1], seed=seed, compact=compact, refine=refine, format=format)
    enc = encoding_of(probe)
    check_budget(f, ladder[-1], header_size(_header_for(f, probe), 1 << 40, encoding=enc), sizing_bpp(enc))
    cache: dict = {}
    models = []
    for i, (n, path) in enumerate(zip(ladder, paths)):
        timer = first if i == 0 else StageRecorder(on_stage=on_stage)
        opts = EncodeOptions(
            n,
            None,
            seed,
            compact,
            allocation or AllocationConfig(),
            stride=(read or ReadOptions()).stride,
            refine=refine,
            self_test=self_test and i == 0,
            format=format,
        )
        model = encode_field(
            f,
            opts,
            device=device,
            timer=timer,
            input_info=info,
            evaluate=evaluate,
            full_eval=full_eval,
            on_progress=on_progress,
            cache=cache,
        )
        if i > 0:
            model.report["skipped"].insert(0, {"what": "P", "why": "volume loaded once for the ladder", "seconds_saved": load_seconds})
            if self_test:
                model.report["skipped"].append({"what": "self-test", "why": "run once for the ladder, with the first budget"})
        if path is not None:
            with timer.stage("S3", "export"):
                model.save(path, encoding=enc, force=force)
            model.report["output"] = str(path)
        finish_report(model, timer)
        model.report["ladder"] = {"budgets": ladder, "position": i, "shared": ["P", "S1a"] if i else []}
        models.append(model)
    return models
