"""The parts of an encode's report that whole and bricked runs share: where and when it ran, and
what the budget became (N, bytes, how a coded file met its size)."""

from __future__ import annotations

import datetime as _dt
import platform

from ..._version import __version__
from ...core.profiling import StageRecorder
from ...field.analysis import Field, seed_limit
from ...format.model import Model
from .options import EncodeOptions
from .sizing import coded_choice


def run_facts(device: str, input_info: dict | None, f: Field) -> dict:
    """Version, date, device, Warp version, host and input of a run."""
    from ...core.warp import device_name, warp

    return {
        "warpgauss_version": __version__,
        "date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "device": device,
        "device_name": device_name(device),
        "warp_version": warp().config.version,
        "host": platform.node(),
        "input": input_info or {"name": f.name, "shape_xyz": list(f.shape_xyz)},
    }


def budget_facts(
    model: Model,
    opts: EncodeOptions,
    f: Field,
    enc: str,
    budget_bytes: int | None,
    sizing: dict | None,
    fit: dict | None,
    replan: dict | None = None,
    note: dict | None = None,
) -> dict:
    """The report's ``budget``: what was asked, N, the file's bytes and ratio, and for a coded
    byte budget the sizing, re-plan and fit, with one sentence on how the size was met."""
    size, payload = model.file_sizes(encoding=enc)  # one coding of a coded model gives both
    return {
        "n": model.n,
        "requested_budget": opts.budget,
        "requested_ratio": opts.ratio if opts.budget is None and opts.bytes is None else None,
        "requested_bytes": budget_bytes,
        "budget_used": None if budget_bytes is None else size / budget_bytes,
        "coded_sizing": sizing,
        "coded_replan": replan,
        "coded_fit": fit,
        "coded_bits_from_accuracy": note,
        "coded_choice": coded_choice(sizing, fit, note, replan),
        "n_max": seed_limit(f.eligible, f.occupied),
        "format": enc,
        "bytes": size,
        "bytes_per_primitive": payload / max(model.n, 1),
        "compression_ratio": model.source_bytes / size,
        "full_precision_bytes": model.file_size(False),
        "compact_bytes": model.file_size(True),
    }


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
