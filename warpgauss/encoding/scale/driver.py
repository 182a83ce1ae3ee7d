"""The bricked encode's driver (:func:`encode_bricked`, see :mod:`warpgauss.encoding.scale.bricks`) and the choice
of whether a file is bricked and read on demand (:func:`bricking`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
from collections.abc import Callable

import numpy as np

from ...core.profiling import StageRecorder
from ...errors import WarpgaussError
from ...field.analysis import Field
from ...format.model import Model
from ..driver.load import header_shape, read_on_demand
from ..driver.options import EncodeOptions, encoding_of, header_for
from ..driver.report import budget_facts, run_facts
from ..driver.sizing import coded_budget, resolve_budget, sizing_bpp, target_bytes


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
    max_host_memory: int | None = None,
) -> Model:
    """The bricked encode (see :mod:`warpgauss.encoding.scale.bricks`): the budget split over ``bricks`` (counts
    x, y, z) before any refinement, each brick encoded in this process (``client`` None) or on a
    Dask cluster, the primitives merged into one model of exactly N (then stored in the format,
    coded budgets fitted as in the monolithic encode).
    """
    from ...core.warp import resolve_device
    from ...field.analysis import DeviceVolume
    from ...format.wgs import header_size
    from ...readers.lazy import is_lazy
    from .bricks import brick_seed, device_setup
    from .plan import brick_cap, default_halo, parse_bricks, plan_bricks, split_bricks
    from .schedule import choose_schedule
    from .seams import refit_seams

    counts_xyz = parse_bricks(bricks)
    if opts.resume or opts.time_budget is not None or opts.refine.target_psnr is not None or opts.refine.plateau_db is not None:
        raise WarpgaussError("--bricks does not combine with --resume, --time-budget, --target-psnr or --plateau yet")
    enc = encoding_of(opts)
    budget_bytes = target_bytes(f, opts)
    header = header_for(f, opts)
    n = resolve_budget(f, opts, header_size(header, 1 << 40, encoding=enc))
    plan_bricks(f.shape_xyz, counts_xyz, 0 if halo is None else halo)  # a bad bricking is refused before the device starts
    dev = resolve_device(device)
    timer = timer or StageRecorder()
    timer.device = dev
    sizing = None
    dv = None
    if enc == "coded" and budget_bytes is not None:
        if is_lazy(f.values):
            raise WarpgaussError(
                "a volume read brick by brick takes its budget as --budget N (the coded size pilot of --bytes/--ratio needs the whole volume on the device)"
            )
        with timer.stage("S1p", "coded size pilot"):
            dv = DeviceVolume(f, dev)
            n, sizing = coded_budget(dv, f, opts, header, budget_bytes, n)
    cap = brick_cap(opts.allocation.resolved_cap(f.shape_xyz), f.shape_xyz, n)
    allocation = dataclasses.replace(opts.allocation, scale_cap=cap)
    halo = default_halo(cap) if halo is None else int(halo)
    plan = plan_bricks(f.shape_xyz, counts_xyz, halo)
    workers = 0 if client is None else max(1, len(client.scheduler_info().get("workers", {})))
    order = choose_schedule(dev, client, is_lazy(f.values), f.shape_xyz, n, opts.refine.iterations, max_device_memory, counts_xyz, workers)
    # the whole volume on this process's device (the coded pilot's, or for the seams' refit): the
    # bricks' statistics are taken there, and the bricks of this process cut their boxes from it
    resident = None
    if not is_lazy(f.values) and device_setup(dev) and (dv is not None or order.seam_refit > 0):
        if dv is None:
            with timer.stage("Su", "the volume to the device"):
                dv = DeviceVolume(f, dev)
        resident = dv
    with timer.stage("Sb", "budget split over the bricks"):
        # a file read on demand: each box counted on this process's GPU where it has one
        upload = dev if resident is None and is_lazy(f.values) and device_setup(dev) else None
        counts, stats = split_bricks(f, plan, n, dv=resident, host_limit=max_host_memory, device=upload)
    if not f.counted:  # the bricks' interiors partition the grid: their counts are the volume's
        from ...field.analysis import check_budget

        f.occupied, f.eligible = sum(int(s["occupied"]) for s in stats), sum(int(s["eligible"]) for s in stats)
        f.counted = True
        check_budget(f, n, header_size(header, 1 << 40, encoding=enc), sizing_bpp(enc))
    waves: list[dict] = []
    results, sharing, wall = _run_bricks(
        f, plan, stats, opts, allocation, n, dev, client, resident, max_device_memory, timer, on_progress, waves, order
    )
    params = np.concatenate([r["params"] for r in results]) if results else np.zeros((0, 12), np.float32)
    seams = None  # a joint refit of the seams (the schedule's share; the whole volume on one device)
    if order.seam_refit > 0 and opts.refine.iterations > 0 and len(params) and not is_lazy(f.values):
        with timer.stage("S2s", "joint refit of the seams"):
            params, seams = refit_seams(
                f, plan, params, opts.refine, allocation, brick_seed(opts.seed, len(plan)), dev, order.seam_refit, dv=dv
            )
    bits_note = _accuracy_bits(results, plan) if enc == "coded" else None
    model, fit = _stored(Model(params, header), enc, budget_bytes, sizing, bits_note)
    evaluation: dict = {}
    if evaluate:
        from ...field.evaluate import evaluate_field

        with timer.stage("EV", "evaluation"):
            evaluation["final"] = evaluate_field(model.field(dev), f, full=full_eval)
    bricking = {
        "bricks_xyz": list(counts_xyz),
        "halo": halo,
        "scale_cap": allocation.scale_cap,
        "scheduler": "this process" if client is None else str(client.scheduler.address),
        "wall_seconds": wall,
        "volume_to_workers": sharing,
        "schedule": order.report(),
        "waves": waves,
        "seam_refit": seams,
        "workers": _workers(results),
        "bricks": _brick_rows(plan, stats, results),
        "rule": "detail share by interior sum of |grad V|, coverage share by occupied voxels, largest remainders, seed limits",
    }
    model.report = _report(
        model, f, opts, dev, input_info, evaluation, bricking, budget_facts(model, opts, f, enc, budget_bytes, sizing, fit, note=bits_note)
    )
    return model


def _report(model: Model, f: Field, opts: EncodeOptions, dev: str, input_info, evaluation: dict, bricking: dict, budget: dict) -> dict:
    """A bricked encode's run report: the run's facts, its budget and bricking, its evaluation."""
    return {
        **run_facts(dev, input_info, f),
        "budget": budget,
        "bricking": bricking,
        "seed": opts.seed,
        "refinement": {"iterations": opts.refine.iterations, "per_brick": True},
        "evaluation": evaluation,
        "psnr_db": evaluation.get("final", {}).get("psnr_db"),
        "interrupted": False,
        "skipped": [],
    }


def _stored(merged: Model, enc: str, budget_bytes: int | None, sizing: dict | None, bits_note: dict | None) -> tuple[Model, dict | None]:
    """The merged model as the file holds it: coded on the grids its accuracy asks for (as the
    monolithic encode codes) and fitted to a byte budget, or stored in ``enc``; and the fit."""
    merged.coded_bits = None if sizing is None else sizing["bits"]
    if bits_note is not None:  # finer grids for a more accurate model
        merged.coded_bits = bits_note["bits"]
    if enc == "coded" and budget_bytes is not None:
        return merged.fit_bytes(budget_bytes)
    model = merged.stored(enc)
    model.format = enc
    return model, None


def _run_bricks(f, plan, stats, opts, allocation, n, dev, client, resident, max_device_memory, timer, on_progress, waves, order):
    """Stage S1-S2b: every brick's allocation and refinement, in this process or on the cluster,
    the volume handed to them the cheapest way there is. Returns (results, how the volume
    reached the bricks, wall seconds); ``waves`` gets the schedule's waves."""
    from ...readers.lazy import is_lazy
    from .bricks import brick_tasks, resident_bytes, resident_volume
    from .cluster import share_arrays
    from .schedule import run_bricks

    with contextlib.ExitStack() as stack:
        volume, sharing = None, "this process" if client is None else "the boxes in the task graph"
        if client is not None and is_lazy(f.values):
            sharing = "the workers read the file"
        elif client is not None:  # one file the workers read, where they can, not the volume through the graph
            with timer.stage("Sh", "the volume shared with the workers on this machine"):
                files, why = share_arrays(client, [f.values, f.mask], stack)
            if files is not None:
                volume, sharing = tuple(files), "a temporary file the workers read"
            elif why is not None:
                sharing = f"the boxes in the task graph ({why})"
        if resident is not None and client is None:
            volume, sharing = resident_volume(resident), "this process, the volume on its device"
        tasks = brick_tasks(f, plan, stats, opts.seed, allocation, opts.refine, None if client is not None else dev, n, volume=volume)
        limit = max_device_memory
        if limit is not None and resident is not None and client is None:  # the volume held there counts against the bricks
            limit = max(1, limit - resident_bytes(resident))
        t0 = time.perf_counter()
        with timer.stage("S1-S2b", f"{len(plan)} bricks: allocation and refinement"):
            results = run_bricks(tasks, client, on_progress, limit=limit, waves_out=waves, together=order.together)
        wall = time.perf_counter() - t0
    return results, sharing, wall


def _brick_rows(plan, stats, results) -> list[dict]:
    """The report's row of each brick: where it is, its statistics and how its encode went."""
    return [
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
            "sample_psnr_db": r.get("sample_psnr_db"),
            "at_once": r.get("at_once", 1),
            "worker": r.get("worker"),
            "setup_seconds": r.get("setup_seconds"),
            "refine_seconds": r.get("refine_seconds"),
        }
        for b, st, r in zip(plan, stats, results)
    ]


def _accuracy_bits(results: list[dict], plan) -> dict | None:
    """The coded grids for the merged model's accuracy (``ratefit.bits_for_psnr``, as the
    monolithic encode picks them from its training samples): the bricks' last sample MSEs,
    weighted by their interior voxels. None where no brick refined. Without it a 2x2x2 bricked
    model of bubbles 48^3 (3,000 Gaussians, 200 iterations, CPU) was coded on the default grids:
    58.07 dB against 65.95 as float32 and the monolithic encode's 68.21 coded."""
    from ...format.ratefit import accuracy_bits

    mse = weight = 0.0
    for b, r in zip(plan, results):
        if r.get("sample_psnr_db") is None:
            continue
        voxels = float(np.prod([hi - lo for lo, hi in b.interior]))
        mse += voxels * 10.0 ** (-float(r["sample_psnr_db"]) / 10.0)
        weight += voxels
    if weight == 0.0:
        return None
    psnr = float(10.0 * np.log10(weight / max(mse, 1e-20)))
    return accuracy_bits(psnr) | {"from": "the bricks' samples, by interior voxels"}


def _workers(results: list[dict]) -> dict:
    """Per process that ran bricks: how many, and its high-water marks of device memory (Warp's
    pool) and host memory (peak RSS) as its last group reported them."""
    out: dict[str, dict] = {}
    for r in results:
        w = out.setdefault(
            str(r.get("worker")), {"bricks": 0, "device": r["device"], "device_peak_bytes": None, "host_peak_rss_bytes": None}
        )
        w["bricks"] += 1
        for k in ("device_peak_bytes", "host_peak_rss_bytes"):
            if r.get(k) is not None:
                w[k] = max(w[k] or 0, r[k])
    return out


def check_bricking(source, read, example, example_size, bricks, halo) -> None:
    """Refuse a bricking that cannot split the volume (too many bricks along an axis), where its
    shape is known without reading it: an example, or a file whose header gives it (the formats
    read on demand). Runs before a Dask cluster starts; other inputs are checked once read."""
    from .plan import parse_bricks, plan_bricks

    counts = parse_bricks(bricks)
    if example is not None:
        size = example_size
        shape_xyz = tuple(int(v) for v in size) if isinstance(size, (tuple, list)) else (int(size),) * 3
    elif read_on_demand(source, example):
        shape_xyz = header_shape(source, read)
    else:
        return
    plan_bricks(shape_xyz, counts, 0 if halo is None else int(halo))
