"""`warpgauss stats`: structure statistics, seed limit and a budget table, before encoding."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, human_bytes, out_console, parse_int_list, parse_shape, print_json


@handle_errors
def stats(
    input: Annotated[Path | None, typer.Argument(help="Volume file (any format encode reads)")] = None,
    example: Annotated[str | None, typer.Option(help="A built-in example volume instead of a file")] = None,
    size: Annotated[int, typer.Option(help="Edge length of the --example volume")] = 64,
    budgets: Annotated[str | None, typer.Option(help="Budgets to tabulate, e.g. 2000,20000,200000 (N_max is always added)")] = None,
    device: Annotated[str | None, typer.Option(help="Warp device: cpu, cuda, cuda:N (default: CUDA if present)")] = None,
    stride: Annotated[int, typer.Option(help="Take every K-th voxel on each axis")] = 1,
    shape: Annotated[str | None, typer.Option(help="Raw files: XxYxZ when the name does not say")] = None,
    dtype: Annotated[str | None, typer.Option(help="Raw files: uint8, int16, float32, ...")] = None,
    endian: Annotated[str | None, typer.Option(help="Raw files: little (default) or big")] = None,
    dataset: Annotated[str | None, typer.Option(help="HDF5: dataset path")] = None,
    variable: Annotated[str | None, typer.Option(help="netCDF: variable name")] = None,
    fill_value: Annotated[float | None, typer.Option(help="Source value marking missing data (masked out)")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print a JSON object")] = False,
) -> None:
    """Occupancy, gradient top-10 %, S(1)/S(16), the seed limit N_max and the bytes and compression
    ratio of a ladder of budgets (full precision and compact), with a one-line reading."""
    from warpgauss.driver import load_field
    from warpgauss.errors import WarpgaussError
    from warpgauss.io import ReadOptions
    from warpgauss.stats import DEFAULT_BUDGETS, field_stats

    if (input is None) == (example is None):
        raise WarpgaussError("give a volume file or --example NAME (one of them)")
    ladder = parse_int_list(budgets, "--budgets") or DEFAULT_BUDGETS
    t0 = time.perf_counter()
    f, _ = load_field(
        input, ReadOptions(parse_shape(shape), dtype, endian, dataset, variable, stride, fill_value), example=example, example_size=size
    )
    load_seconds = time.perf_counter() - t0
    res = field_stats(f, device, ladder)
    res["seconds_load"] = load_seconds
    if as_json:
        print_json(res)
        return
    out_console.print(
        f"[bold]{res['name']}[/] {'x'.join(map(str, res['shape_xyz']))} {res['source_dtype']} "
        f"({human_bytes(res['source_bytes'])}), values [{res['value_min']:g}, {res['value_max']:g}]"
        + (f", {res['masked_voxels']:,} masked voxels" if res["masked_voxels"] else ""),
        soft_wrap=True,
    )
    out_console.print(
        f"occupancy {100 * res['occupancy']:.2f} %   gradient top-10 % {100 * res['grad_top10']:.1f} %   "
        f"S(1)/S(16) {'n/a' if res['s1_s16'] is None else format(res['s1_s16'], '.4f')}   N_max {res['n_max']:,}"
        + ("   (statistics sampled)" if res["sampled"] else ""),
        soft_wrap=True,
    )
    from rich.table import Table

    t = Table(show_edge=False, header_style="bold")
    for col in ("N", "coded (default) ~", "ratio ~", "full", "ratio", "compact", "ratio"):
        t.add_column(col, justify="right")
    for b in res["budgets"]:
        t.add_row(
            f"{b['n']:,}" + (" (N_max)" if b["is_n_max"] else ""),
            "{}-{}".format(*(human_bytes(v) for v in b["coded_bytes_estimate"])),
            "{:.1f}-{:.1f}x".format(*b["coded_compression_ratio_estimate"]),
            human_bytes(b["bytes"]),
            f"{b['compression_ratio']:.2f}x",
            human_bytes(b["compact_bytes"]),
            f"{b['compact_compression_ratio']:.2f}x",
        )
    out_console.print(t)
    out_console.print(f"reading: {res['reading']}", soft_wrap=True)
