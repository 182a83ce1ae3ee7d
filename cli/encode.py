"""`warpgauss encode`: volume -> fixed-budget Gaussian model (.wgs) plus a JSON run report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from warpgauss.encoding.driver.config import OPTIONS, config_from_options, option_default

from .common import (
    PhaseLines,
    config_callback,
    err_console,
    error_text,
    fail,
    handle_errors,
    human_bytes,
    json_text,
    out_console,
    print_json,
    psnr_text,
    resolved_config,
    size_text,
    with_settings,
)

SERIES_ONLY = "--cold, --warm-iterations, --keyframe-drift and --no-motion apply to a series: a glob such as 'run/t_*.raw', a file with a time axis, or several --variable"


@handle_errors
@with_settings(OPTIONS, option_default)
def encode(
    ctx: typer.Context,
    input: Annotated[
        Path | None, typer.Argument(rich_help_panel="Input", help="Volume file (.raw .npy .h5 .vti .nii.gz .nrrd .mha .nc .mrc ...)")
    ] = None,
    variable: Annotated[
        list[str] | None,
        typer.Option(
            rich_help_panel="Input",
            help="netCDF/HDF5/Zarr variable (default: the first 3D one); a (t, z, y, x) variable is a series; several --variable: a series each",
        ),
    ] = None,
    ladder: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Budget and format",
            help="Several budgets, e.g. 2000,20000,200000: one read and analysis, one model each (OUTPUT with .nN before the suffix)",
        ),
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            rich_help_panel="Bricks and cluster",
            help="Local cluster size for --bricks or a series (default: one worker per GPU, this process on one GPU, up to 4 processes on the CPU; 0: this process)",
        ),
    ] = None,
    scheduler: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Bricks and cluster", help="Address of a running Dask scheduler (e.g. tcp://host:8786) for --bricks or a series"
        ),
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            is_eager=True,
            callback=config_callback,
            rich_help_panel="Run control",
            help="TOML file of options (names as here, e.g. ratio = 100, w-smooth = 0.01), or a run report to repeat; the command line wins",
        ),
    ] = None,
    report: Annotated[Path | None, typer.Option(rich_help_panel="Output", help="Run report JSON; default OUTPUT.report.json")] = None,
    as_json: Annotated[bool, typer.Option("--json", rich_help_panel="Output", help="Print the run report as JSON on stdout")] = False,
    verbose: Annotated[
        bool,
        typer.Option(
            "--verbose", "-v", rich_help_panel="Output", help="Also print each stage's seconds and memory and what the run skipped"
        ),
    ] = False,
    cold: Annotated[
        bool,
        typer.Option(
            "--cold",
            rich_help_panel="Time series",
            help="A series (INPUT a glob such as 'run/t_*.raw'): encode every timestep from its own allocation, not from the previous model",
        ),
    ] = False,
    warm_iterations: Annotated[
        int | None,
        typer.Option(rich_help_panel="Time series", help="Refinement iterations of a warm-started timestep (default: --iterations)"),
    ] = None,
    keyframe_drift: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Time series",
            help="Key frames: a warm timestep whose PSNR falls more than this many dB below the best warm PSNR since the chain's last cold timestep is encoded again cold and the better of the two kept; the chain goes on from it (default 1.0; 0: never)",
        ),
    ] = None,
    *,
    settings: dict,
) -> None:
    """Encode a volume into N anisotropic Gaussians, evaluate it and write the model and a report."""
    from warpgauss.encoding.driver.sizing import check_budget_options

    if (input is None) == (settings["example"] is None):
        fail("give a volume file or --example NAME (one of them)")
    check_budget_options(settings["budget"], settings["ratio"], settings["file_bytes"])  # what needs no data, before any file is looked at
    variables = list(variable or [])
    cfg = config_from_options(settings, read={"variable": variables[0] if len(variables) == 1 else None})
    _refuse_combinations(cfg, ladder)
    series = input is not None and not input.exists() and any(c in str(input) for c in "*?[")
    if input is not None and not series and (len(variables) > 1 or input.exists()):
        from warpgauss.series import time_steps

        series = len(variables) > 1 or time_steps(input, variables[0] if len(variables) == 1 else None) is not None
    if not series and (cold or warm_iterations is not None or not cfg.start.motion or keyframe_drift is not None):
        fail(SERIES_ONLY)
    if keyframe_drift is not None and keyframe_drift < 0:
        fail(f"--keyframe-drift must be >= 0 dB (0: never re-encode cold), got {keyframe_drift:g}")
    if series:
        run = cfg.run
        if ladder is not None or run.resume or run.analytic_output is not None or cfg.bricking.bricks is not None or cfg.bound.given:
            fail("a series does not combine with --ladder, --resume, --save-analytic, --bricks, --max-error or --psnr yet")
        from .encode_many import encode_series

        encode_series(str(input), variables, (workers, scheduler), run.output, cfg, cold, warm_iterations, keyframe_drift, as_json)
        return
    if input is not None and not input.exists():
        fail(f"no such file: {input}")
    example = cfg.reading.example
    stem = example if example is not None else _stem(input) if input is not None else "volume"
    out = Path(cfg.run.output) if cfg.run.output is not None else Path(f"{stem}.wgs")
    rep_path = report or out.with_name(out.name + ".report.json")
    _check_writable(out, rep_path, cfg)  # the file the user named first, then its report beside it
    if ladder is not None:
        from .encode_many import encode_ladder

        encode_ladder(ladder, input, out, cfg, as_json)
        return
    model = _encode_one(input, cfg.replace(output=out), workers, scheduler, as_json, verbose)
    _finish(ctx, model, rep_path, as_json, verbose)


def _refuse_combinations(cfg, ladder: str | None) -> None:
    """What the command line refuses before it reads anything: a bound with a ladder, bricks or a
    stride; a ladder with any other budget, a resume, a time budget, an analytic model or the
    volume on the host."""

    if cfg.bound.given:
        cfg.bound.check()
        if ladder is not None or cfg.bricking.bricks is not None or cfg.reading.stride > 1:
            fail(
                "--max-error (or --psnr) bounds every source voxel of one whole encode: it does not combine with --ladder, --bricks or --stride"
            )
    if ladder is not None and (
        cfg.budget.given or cfg.run.resume or cfg.refinement.time_budget is not None or cfg.run.analytic_output is not None
    ):
        fail("--ladder gives the budgets: it does not combine with --budget, --ratio, --bytes, --time-budget, --resume or --save-analytic")
    if ladder is not None and cfg.bricking.volume_on_host:
        fail("--volume-on-host is one encode's: it does not combine with --ladder (the rungs share one device volume)")
    if ladder is not None and cfg.devices is not None:
        fail("--devices is one encode's: it does not combine with --ladder (the rungs refine on one device)")


def _check_writable(out: Path, rep_path: Path, cfg) -> None:
    from warpgauss.core.files import check_writable

    force = cfg.run.force or cfg.run.resume
    check_writable(out, force=force)
    check_writable(rep_path, force=force)


def _encode_one(input, cfg, workers, scheduler, as_json: bool, verbose: bool):
    """One model: the encode with its progress lines (and a Dask cluster for bricks)."""
    import warpgauss

    status = None if as_json else err_console.status("starting", spinner="dots")
    lines = None if status is None else PhaseLines(status)
    b = cfg.bricking
    if b.bricks is None and (
        workers is not None or scheduler is not None or (b.halo is not None and b.max_device_memory is None and b.max_host_memory is None)
    ):
        fail("--halo, --workers and --scheduler apply to a bricked encode: give --bricks XxYxZ (--halo also --max-device-memory)")
    if status is not None:
        status.start()

    def progress(it: int, total: int, rec: dict) -> None:
        if lines is not None:
            lines.update(f"iteration {it}/{total}, sample PSNR {rec['sample_psnr_db']:.2f} dB")

    def brick_progress(done: int, total: int) -> None:
        if lines is not None:
            lines.update(f"{done}/{total} bricks encoded")

    client = None
    try:
        if b.bricks is not None:
            client = _cluster(input, cfg, workers, scheduler, status)
        model = warpgauss.encode(
            input,
            **cfg.to_kwargs(),
            on_stage=None if lines is None else lines.stage,
            on_stats=None if status is None or not verbose else lambda s: status.console.print(_stats_line(s)),
            on_progress=None if status is None else progress,
            client=client,
            on_bricks=brick_progress,
        )
        if lines is not None:
            lines.close()
    finally:
        if status is not None:
            status.stop()
        if client is not None:
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and scheduler is None:
                cluster.close()
    return model


def _cluster(input, cfg, workers, scheduler, status):
    """The Dask client a bricked encode runs on, once the bricking is known to split the volume."""
    from warpgauss.encoding.scale.cluster import default_client
    from warpgauss.encoding.scale.driver import check_bricking
    from warpgauss.encoding.scale.plan import parse_bricks

    b, reading = cfg.bricking, cfg.reading
    parse_bricks(b.bricks)  # refused in one line before a cluster starts
    if b.halo is not None and b.halo < 0:
        fail(f"--halo must be >= 0 voxels, got {b.halo}")
    check_bricking(input, reading.read, reading.example, reading.example_size, b.bricks, b.halo)
    client, where = default_client(workers, scheduler, cfg.device)
    if status is not None:
        status.console.print(f"bricks {b.bricks}: {where}", highlight=False)
    return client


def _finish(ctx: typer.Context, model, rep_path: Path, as_json: bool, verbose: bool) -> None:
    """The report written beside the model (with the options that repeat the run), the summary or
    the JSON printed; an interrupted run says how to continue and exits 130."""
    from warpgauss.core.files import atomic_write_bytes

    rep = model.run_report
    rep["report"] = str(rep_path)
    rep["config"] = resolved_config(ctx, rep_path.parent)  # warpgauss encode --config REPORT repeats the run, from any folder
    atomic_write_bytes(rep_path, json_text(rep).encode())
    if as_json:
        print_json(rep)
    elif not rep.get("interrupted"):
        _print_summary(rep, verbose)
    if rep.get("interrupted"):
        r = rep["refinement"]
        ck = r.get("checkpoint") or {}
        err_console.print(
            f"interrupted at iteration {r['iterations_done']}/{r['iterations']}: wrote {rep['output']} (a valid model of "
            f"the state reached)" + (f" and {ck['path']}; continue with the same command and --resume" if ck.get("path") else ""),
            soft_wrap=True,
            highlight=False,
        )
        raise typer.Exit(130)


def _stem(path: Path) -> str:
    name = path.name
    for suffix in (".gz", ".bz2"):
        if name.endswith(suffix):
            name = name[: -len(suffix)]
    return name.rsplit(".", 1)[0] if "." in name else name


def _stats_line(s: dict) -> str:
    return (
        f"structure: occupancy {100 * s['occupancy']:.1f} %, gradient top-10 % {100 * s['grad_top10']:.1f} %, "
        f"S(1)/S(16) {'n/a' if s['s1_s16'] is None else format(s['s1_s16'], '.3f')}" + (" (sampled)" if s["sampled"] else "")
    )


def _print_summary(rep: dict, verbose: bool = False) -> None:
    """The encode's result for people: what was written (N, bytes, ratio), how accurate it is, how
    long it took and where the files went; with ``verbose`` also the structure, the stage table
    (codes as in the report) and what the run skipped."""
    from rich.table import Table

    b, res = rep["budget"], rep.get("residual")
    ev = rep["evaluation"].get("final")
    head = f"[bold]{rep['input']['name']}[/] {'x'.join(map(str, rep['input']['shape_xyz']))} -> {b['n']} Gaussians"
    if res:  # one file, one ratio: the file as written; its parts' sizes on the next line
        out_console.print(f"{head} and a residual: file {size_text(res['file_bytes'])}, compression {res['compression_ratio']:.2f}x")
        out_console.print(
            f"in the file: Gaussians {res['gaussian_bytes']:,} B ({b['format']} at {b['bytes_per_primitive']:.2f} B a Gaussian "
            f"plus the header), residual {res['residual_bytes']:,} B ({res['predictor']} predictor, {res['literals']} voxels stored exactly)",
            soft_wrap=True,
        )
    else:
        out_console.print(
            f"{head}, {b['format']} at {b['bytes_per_primitive']:.2f} B a Gaussian plus the header: file {size_text(b['bytes'])}, "
            f"compression {b['compression_ratio']:.2f}x"
        )
    if b.get("coded_choice"):  # how a coded file met its byte budget: primitives against precision
        label = "the Gaussians' size" if res else "size"
        if verbose:
            out_console.print(f"{label}: {b['coded_choice']}", soft_wrap=True)
        else:  # one sentence; the sizing, re-plan and rate control behind --verbose
            out_console.print(
                f"{label}: {b['n']:,} Gaussians on the grids their accuracy needs fill the budget (--verbose: how they were chosen)"
            )
    an = rep["evaluation"].get("analytic")
    if an and ev and an is not ev and rep["refinement"].get("iterations"):
        r = rep["refinement"]
        done = r.get("iterations_done", r["iterations"])
        its = f"{done} iterations" if done == r["iterations"] else f"{done} of {r['iterations']} iterations"
        out_console.print(
            f"refinement: {its} x {r['samples']} samples in {r['seconds']:.2f} s "
            f"({r['ms_per_iteration']:.2f} ms/iteration); PSNR {an['psnr_db']:.2f} -> {ev['psnr_db']:.2f} dB"
        )
    if ev:
        what = "Gaussians alone: " if res else ""
        out_console.print(
            f"{what}{psnr_text(ev['psnr_db'], ev['psnr_occupied_db'])}, max abs error {error_text(ev['max_abs_error'])}, {ev['mode']}"
        )
    if res:
        out_console.print(
            f"with the residual: {psnr_text(res['psnr_db'], res['psnr_occupied_db'])}, "
            f"max abs error {error_text(res['max_abs_error_normalised'], res['max_abs_error'])}, "
            f"every voxel within the bound {res['bound']:.6g} source units",
            soft_wrap=True,
        )
    replicas = (rep.get("refinement") or {}).get("replicas")
    spread = f" (refined on {', '.join(replicas['devices'])})" if replicas else ""
    out_console.print(f"time: {rep['total_seconds']:.2f} s on {rep['device_name']}{spread}")
    if verbose:
        t = Table(show_edge=False, header_style="bold")
        for col in ("stage", "what", "seconds", "host peak", "device peak"):
            t.add_column(col, justify="right" if col in ("seconds", "host peak", "device peak") else "left")
        for s in rep["stages"]:
            t.add_row(s["stage"], s["title"], f"{s['seconds']:.3f}", human_bytes(s["host_peak_bytes"]), human_bytes(s["device_peak_bytes"]))
        out_console.print(t)
        for sk in rep["skipped"]:
            out_console.print(f"skipped {sk['what']}: {sk['why']}")
    elif rep["skipped"]:
        n = len(rep["skipped"])
        out_console.print(f"{n} note{'s' * (n != 1)} on what the run skipped: --verbose or the report")
    out_console.print(f"model: {rep['output']}   report: {rep['report']}")
