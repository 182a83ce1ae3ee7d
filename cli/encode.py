"""`warpgauss encode`: volume -> fixed-budget Gaussian model (.wgs) plus a JSON run report."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

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
    parse_shape,
    print_json,
    psnr_text,
    resolved_config,
    size_text,
)


@handle_errors
def encode(
    ctx: typer.Context,
    input: Annotated[
        Path | None, typer.Argument(rich_help_panel="Input", help="Volume file (.raw .npy .h5 .vti .nii.gz .nrrd .mha .nc .mrc ...)")
    ] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", rich_help_panel="Output", help="Model file; default NAME.wgs")] = None,
    example: Annotated[str | None, typer.Option(rich_help_panel="Input", help="Encode a built-in example volume instead of a file")] = None,
    size: Annotated[int, typer.Option(rich_help_panel="Input", help="Edge length of the --example volume")] = 64,
    budget: Annotated[
        int | None, typer.Option("--budget", "-n", rich_help_panel="Budget and format", help="Number of Gaussians N (exact)")
    ] = None,
    ladder: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Budget and format",
            help="Several budgets, e.g. 2000,20000,200000: one read and analysis, one model each (OUTPUT with .nN before the suffix)",
        ),
    ] = None,
    ratio: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Budget and format", help="Target compression ratio: a file of at most source bytes / RATIO; default 20"
        ),
    ] = None,
    file_bytes: Annotated[
        int | None,
        typer.Option(
            "--bytes",
            rich_help_panel="Budget and format",
            help="File size budget in bytes (header included), instead of --budget or --ratio",
        ),
    ] = None,
    max_error: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Error bound",
            help="Every decoded voxel within this of the source (source units): a residual stored after the Gaussians; without a budget the Gaussians get 1/1000 of the source's bytes (8 KiB at least)",
        ),
    ] = None,
    max_error_rel: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Error bound",
            help="The bound as a share of the source's value range (e.g. 1e-3), instead of --max-error",
        ),
    ] = None,
    psnr: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Error bound",
            help="Instead of a bound: the full-grid PSNR (dB) the decode must reach, with the largest point-wise bound that reaches it",
        ),
    ] = None,
    seed: Annotated[int, typer.Option(rich_help_panel="Refinement", help="Seed: same seed and device give the same model")] = 0,
    device: Annotated[
        str | None, typer.Option(rich_help_panel="Refinement", help="Warp device: cpu, cuda, cuda:N (default: CUDA if present)")
    ] = None,
    compact: Annotated[
        bool, typer.Option("--compact", rich_help_panel="Budget and format", help="Write the compact 12-byte/primitive format")
    ] = False,
    fmt: Annotated[
        str | None,
        typer.Option(
            "--format",
            rich_help_panel="Budget and format",
            help="File format: coded (default: quantised + Zstandard, about 7-14 B/Gaussian, --ratio/--bytes budgets never exceeded, 99-100 % used), full (float32, 48 B) or compact (12 B)",
        ),
    ] = None,
    iterations: Annotated[
        int | None, typer.Option(rich_help_panel="Refinement", help="Refinement iterations (default 1500; 0: analytic model only)")
    ] = None,
    samples: Annotated[
        int | None,
        typer.Option(
            rich_help_panel="Refinement",
            help="Samples per iteration (default 3072, x ceil(N / 350000) for large budgets; on a GPU at least voxels / 128 as a power of two in 16384-131072; the report says what it chose)",
        ),
    ] = None,
    preset: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Refinement",
            help="paper (1500 x 3072 whatever N), fast (the default's sampling for 300 iterations) or quality (1500 x 12288)",
        ),
    ] = None,
    no_self_test: Annotated[
        bool, typer.Option("--no-self-test", rich_help_panel="Refinement", help="Skip the binned-vs-dense self-test")
    ] = False,
    time_budget: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Refinement",
            help="Seconds the whole encode may take, reading to writing (the kernels' first compile not counted): refinement gets what the other stages leave, keeps >= 1,500 iterations where they fit and spends spare time on more samples (unless --samples is given)",
        ),
    ] = None,
    lr: Annotated[float, typer.Option(rich_help_panel="Refinement", help="Adam base learning rate (per-group multipliers apply)")] = 8e-3,
    w_value_empty: Annotated[
        float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: value term at empty samples (paper: 0)")
    ] = 1.0,
    w_density: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: density towards 1 where occupied")] = 0.001,
    w_smooth: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: smoothness at the start (anneals)")] = 0.01,
    w_smooth_final: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: smoothness at the end")] = 0.0001,
    w_anchor: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: anchor of a to V(mu)")] = 0.001,
    w_aniso: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: anisotropy bound 3:1")] = 1.0,
    w_cap: Annotated[float, typer.Option(rich_help_panel="Loss weights", help="Loss weight: scale range")] = 1.0,
    save_analytic: Annotated[
        Path | None, typer.Option(rich_help_panel="Output", help="Also write the analytic (pre-refinement) model")
    ] = None,
    stride: Annotated[int, typer.Option(rich_help_panel="Input", help="Take every K-th voxel on each axis")] = 1,
    shape: Annotated[str | None, typer.Option(rich_help_panel="Input", help="Raw files: XxYxZ when the name does not say")] = None,
    dtype: Annotated[str | None, typer.Option(rich_help_panel="Input", help="Raw files: uint8, int16, float32, ...")] = None,
    endian: Annotated[str | None, typer.Option(rich_help_panel="Input", help="Raw files: little (default) or big")] = None,
    dataset: Annotated[str | None, typer.Option(rich_help_panel="Input", help="HDF5: dataset path (default: first 3D dataset)")] = None,
    variable: Annotated[
        list[str] | None,
        typer.Option(
            rich_help_panel="Input",
            help="netCDF/HDF5/Zarr variable (default: the first 3D one); a (t, z, y, x) variable is a series; several --variable: a series each",
        ),
    ] = None,
    fill_value: Annotated[
        float | None, typer.Option(rich_help_panel="Input", help="Source value marking missing data (masked out)")
    ] = None,
    report: Annotated[Path | None, typer.Option(rich_help_panel="Output", help="Run report JSON; default OUTPUT.report.json")] = None,
    full_eval: Annotated[
        bool, typer.Option("--full-eval", rich_help_panel="Output", help="PSNR on the full grid, not 500,000 samples")
    ] = False,
    as_json: Annotated[bool, typer.Option("--json", rich_help_panel="Output", help="Print the run report as JSON on stdout")] = False,
    verbose: Annotated[
        bool,
        typer.Option(
            "--verbose", "-v", rich_help_panel="Output", help="Also print each stage's seconds and memory and what the run skipped"
        ),
    ] = False,
    checkpoint: Annotated[
        Path | None,
        typer.Option(rich_help_panel="Run control", help="Refinement checkpoint file; default OUTPUT.ckpt (deleted when the run ends)"),
    ] = None,
    checkpoint_every: Annotated[
        float, typer.Option(rich_help_panel="Run control", help="Seconds between checkpoints (Ctrl-C also writes one)")
    ] = 60.0,
    resume: Annotated[
        bool,
        typer.Option(
            "--resume", rich_help_panel="Run control", help="Continue an interrupted run from its checkpoint (same input and options)"
        ),
    ] = False,
    target_psnr: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Refinement", help="dB: skip refinement if the analytic model reaches it, else stop once a validation PSNR does"
        ),
    ] = None,
    plateau: Annotated[
        float | None,
        typer.Option(
            rich_help_panel="Refinement", help="dB: stop refinement once the validation PSNR gains less than this over 300 iterations"
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", rich_help_panel="Output", help="Overwrite existing output files")] = False,
    bricks: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Bricks and cluster",
            help="Split the grid into bricks, e.g. 2x2x2 (x, y, z), the budget over them up front, each encoded on a Dask worker and merged into one model",
        ),
    ] = None,
    halo: Annotated[
        int | None,
        typer.Option(
            rich_help_panel="Bricks and cluster",
            help="Voxels of halo around each brick (default: the longest side / 32, at least 4); a brick caps sigma at halo / 2",
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
    motion: Annotated[
        bool,
        typer.Option(
            "--motion/--no-motion",
            rich_help_panel="Time series",
            help="Move a warm start's Gaussians with the field's motion (block Lucas-Kanade) before refining",
        ),
    ] = True,
    max_device_memory: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Bricks and cluster",
            help="Device memory an encode may use, e.g. 24GiB (default: 90 % of a GPU's free memory); a volume whose encode would not fit is split into bricks and read brick by brick",
        ),
    ] = None,
    max_host_memory: Annotated[
        str | None,
        typer.Option(
            rich_help_panel="Bricks and cluster",
            help="Host memory a brick may use, e.g. 16GiB (default: half of what is available); a volume that would not fit is split into bricks and read brick by brick",
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
) -> None:
    """Encode a volume into N anisotropic Gaussians, evaluate it and write the model and a report."""
    import warpgauss
    from warpgauss._fs import atomic_write_bytes, check_writable
    from warpgauss.io import ReadOptions
    from warpgauss.optimize import LossWeights, RefineConfig

    if (input is None) == (example is None):
        fail("give a volume file or --example NAME (one of them)")
    from warpgauss.driver.sizing import check_budget_options

    check_budget_options(budget, ratio, file_bytes)  # what needs no data is checked before any file is looked at
    from warpgauss.residual import Bound

    bounded = Bound(max_error, max_error_rel, psnr).given
    if bounded:
        Bound(max_error, max_error_rel, psnr).check()
        if ladder is not None or bricks is not None or stride > 1:
            fail(
                "--max-error (or --psnr) bounds every source voxel of one whole encode: it does not combine with --ladder, --bricks or --stride"
            )
    weights = LossWeights(w_value_empty, w_density, w_smooth, w_smooth_final, w_anchor, w_aniso, w_cap)
    variables = list(variable or [])
    one_variable = variables[0] if len(variables) == 1 else None
    read = ReadOptions(parse_shape(shape), dtype, endian, dataset, one_variable, stride, fill_value)
    from warpgauss.driver.config import EncodeConfig

    cfg = EncodeConfig.from_kwargs(  # every path below takes its settings from here
        budget=budget,
        ratio=ratio,
        file_bytes=file_bytes,
        seed=seed,
        device=device,
        iterations=iterations,
        samples=samples,
        preset=preset,
        refine=RefineConfig(lr=lr, weights=weights),
        self_test=not no_self_test,
        time_budget=time_budget,
        checkpoint=checkpoint,
        checkpoint_every=checkpoint_every,
        resume=resume,
        target_psnr=target_psnr,
        plateau_db=plateau,
        compact=compact,
        format=fmt,
        example=example,
        example_size=size,
        read=read,
        full_eval=full_eval,
        force=force,
        analytic_output=save_analytic,
        bricks=bricks,
        halo=halo,
        max_device_memory=max_device_memory,
        max_host_memory=max_host_memory,
        motion=motion,
        max_error=max_error,
        max_error_rel=max_error_rel,
        residual_psnr=psnr,
    )
    series = input is not None and not input.exists() and any(c in str(input) for c in "*?[")
    if input is not None and not series and (len(variables) > 1 or input.exists()):
        from warpgauss.series import time_steps

        series = len(variables) > 1 or time_steps(input, one_variable) is not None
    if not series and (cold or warm_iterations is not None or not motion or keyframe_drift is not None):
        fail(
            "--cold, --warm-iterations, --keyframe-drift and --no-motion apply to a series: a glob such as 'run/t_*.raw', a file with a time axis, or several --variable"
        )
    if keyframe_drift is not None and keyframe_drift < 0:
        fail(f"--keyframe-drift must be >= 0 dB (0: never re-encode cold), got {keyframe_drift:g}")
    if series:
        if ladder is not None or resume or save_analytic is not None or bricks is not None or bounded:
            fail("a series does not combine with --ladder, --resume, --save-analytic, --bricks, --max-error or --psnr yet")
        from .encode_many import encode_series

        encode_series(str(input), variables, (workers, scheduler), output, cfg, cold, warm_iterations, keyframe_drift, as_json)
        return
    if input is not None and not input.exists():
        fail(f"no such file: {input}")
    stem = example if example is not None else _stem(input) if input is not None else "volume"
    out = output or Path(f"{stem}.wgs")
    rep_path = report or out.with_name(out.name + ".report.json")
    check_writable(out, force=force or resume)  # the file the user named first, then its report beside it
    check_writable(rep_path, force=force or resume)

    if ladder is not None:
        if (
            budget is not None
            or ratio is not None
            or file_bytes is not None
            or resume
            or time_budget is not None
            or save_analytic is not None
        ):
            fail(
                "--ladder gives the budgets: it does not combine with --budget, --ratio, --bytes, --time-budget, --resume or --save-analytic"
            )
        from .encode_many import encode_ladder

        encode_ladder(ladder, input, out, cfg, as_json)
        return
    status = None if as_json else err_console.status("starting", spinner="dots")
    lines = None if status is None else PhaseLines(status)
    if status is not None:
        status.start()

    def progress(it: int, total: int, rec: dict) -> None:
        if lines is not None:
            lines.update(f"iteration {it}/{total}, sample PSNR {rec['sample_psnr_db']:.2f} dB")

    client = None
    if bricks is None and (
        workers is not None or scheduler is not None or (halo is not None and max_device_memory is None and max_host_memory is None)
    ):
        fail("--halo, --workers and --scheduler apply to a bricked encode: give --bricks XxYxZ (--halo also --max-device-memory)")
    if bricks is not None:
        from warpgauss.brickplan import parse_bricks
        from warpgauss.cluster import default_client

        parse_bricks(bricks)  # refused in one line before a cluster starts
        if halo is not None and halo < 0:
            fail(f"--halo must be >= 0 voxels, got {halo}")
        from warpgauss.driver.bricked import check_bricking

        check_bricking(input, read, example, size, bricks, halo)
        client, where = default_client(workers, scheduler, device)
        if status is not None:
            status.console.print(f"bricks {bricks}: {where}", highlight=False)

    def brick_progress(done: int, total: int) -> None:
        if lines is not None:
            lines.update(f"{done}/{total} bricks encoded")

    try:
        model = warpgauss.encode(
            input,
            **cfg.replace(output=out).to_kwargs(),
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
        out_console.print(f"{label}: {b['coded_choice']}", soft_wrap=True)
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
    out_console.print(f"time: {rep['total_seconds']:.2f} s on {rep['device_name']}")
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
