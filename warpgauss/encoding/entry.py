"""The encode entry point, :func:`warpgauss.encode`: stage P, then the whole or bricked driver, then
S3 (export) and the report.

    model = warpgauss.encode("scan.nii.gz", ratio=100)          # or an array, or example="vortex"
    model.save("scan.wgs"); model.report["evaluation"]["final"]["psnr_db"]

Everything up to the budget check runs without Warp, so an impossible request is refused at once.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..core.limits import host_limit
from ..core.profiling import StageRecorder
from ..errors import WarpgaussError
from ..field.device import device_array, is_device_array
from ..format.model import Model
from ..readers import ReadOptions
from .allocate import AllocationConfig
from .driver.bounded import attach_residual, check_bounded_request
from .driver.config import EncodeConfig, config_of
from .driver.load import header_shape, load_field, read_on_demand
from .driver.options import EncodeOptions, encoding_of
from .driver.report import finish_report
from .driver.run import encode_field
from .refine import RefineConfig


def _array_device(arr, device: str | None) -> str:
    """The device that encodes a device array: its own (``device`` must name it, if given)."""
    from ..core.warp import resolve_device

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


def encode(
    source: str | os.PathLike | np.ndarray | None = None,
    *,
    budget: int | None = None,
    ratio: float | None = None,
    file_bytes: int | None = None,
    seed: int = 0,
    device: str | None = None,
    devices: str | list[str] | None = None,
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
    read_by_bricks: bool | None = None,
    volume_on_host: bool | None = None,
    warm_start=None,
    motion: bool = True,
    max_error: float | None = None,
    max_error_rel: float | None = None,
    residual_psnr: float | None = None,
    session=None,
    progress: bool | None = None,
) -> Model:
    """Encode a volume into a fixed budget of Gaussians.

    One line a keyword here; [Encode options](guide/options.md) (``docs/guide/options.md``) says
    everything of each, grouped as :class:`~warpgauss.encoding.driver.config.EncodeConfig` holds them.

    Args:
        source: File path, 3D numpy array (nz, ny, nx) or device array (encoded on its device); None with ``example``.
        budget: Number of primitives N (exact); or give ``ratio`` or ``file_bytes`` (none: ratio 20).
        ratio: Target compression ratio: the file holds at most floor(S_src / R) bytes.
        file_bytes: The file size budget in bytes instead (header included; never exceeded).
        seed: Encoding seed; same seed and device give the same model.
        device: Warp device; None picks CUDA when present, else CPU.
        devices: Several GPUs of this machine refining one model ("cuda:0,cuda:1"; the first is ``device``).
        iterations: Refinement iterations (default 1,500, the paper's; 0: analytic model only).
        samples: Samples per iteration (default 3,072, more for large N and on a GPU).
        preset: "paper", "fast" (300 iterations) or "quality"; explicit ``iterations``/``samples`` override it.
        refine: Learning rates, loss weights and schedule (:class:`warpgauss.encoding.refine.RefineConfig`).
        self_test: Run the binned-vs-dense self-test before refining.
        time_budget: Seconds the whole call may take, reading to writing (the first compile not counted).
        checkpoint: Refinement's checkpoint file (None: ``OUTPUT.ckpt`` when ``output`` is given).
        checkpoint_every: Seconds between checkpoints.
        resume: Continue from the checkpoint (same input and options). Overwrites ``output``.
        target_psnr: Skip refinement if the analytic model reaches this PSNR (dB), else stop once validation does.
        plateau_db: Stop refinement once the validation PSNR gained less than this (dB) over 300 iterations.
        compact: Size the budget (and the report) for the compact 12-byte format.
        format: "coded" (default, about 6.2-12.8 B a primitive), "float32" ("full", 48 B) or "compact96" ("compact", 12 B).
        example: Built-in example volume name instead of ``source``.
        example_size: Size of the example volume.
        read: Reader options (:class:`warpgauss.readers.ReadOptions`).
        allocation: Allocation knobs (:class:`warpgauss.encoding.allocate.AllocationConfig`).
        evaluate: Run stage EV (PSNR).
        full_eval: EV on the full grid instead of 500,000 sampled voxels.
        output: If given, write the model there (stage S3; atomic).
        force: Overwrite ``output`` if it exists.
        analytic_output: Also write the analytic (pre-refinement) model there.
        on_stage: Optional callback(name, title) as each stage starts (progress display).
        on_stats: Optional callback(stats) once the structure statistics exist (before allocation).
        on_progress: Optional callback(iteration, total, losses) during refinement.
        bricks: Split the grid into bricks (``"2x2x2"``, counts x, y, z), each encoded on its own.
        halo: Voxels of halo around each brick.
        client: A ``distributed.Client``: the bricks run on its cluster (None: in this process).
        on_bricks: Optional callback(bricks done, bricks) during a bricked encode.
        max_device_memory: Bytes (or ``"24GiB"``) one encode may use on the device; a larger one is bricked.
        max_host_memory: The same for this machine's memory.
        read_by_bricks: With ``bricks``, read a file brick by brick (True) or whole (False); None: whole where it fits.
        volume_on_host: Keep the volume in pinned host memory (read by the GPU over the bus), the model whole on the device.
        warm_start: A :class:`Model` (or its (N, 12) parameters) of the previous timestep to refine from.
        motion: With ``warm_start``, first move the primitives with the field's motion.
        max_error: A point-wise bound in source units, kept by a residual stored after the Gaussians.
        max_error_rel: The bound as a share of the source's value range instead.
        residual_psnr: Instead of a bound, the full-grid PSNR (dB) the decode must reach.
        session: The state a :class:`warpgauss.Encoder` keeps between its calls; not for direct use.
        progress: Print refinement's progress on standard error (None: where a person watches).

    Returns:
        The :class:`Model` (the stored one), with ``model.report`` holding the run report.
    """
    line = None
    if on_progress is None and (progress if progress is not None else watched()):
        on_progress = line = ProgressLine()
    try:
        cfg = config_of(locals())
        return encode_with(
            source, cfg, on_stage=on_stage, on_stats=on_stats, on_progress=on_progress, on_bricks=on_bricks, client=client, session=session
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
    """:func:`encode` of ``source`` with the settings of ``cfg`` (see :mod:`.driver.config`), the
    callbacks, Dask client and Encoder session beside them: the request checked, the path chosen
    once (whole or bricked), stage P, the path, then export and the report."""
    source, device, opts = checked_request(source, cfg, session)
    run, reading, bricking = cfg.run, cfg.reading, cfg.bricking
    workers = 0 if client is None else max(1, len(client.scheduler_info().get("workers", {})))  # 0: this process
    path = choose_path(source, cfg, device, workers)
    peers = device_list(cfg)[1:]
    if peers and (path.bricks is not None or client is not None):
        raise WarpgaussError(
            "--devices refines one model on this machine's GPUs; this encode is bricked"
            + (f" ({path.why})" if path.why else "")
            + ": give --volume-on-host for one model, or bricks on a cluster without --devices"
        )
    timer = StageRecorder(on_stage=on_stage)
    from ..field import limits as field_limits

    with timer.stage("P", "load and normalise"):
        buffers = None if session is None else session.buffers
        # a file read on demand is counted by the bricks' statistics (stage Sb), not by a pass of its own
        f, info = load_field(
            source,
            reading.read,
            example=reading.example,
            example_size=reading.example_size,
            lazy=path.lazy,
            buffers=buffers,
            count=not path.lazy,
            max_voxels=field_limits.MAX_HOST_VOXELS if path.volume_on_host else None,  # int64 indices with the volume in host memory
            pinned=path.volume_on_host,  # normalised straight into the pinned memory the kernels read: held once
        )
    warm_start = cfg.start.warm_start
    if isinstance(warm_start, Model) and tuple(warm_start.shape_xyz) != tuple(f.shape_xyz):
        raise WarpgaussError(
            f"the warm-start model is on a {'x'.join(map(str, warm_start.shape_xyz))} grid, this volume {'x'.join(map(str, f.shape_xyz))}; encode cold"
        )
    if path.bricks is not None:
        if run.analytic_output is not None:
            raise WarpgaussError("--bricks does not write an analytic model (--save-analytic)")
        from .scale.driver import encode_bricked

        model = encode_bricked(
            f,
            opts,
            path.bricks,
            halo=bricking.halo,
            device=device,
            client=client,
            timer=timer,
            input_info=info,
            evaluate=run.evaluate,
            full_eval=run.full_eval,
            on_progress=on_bricks,
            max_device_memory=path.device_limit,
            max_host_memory=host_limit(bricking.max_host_memory),
        )
        model.run_report["bricking"].update(
            chosen="by the device and host limits" if path.chosen else "given",
            max_device_memory=path.device_limit,
            read_lazily=bool(info.get("read_lazily")),
            read_why=path.why,
        )
    else:
        model = encode_whole(
            f,
            info,
            source,
            cfg,
            opts,
            device,
            timer,
            on_stats=on_stats,
            on_progress=on_progress,
            volume_on_host=path.volume_on_host,
            peers=peers,
        )
        if path.volume_on_host:
            model.run_report["volume_memory"]["why"] = path.why
    return finish(model, cfg, opts, timer)


def checked_request(source, cfg: EncodeConfig, session) -> tuple[object, str | None, EncodeOptions]:
    """Everything refused before any work, in the order a user should hear it: the budget, the
    bound, the outputs, the checkpoint, the warm start, the format. Returns the source (a device
    array wrapped for Warp), the device and the options the encode runs with."""
    import time

    from ..core.files import check_writable

    called = time.perf_counter()  # a time budget is the whole call's
    cfg.budget.check()  # before the output check: say what is wrong with the request first
    run, bricks, device = cfg.run, cfg.bricking.bricks, cfg.device
    if cfg.bound.given:
        cfg.bound.check()
        check_bounded_request(source, cfg.reading.read, bricks, cfg.start.warm_start, session)
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
    if cfg.devices is not None:
        devices = device_list(cfg)
        if cfg.refinement.time_budget is not None or session is not None:
            raise WarpgaussError("--devices does not combine with a time budget (it refines on one device); give one of them")
        if is_device_array(source):
            raise WarpgaussError("--devices takes a file or a host array; a device array is encoded on its own device")
        device = devices[0]
    return source, device, opts


def device_list(cfg: EncodeConfig) -> list[str]:
    """The devices of ``--devices`` (each present; CUDA devices once each, or the CPU, which may be
    named again: its replicas take turns, a test of the path), the first ``--device`` if that is
    given too; without ``--devices``, ``--device`` alone."""
    from ..core.warp import resolve_device

    given = cfg.devices
    if given is None:
        return [cfg.device] if cfg.device not in (None, "", "auto") else []
    names = [d.strip() for d in given.split(",")] if isinstance(given, str) else [str(d).strip() for d in given]
    if not names or "" in names:
        raise WarpgaussError(f"--devices takes a comma list of devices such as cuda:0,cuda:1, got {given!r}")
    devices = [resolve_device(d) for d in names]
    cuda = [d for d in devices if d != "cpu"]
    if cuda and len(cuda) != len(devices):
        raise WarpgaussError(f"--devices {given}: give GPUs only (cuda:0,cuda:1) or the CPU alone")
    if len(set(cuda)) != len(cuda):
        raise WarpgaussError(f"--devices {given} names a GPU twice; name each once")
    if cfg.device not in (None, "", "auto") and resolve_device(cfg.device) != devices[0]:
        raise WarpgaussError(f"--device {cfg.device} is not the first of --devices {given}; leave --device out")
    return devices


def encode_whole(
    f,
    info: dict,
    source,
    cfg: EncodeConfig,
    opts: EncodeOptions,
    device,
    timer: StageRecorder,
    *,
    on_stats,
    on_progress,
    volume_on_host: bool = False,
    peers: list[str] | None = None,
) -> Model:
    """The whole-volume path: the staged run of :func:`.driver.run.encode_field` (S1-S2, EV) and,
    with an error bound, the residual (S4)."""
    run, bound = cfg.run, cfg.bound
    if bound.given:
        from ..format.residual import CODE_BYTES_PER_VOXEL, DEFAULT_RATIO, MIN_GAUSSIAN_BYTES, check_memory

        check_memory(f.n_voxels, CODE_BYTES_PER_VOXEL, "coding a bounded residual of")
        if not cfg.budget.given:  # the Gaussians' default share, now that the source's bytes are known
            opts.bytes = max(int(f.source_bytes / DEFAULT_RATIO), MIN_GAUSSIAN_BYTES)
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
        force=run.force or run.resume,
        volume_on_host=volume_on_host,
        peers=peers,
    )
    if bound.given:
        with timer.stage("S4", "bounded residual"):
            reading = cfg.reading
            attach_residual(model, source, reading.read, reading.example, reading.example_size, bound, device)
    return model


def finish(model: Model, cfg: EncodeConfig, opts: EncodeOptions, timer: StageRecorder) -> Model:
    """Either path's end: the model written (S3), its checkpoint gone, the report's stage table."""
    run, output, checkpoint = cfg.run, cfg.run.output, opts.checkpoint
    if output is not None:
        with timer.stage("S3", "export"):
            model.save(output, encoding=encoding_of(opts), force=True if run.resume else run.force)
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


AUTO_BRICK_FLOOR = 2 * 2**30  # an encode estimated below this is never bricked by the default limit


@dataclass(frozen=True)
class EncodePath:
    """The path an encode takes: ``bricks`` (None: the whole volume), whether the file is read on
    demand, the device memory limit in bytes, and whether the bricks were chosen here."""

    bricks: Any
    lazy: bool
    device_limit: int | None
    chosen: bool
    why: str = ""  # why a bricked file is read brick by brick or whole, or why the volume stays on the host
    volume_on_host: bool = False  # the whole volume in pinned host memory, the model whole on the device


def choose_path(source, cfg: EncodeConfig, device, workers: int = 0) -> EncodePath:
    """The one decision between the two paths. Given bricks are kept (a file read whole or brick
    by brick by :func:`read_by_bricks_rule`); otherwise a file whose whole encode would not fit
    the device or host limit (or the kernels' voxel index) is bricked by
    :func:`~warpgauss.encoding.scale.plan.choose_bricks` (with a wave for each of a cluster's
    ``workers``; 0: no cluster, this process). Only a format that can be read on demand is looked
    at before it is read."""
    from ..core.limits import HOST_SHARE, available_memory, brick_device_bytes, default_device_limit, parse_memory
    from ..core.warp import resolve_device

    b = cfg.bricking
    bricks, halo, budget = b.bricks, b.halo, cfg.budget.n
    limit = None if b.max_device_memory is None else parse_memory(b.max_device_memory, "--max-device-memory")
    host = host_limit(b.max_host_memory)
    is_file = read_on_demand(source, cfg.reading.example)
    if b.volume_on_host:
        return host_volume_path(source, cfg, bricks, limit, "asked (--volume-on-host)")
    if bricks is not None and is_file:
        gpu_cluster = workers > 0 and resolve_device(device).startswith("cuda")
        lazy, why = read_by_bricks_rule(header_shape(source, cfg.reading.read), host, b.read_by_bricks, gpu_cluster)
        return EncodePath(bricks, lazy, limit, False, why)
    if bricks is not None or not is_file:
        return EncodePath(bricks, False, limit, False, "" if bricks is None else "not a file read on demand: the volume is in memory")
    shape_xyz = header_shape(source, cfg.reading.read)
    voxels = int(np.prod(shape_xyz, dtype=np.int64))
    if host is None:
        free = available_memory()
        host = None if free is None else int(HOST_SHARE * free)
    if limit is None and brick_device_bytes(voxels, int(budget or 0)) > AUTO_BRICK_FLOOR:
        limit = default_device_limit(resolve_device(device))  # None on the CPU
    from .scale.plan import brick_cap, choose_bricks, default_halo

    if halo is None:  # as the bricked encode will choose it (without a budget: for 1 Gaussian per 300 voxels)
        n_guess = int(budget) if budget else max(1, voxels // 300)
        halo = default_halo(brick_cap(max(2.0, max(shape_xyz) / 16.0), shape_xyz, n_guess))
    counts = choose_bricks(shape_xyz, int(budget or 0), limit, int(halo), host, workers)
    if counts == (1, 1, 1):
        return EncodePath(None, False, limit, False)
    if host_volume_auto(device) and b.volume_on_host is None and workers == 0 and limit is not None:
        from ..core.limits import host_volume_device_bytes

        n_guess = int(budget) if budget else max(1, voxels // 300)
        fits_host = host is None or HOST_BYTES_PER_VOXEL_WHOLE * voxels <= host
        if host_volume_device_bytes(voxels, n_guess) <= limit and fits_host:
            return host_volume_path(source, cfg, None, limit, "the volume's encode does not fit the device limit, the model does")
    if b.read_by_bricks is False:
        return EncodePath(counts, False, limit, True, "asked (read_by_bricks False)")
    return EncodePath(counts, True, limit, True, "the bricks were chosen because the whole encode does not fit a memory limit")


# where a file's whole encode does not fit a GPU's device limit but its model does (the volume in
# pinned host memory, read by the kernels over the bus), choose_path keeps the volume whole on the
# host rather than bricking it: the in-core model within 0.05 dB, where bricks in waves lose at
# their seams (issue #55: the 1024^3 vortex in 4x4x4 bricks on Dask 68.40 dB against 69.71
# monolithic, 147.0 s on one GPU worker against 25.9 s). Measured on one H200 (issue #55,
# scale/volume_on_host1024_anchors_h200.json, the 1024^3 vortex at CR 100): 91.6 s against 79.9 s
# in core (1.15x), 68.18 against 68.23 dB
HOST_VOLUME_AUTO = True


def host_volume_auto(device: str | None) -> bool:
    """Whether choose_path may keep a volume too large for the device limit whole in host memory
    (:data:`HOST_VOLUME_AUTO`, on a CUDA device: on the CPU the volume is in host memory anyway and
    the limit holds the volume and the model together)."""
    from ..core.warp import resolve_device

    return HOST_VOLUME_AUTO and resolve_device(device).startswith("cuda")


# host memory of a whole encode with the volume on the host, per voxel: the float32 values
# normalised straight into pinned memory (field.slabs.host_buffers: no second copy since h2048),
# the validity mask, and a byte for stage P's passes over slabs (an estimate by the arrays' sizes;
# a memory-mapped source, raw, .npy or contiguous HDF5, is read a slab at a time, while a format
# read into memory whole adds its own itemsize a voxel for the time of stage P)
HOST_BYTES_PER_VOXEL_WHOLE = 6.0


def host_volume_path(source, cfg: EncodeConfig, bricks, limit: int | None, why: str) -> EncodePath:
    """The whole-volume path with the volume in pinned host memory: refused with bricks, or where
    the model alone would not fit ``limit``."""
    from ..core.limits import host_volume_device_bytes

    if bricks is not None:
        raise WarpgaussError("--volume-on-host keeps the model whole: give it or --bricks, not both")
    if limit is not None and cfg.budget.n:
        shape = header_shape(source, cfg.reading.read) if read_on_demand(source, cfg.reading.example) else np.shape(source)
        need = host_volume_device_bytes(int(np.prod([int(v) for v in shape], dtype=np.int64)), int(cfg.budget.n))
        if need > limit:
            raise WarpgaussError(
                f"with the volume on the host the model alone needs about {need / 2**30:.1f} GiB of device memory, "
                f"--max-device-memory allows {limit / 2**30:.1f} GiB; give a smaller budget or leave the volume to bricks"
            )
    return EncodePath(None, False, limit, False, why, volume_on_host=True)


def read_by_bricks_rule(shape_xyz, host: int | None, asked: bool | None, gpu_cluster: bool = False) -> tuple[bool, str]:
    """Whether a file given bricks is read brick by brick, and why: as ``asked``; on a cluster of
    GPU workers (``gpu_cluster``: their bricks run in waves with no seams' refit, so the whole
    volume would buy nothing and be copied to a file for the workers); else where the whole
    volume's encode would not fit ``host`` bytes (default :data:`~warpgauss.core.limits.HOST_SHARE`
    of the memory available now) at :data:`~warpgauss.core.limits.HOST_BYTES_PER_VOXEL`. A volume
    read whole gets the seams' joint refit (it needs the whole grid in one process): read brick
    by brick, bubbles 48^3 in 2x2x2 bricks on two CPU workers lost 2.35 dB against the monolithic
    encode (issue #55)."""
    from ..core.limits import HOST_BYTES_PER_VOXEL, HOST_SHARE, available_memory

    if asked is not None:
        return bool(asked), f"asked (read_by_bricks {bool(asked)})"
    if gpu_cluster:
        return True, "a cluster of GPU workers runs the bricks in waves without the seams' refit: the workers read their own boxes"
    need = HOST_BYTES_PER_VOXEL * int(np.prod([int(v) for v in shape_xyz], dtype=np.int64))
    if host is None:
        free = available_memory()
        host = None if free is None else int(HOST_SHARE * free)
    if host is None:
        return False, "no host limit is known: the volume is read whole"
    if need <= host:
        return False, f"the whole volume fits the host limit (about {need / 2**30:.2f} GiB of {host / 2**30:.1f} GiB)"
    return True, f"the whole volume would need about {need / 2**30:.1f} GiB of host memory, {host / 2**30:.1f} GiB allowed"
