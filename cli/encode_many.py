"""`warpgauss encode` of several models at once: a ladder of budgets (``--ladder``) and a time
series (a glob, a file with a time axis, several ``--variable``), each with its table."""

from __future__ import annotations

from pathlib import Path

from .common import err_console, json_text, out_console, parse_int_list, print_json


def encode_ladder(text, input, out, cfg, as_json) -> None:
    """``warpgauss encode --ladder N1,N2,...``: one model and report per budget (see warpgauss.encode_ladder)."""
    import inspect

    import warpgauss
    from warpgauss.core.files import atomic_write_bytes, check_writable

    force = cfg.run.force
    budgets = parse_int_list(text, "--ladder") or ()
    pattern = str(out.with_name(f"{out.stem}.n{{n}}{out.suffix or '.wgs'}"))
    for n in sorted(set(budgets)):
        check_writable(Path(pattern.format(n=n) + ".report.json"), force=force)
    status = None if as_json else err_console.status("starting", spinner="dots")
    if status is not None:
        status.start()
    try:
        takes = inspect.signature(warpgauss.encode_ladder).parameters
        models = warpgauss.encode_ladder(
            input,
            budgets=budgets,
            output_pattern=pattern,
            **{k: v for k, v in cfg.to_kwargs().items() if k in takes},  # the command line refused the others already
            on_stage=None if status is None else lambda name, title: status.update(f"[bold]{name}[/] {title}"),
        )
    finally:
        if status is not None:
            status.stop()
    rows = []
    for m in models:
        rep = m.run_report
        rep["report"] = rep["output"] + ".report.json"
        atomic_write_bytes(rep["report"], json_text(rep).encode())
        ev = rep["evaluation"]
        rows.append(
            {
                "n": rep["budget"]["n"],
                "bytes": rep["budget"]["bytes"],
                "compression_ratio": rep["budget"]["compression_ratio"],
                "psnr_analytic_db": ev["analytic"]["psnr_db"],
                "psnr_db": ev["final"]["psnr_db"],
                "seconds": rep["total_seconds"],
                "output": rep["output"],
            }
        )
    if as_json:
        print_json({"ladder": rows})
        return
    from rich.table import Table

    t = Table(show_edge=False, header_style="bold")
    for col in ("N", "bytes", "ratio", "analytic dB", "PSNR dB", "seconds", "model"):
        t.add_column(col, justify="left" if col == "model" else "right")
    for r in rows:
        t.add_row(
            f"{r['n']:,}",
            f"{r['bytes']:,}",
            f"{r['compression_ratio']:.2f}x",
            f"{r['psnr_analytic_db']:.2f}",
            f"{r['psnr_db']:.2f}",
            f"{r['seconds']:.2f}",
            r["output"],
        )
    out_console.print(t)


def encode_series(
    pattern: str,
    variables: list[str],
    cluster: tuple,
    output,
    cfg,
    cold: bool,
    warm_iterations,
    keyframe_drift: float | None,
    as_json: bool,
) -> None:
    """``warpgauss encode 'GLOB'`` (or a file with a time axis, or several --variable): one model
    and report per timestep and variable (see warpgauss.encode_series)."""
    import warpgauss
    from warpgauss.core.files import atomic_write_bytes
    from warpgauss.series.steps import KEYFRAME_DRIFT_DB

    read, force = cfg.reading.read, cfg.run.force
    # what a series sets per timestep (output, warm start) or passes on its own (read, force); the
    # command line refused the options a series does not take (bricks, bounds, resume, --save-analytic)
    per_step = (
        "read",
        "force",
        "output",
        "example",
        "example_size",
        "checkpoint",
        "checkpoint_every",
        "max_device_memory",
        "max_host_memory",
    )
    kw = {k: v for k, v in cfg.to_kwargs().items() if k not in per_step}
    name = _series_name(output, variables)
    from warpgauss.core.files import check_writable
    from warpgauss.series.steps import series_chains

    total = 0
    for var, items, _ in series_chains(pattern, variables or None, read):  # the reports too, before any work
        total += len(items)
        for t in range(len(items)):
            check_writable(name.format(t=t, var=var or "") + ".report.json", force=force)
    status = None if as_json else err_console.status("starting", spinner="dots")
    if status is not None:
        status.start()
    workers, scheduler = cluster
    client = None
    if workers is not None or scheduler is not None:
        from warpgauss.encoding.scale.cluster import default_client

        client, where = default_client(workers, scheduler, kw.get("device"))
        if status is not None:
            status.console.print(f"series: {where}", highlight=False)

    rows: list[dict] = []

    def step(t: int, steps: int, m) -> None:
        rep = m.run_report
        rep["report"] = rep["output"] + ".report.json"
        atomic_write_bytes(rep["report"], json_text(rep).encode())
        rows.append(
            {
                "variable": rep["series"]["variable"],
                "step": rep["series"]["step"],
                "source": rep["series"]["source"],
                "warm_start": rep["series"]["warm_start"],
                "keyframe": "keyframe" in rep["series"],
                "n": m.n,
                "iterations": rep["refinement"].get("iterations", 0),
                "psnr_db": rep["psnr_db"],
                "seconds": rep.get("total_seconds"),
                "output": rep["output"],
            }
        )
        if status is not None:
            status.update(f"[bold]series[/] {len(rows)}/{total} timesteps encoded")

    args = dict(
        variables=variables or None,
        output_pattern=name,
        cold=cold,
        warm_iterations=warm_iterations,
        keyframe_drift=KEYFRAME_DRIFT_DB if keyframe_drift is None else keyframe_drift,
        force=force,
        read=read,
        **kw,
    )
    try:
        if client is None:  # one model at a time: a long series holds two models, not all
            for m in warpgauss.series.steps.iter_series(pattern, **args):
                step(m.run_report["series"]["step"], total, m)
        else:
            warpgauss.encode_series(pattern, on_step=step, client=client, **args)
    finally:
        if status is not None:
            status.stop()
        if client is not None:
            own = getattr(client, "cluster", None)
            client.close()
            if own is not None and scheduler is None:
                own.close()
    rows.sort(key=lambda r: (variables.index(r["variable"]) if r["variable"] in variables else 0, r["step"]))
    if as_json:
        print_json({"series": rows})
        return
    _print_series(rows)


def _series_name(output, variables: list[str]) -> str:
    """The models' path pattern: ``output`` (a folder: step.wgs inside it) with {var} where there
    are several variables and {t:03d} where the pattern holds no step."""
    out = output or Path("series.wgs")
    name = str(out / "step.wgs") if out.is_dir() else str(out)  # a folder: step_000.wgs ... inside it
    if len(variables) > 1 and "{var" not in name:
        name = str(Path(name).with_name(f"{Path(name).stem}_{{var}}{Path(name).suffix or '.wgs'}"))
    if "{t" not in name:
        p = Path(name)
        name = str(p.with_name(f"{p.stem}_{{t:03d}}{p.suffix or '.wgs'}"))
    return name


def _print_series(rows: list[dict]) -> None:
    """The series' table: a row per timestep and variable."""
    from rich.table import Table

    table = Table(show_edge=False, header_style="bold")
    for col in ("variable", "t", "start", "N", "iterations", "PSNR dB", "seconds", "model"):
        table.add_column(col, justify="left" if col in ("model", "variable") else "right")
    for r in rows:
        psnr = "-" if r["psnr_db"] is None else f"{r['psnr_db']:.2f}"
        secs = "-" if r["seconds"] is None else f"{r['seconds']:.1f}"
        table.add_row(
            r["variable"] or "-",
            str(r["step"]),
            "warm" if r["warm_start"] else ("cold (drift)" if r["keyframe"] else "cold"),
            f"{r['n']:,}",
            str(r["iterations"]),
            psnr,
            secs,
            r["output"],
        )
    out_console.print(table)
