"""The encode entry point, :func:`warpgauss.encode`: stage P, then the whole or bricked driver, then
S3 (export) and the report.

    model = warpgauss.encode("scan.nii.gz", ratio=100)          # or an array, or example="vortex"
    model.save("scan.wgs"); model.report["evaluation"]["final"]["psnr_db"]

Everything up to the budget check runs without Warp, so an impossible request is refused at once.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..allocate import AllocationConfig
from ..devicefield import device_array, is_device_array
from ..errors import WarpgaussError
from ..io import ReadOptions
from ..model import Model
from ..optimize import RefineConfig
from ..profiling import StageRecorder
from ..residual import Bound
from .bricked import bricking, encode_bricked, host_limit
from .config import EncodeConfig, config_of
from .load import load_field
from .options import encoding_of
from .run import encode_field


def _array_device(arr, device: str | None) -> str:
    """The device that encodes a device array: its own (``device`` must name it, if given)."""
    from .._warp import resolve_device

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
    rep = model.run_report
    rep["stages"] = timer.to_list()
    rep["total_seconds"] = round(sum(s.seconds for s in timer.stages), 6)
    host = [s.host_peak_bytes for s in timer.stages]
    dev = [s.device_peak_bytes for s in timer.stages if s.device_peak_bytes is not None]
    rep["peak_host_bytes"] = max(host) if host else None
    rep["peak_device_bytes"] = max(dev) if dev else None
    return rep


def check_bounded_request(source, read: ReadOptions | None, bricks, warm_start, session) -> None:
    """Refuse, before any work, what a bounded residual cannot go with."""
    if read is not None and read.stride > 1:
        raise WarpgaussError("--max-error bounds every source voxel; --stride drops voxels, so the two do not combine")
    if bricks is not None:
        raise WarpgaussError("--max-error does not combine with --bricks yet; encode the volume whole")
    if is_device_array(source):
        raise WarpgaussError("--max-error takes a file or a numpy array, not a device array")
    if warm_start is not None or session is not None:
        raise WarpgaussError("--max-error does not combine with a series or an Encoder yet; encode each volume on its own")


def attach_residual(model: Model, source, read, example, example_size, bound: Bound, device) -> None:
    """Stage S4: code the bounded residual of the (stored) model against the source's own values
    and attach it to the model; the report's ``residual`` says what it holds."""
    import time

    from ..lazy import valid_mask
    from ..residual import code_for_psnr, code_residual, prediction, residual_device, verify

    t0 = time.perf_counter()
    data, fill = raw_source(source, read, example, example_size)
    if tuple(reversed(data.shape)) != model.shape_xyz:
        raise WarpgaussError(f"internal: the source's shape {data.shape} is not the model grid {model.shape_xyz}")
    lo, hi = model.value_range
    valid = valid_mask(data, fill)
    masked = None if valid.all() else valid
    pred, fragile = prediction(model, device)
    passes = residual_device(device, data.size)
    t1 = time.perf_counter()
    if bound.psnr is not None:
        res, facts, check = code_for_psnr(data, masked, pred, fragile, bound.psnr, (lo, hi), fill_value=fill, device=passes)
    else:
        res, facts = code_residual(data, masked, pred, fragile, bound.absolute(lo, hi), (lo, hi), fill_value=fill, device=passes)
        check = verify(res, pred, data, valid, (lo, hi))
    t2 = time.perf_counter()
    model.residual = res
    gauss = model.file_size(encoding=model.format or "coded") - res.nbytes
    model.run_report["residual"] = {
        **facts,
        "bound": res.info["bound"],
        "bound_rel": res.info["bound_rel"],
        "gaussian_bytes": gauss,
        "residual_bytes": res.nbytes,
        "file_bytes": gauss + res.nbytes,
        "compression_ratio": model.source_bytes / (gauss + res.nbytes),
        **check,
        "predict_seconds": t1 - t0,
        "code_seconds": t2 - t1,
    }


def raw_source(source, read: ReadOptions | None, example, example_size) -> tuple[np.ndarray, float | None]:
    """The source's own values (its dtype, in memory) and fill value, for a bounded residual."""
    from ..readers.timesteps import TimeStep

    read = read or ReadOptions()
    fill = read.fill_value
    if example is not None:
        from ..synthetic import generate

        return generate(example, example_size, seed=0), fill
    if isinstance(source, np.ndarray):
        return source, fill
    if isinstance(source, TimeStep):
        return source.read(), fill if fill is not None else source.meta()[2]
    vol = read.read(source, lazy=False)
    if fill is None and getattr(vol, "fill_value", None) is not None:
        fill = vol.fill_value
    return np.asarray(vol.data), fill


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
    max_error: float | None = None,
    max_error_rel: float | None = None,
    residual_psnr: float | None = None,
    session=None,
    progress: bool | None = None,
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
            :func:`warpgauss.ratefit.fit_bytes`; the report's ``budget`` says what was done).
        seed: Encoding seed; same seed and device give the same model.
        device: Warp device; None picks CUDA when present, else CPU.
        iterations: Refinement iterations (default 1,500, the paper's; 0: analytic model only).
        samples: Samples per iteration (default 3,072, the paper's, times ceil(N / 350,000) for
            large budgets, 12,288 at 1.4M; on a GPU at least one per 128 voxels as a power of two
            within 16,384-131,072; see :meth:`RefineConfig.samples_rule`; the report's
            ``refinement.samples_rule`` says what was chosen).
        preset: "paper" (1,500 x 3,072 whatever N), "fast" (the default's sampling for 300
            iterations; the paper's time-budget mode is "paper" with ``iterations=300``) or
            "quality" (1,500 x 12,288); explicit ``iterations``/``samples`` override it.
        refine: Learning rates, loss weights and schedule (:class:`warpgauss.optimize.RefineConfig`).
        self_test: Run the binned-vs-dense self-test before refining.
        time_budget: Seconds the whole call may take, reading to writing (the kernels' first
            compile not counted): refinement gets what the stages before it leave, less a reserve
            for fitting the byte budget (then the first fit is kept, not a scored choice),
            evaluating and writing; spare time goes to more samples per iteration (unless
            ``samples`` is given) once 1,500 iterations fit, then to iterations (up to 20,000);
            refinement ends within its share, with a valid model at any stop.
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
            7-14 B/primitive on refined models; the returned model is the stored one), "float32"
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
        halo: Voxels of halo around each brick (default :func:`warpgauss.brickplan.default_halo`: 4, 16 at 512^3).
        client: A ``distributed.Client``: the bricks run on its cluster (None: in this process).
        on_bricks: Optional callback(bricks done, bricks) during a bricked encode.
        max_device_memory: Bytes (or ``"24GiB"``) one encode may use on the device; default: 90 %
            of what a CUDA device has free (none on the CPU). Without ``bricks``, a volume whose
            monolithic encode would not fit it, or that has more voxels than the kernels index, is
            bricked (:func:`warpgauss.brickplan.choose_bricks`), and a file read on demand.
        max_host_memory: The same for this machine's memory (default: half of what is available
            now); a bricked encode of a file keeps one brick's box in memory at a time.
        warm_start: A :class:`Model` (or its ``(N, 12)`` parameters) of the previous timestep of
            the same grid and budget: refinement starts from it instead of the analytic
            allocation (stage S1b-S1e is skipped; the report's ``evaluation.analytic`` is the
            starting model on this timestep).
        motion: With ``warm_start``, first move every primitive with the motion from the
            previous model to this timestep (block Lucas-Kanade on a pyramid, see
            :mod:`warpgauss.motion`; stage S1m); False: start where the previous model was.
        max_error: A point-wise bound in source units: a residual stored after the Gaussians
            makes every valid voxel of ``decode()`` lie within it of the source, on any device
            (:mod:`warpgauss.residual`; stage S4). The Gaussians keep the budget given, by
            default the source's bytes / :data:`warpgauss.residual.DEFAULT_RATIO` (at least
            :data:`warpgauss.residual.MIN_GAUSSIAN_BYTES`); render and view use them alone.
        max_error_rel: The bound as a share of the source's value range instead.
        residual_psnr: Instead of a bound, the full-grid PSNR (dB) the decode must reach: the
            largest bound that reaches it (:func:`warpgauss.residual.code_for_psnr`).
        session: The state a :class:`warpgauss.Encoder` keeps between its calls (device buffers
            and this call's deadline); not for direct use.
        progress: Print refinement's progress on one line of standard error (iteration, the
            samples' PSNR), as the command line does; None (the default): where a person watches,
            a terminal or a notebook, not in logs. ``on_progress`` replaces it.

    Returns:
        The :class:`Model`, with ``model.report`` holding the run report.
    """
    line = None
    if on_progress is None and (progress if progress is not None else watched()):
        on_progress = line = ProgressLine()
    try:
        return encode_with(
            source,
            config_of(locals()),
            on_stage=on_stage,
            on_stats=on_stats,
            on_progress=on_progress,
            on_bricks=on_bricks,
            client=client,
            session=session,
        )
    finally:
        if line is not None:
            line.close()


def encode_with(
    source,
    cfg: EncodeConfig,
    *,
    on_stage: Callable[[str, str], None] | None = None,
    on_stats: Callable[[dict], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
    on_bricks: Callable[[int, int], None] | None = None,
    client=None,
    session=None,
) -> Model:
    """:func:`encode` of ``source`` with the settings of ``cfg`` (see :mod:`.config`), the
    callbacks, Dask client and Encoder session beside them."""
    import time

    from .._fs import check_writable

    called = time.perf_counter()  # a time budget is the whole call's
    cfg.budget.check()  # before the output check: say what is wrong with the request first
    run, reading, bricking_ = cfg.run, cfg.reading, cfg.bricking
    read, bricks, device = reading.read, bricking_.bricks, cfg.device
    bound = cfg.bound
    bounded = bound.given
    if bounded:
        bound.check()
        check_bounded_request(source, read, bricks, cfg.start.warm_start, session)
    default_share = bounded and not cfg.budget.given  # sized once the source's bytes are known
    force, resume, output = run.force, run.resume, run.output
    if output is not None:
        check_writable(output, force=force or resume)  # a resume replaces its interrupted model
    if run.analytic_output is not None:
        check_writable(run.analytic_output, force=force or resume)
    checkpoint = run.checkpoint
    if checkpoint is None and output is not None:
        checkpoint = Path(str(output) + ".ckpt")
    if resume and (checkpoint is None or not Path(checkpoint).is_file()):
        raise WarpgaussError(f"--resume: no checkpoint at {checkpoint}; encode without --resume")
    if not run.checkpoint_every >= 0:
        raise WarpgaussError(f"--checkpoint-every must be >= 0 seconds, got {run.checkpoint_every}")
    opts = cfg.options(cfg.refinement.resolved(), checkpoint=checkpoint, init=_warm_params(cfg.start.warm_start))
    if opts.init is not None and (bricks is not None or resume):
        raise WarpgaussError("a warm start does not combine with --bricks or --resume")
    opts.budget_start = called
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
    example, example_size = reading.example, reading.example_size
    workers = 1 if client is None else max(1, len(client.scheduler_info().get("workers", {})))
    bricks, lazy, limit, auto = bricking(
        source, read, example, bricks, bricking_.halo, cfg.budget.n, device, bricking_.max_device_memory, bricking_.max_host_memory, workers
    )
    with timer.stage("P", "load and normalise"):
        buffers = None if session is None else session.buffers
        # a file read on demand is counted by the bricks' statistics (stage Sb), not by a pass of its own
        f, info = load_field(source, read, example=example, example_size=example_size, lazy=lazy, buffers=buffers, count=not lazy)
    if bounded:
        from ..residual import CODE_BYTES_PER_VOXEL, check_memory

        check_memory(f.n_voxels, CODE_BYTES_PER_VOXEL, "coding a bounded residual of")
    if default_share:
        from ..residual import DEFAULT_RATIO as RESIDUAL_RATIO
        from ..residual import MIN_GAUSSIAN_BYTES

        opts.bytes = max(int(f.source_bytes / RESIDUAL_RATIO), MIN_GAUSSIAN_BYTES)
    warm_start = cfg.start.warm_start
    if isinstance(warm_start, Model) and tuple(warm_start.shape_xyz) != tuple(f.shape_xyz):
        raise WarpgaussError(
            f"the warm-start model is on a {'x'.join(map(str, warm_start.shape_xyz))} grid, this volume {'x'.join(map(str, f.shape_xyz))}; encode cold"
        )
    if bricks is not None:
        if run.analytic_output is not None:
            raise WarpgaussError("--bricks does not write an analytic model (--save-analytic)")
        model = encode_bricked(
            f,
            opts,
            bricks,
            halo=bricking_.halo,
            device=device,
            client=client,
            timer=timer,
            input_info=info,
            evaluate=run.evaluate,
            full_eval=run.full_eval,
            on_progress=on_bricks,
            max_device_memory=limit,
            max_host_memory=host_limit(bricking_.max_host_memory),
        )
        model.run_report["bricking"].update(
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
            evaluate=run.evaluate,
            full_eval=run.full_eval,
            on_stats=on_stats,
            on_progress=on_progress,
            analytic_output=run.analytic_output,
            force=force or resume,
        )
    if bounded:
        with timer.stage("S4", "bounded residual"):
            attach_residual(model, source, read, example, example_size, bound, device)
    if output is not None:
        with timer.stage("S3", "export"):
            model.save(output, encoding=encoding_of(opts), force=True if resume else force)
        model.run_report["output"] = str(Path(output))
    if checkpoint is not None and not model.run_report.get("interrupted") and Path(checkpoint).is_file():
        Path(checkpoint).unlink()  # the run finished: its model replaces the checkpoint
    finish_report(model, timer)
    return model


def watched() -> bool:
    """Whether a person is likely watching this process: standard error a terminal, or a notebook."""
    import sys

    try:
        tty = sys.stderr.isatty()
    except (AttributeError, ValueError):
        tty = False
    return bool(tty or "ipykernel" in sys.modules)


class ProgressLine:
    """Refinement's progress on one line of standard error, rewritten in place (``\\r``) and ended
    with a newline when the encode ends: what :func:`encode` shows a Python user."""

    def __init__(self, stream=None):
        import sys

        self.stream = stream if stream is not None else sys.stderr
        self.open = False  # a line written and not yet ended

    def __call__(self, iteration: int, total: int, losses: dict) -> None:
        psnr = losses.get("sample_psnr_db")
        tail = f", samples' PSNR {psnr:.2f} dB" if isinstance(psnr, (int, float)) else ""
        self.stream.write(f"\rwarpgauss: refining, iteration {iteration:,} of {total:,}{tail}")
        self.stream.flush()
        self.open = True

    def close(self) -> None:
        """End the line (a run that stopped early never reached its last iteration)."""
        if self.open:
            self.stream.write("\n")
            self.stream.flush()
            self.open = False
