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
    from warpgauss.encoding.driver import load_field
    from warpgauss.encoding.stats import field_stats
    from warpgauss.errors import WarpgaussError
    from warpgauss.readers import ReadOptions

    if (input is None) == (example is None):
        raise WarpgaussError("give a volume file or --example NAME (one of them)")
    ladder = parse_int_list(budgets, "--budgets")  # None: the default ladder, less files larger than the source
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
        soft_wrap=False,
    )
    out_console.print(
        f"occupancy {100 * res['occupancy']:.2f} %   gradient top-10 % {100 * res['grad_top10']:.1f} %   "
        f"S(1)/S(16) {'n/a' if res['s1_s16'] is None else format(res['s1_s16'], '.4f')}   N_max {res['n_max']:,}"
        + ("   (statistics sampled)" if res["sampled"] else ""),
        soft_wrap=False,
    )
    _print_table(res)
    out_console.print(f"reading: {res['reading']}", soft_wrap=False)


def _size(n: float, top: float | None = None) -> str:
    """Bytes to three digits in the unit of ``top`` (or of ``n``): ``97.8 KiB``, ``15.5-29.4 KiB``."""
    unit = 0
    while (top or n) >= 1024 ** (unit + 1) and unit < 4:
        unit += 1
    name = ("B", "KiB", "MiB", "GiB", "TiB")[unit]
    text = "-".join(_three(v / 1024**unit) for v in ((n,) if top is None else (n, top)))
    return f"{text} {name}"


def _three(x: float) -> str:
    return f"{x:.3g}" if x < 1000 else f"{x:.0f}"


def _ratio(r: float) -> str:
    """A compression ratio in at most four characters and a k: ``0.46``, ``15.7``, ``288k``."""
    return f"{r:.2f}" if r < 10 else _three(r) if r < 1000 else f"{_three(r / 1000)}k"


def _print_table(res: dict) -> None:
    """The budget table in 80 columns (sizes with one decimal, a range in one unit), each ratio
    below 1 marked, the default budgets left out named."""
    from rich import box
    from rich.table import Table

    t = Table(box=box.SIMPLE_HEAD, show_edge=False, pad_edge=False, collapse_padding=True, header_style="bold")
    for col in ("N", "coded ~", "ratio ~", "compact", "ratio", "full", "ratio"):
        t.add_column(col, justify="right", no_wrap=True)
    for b in res["budgets"]:
        big = b["larger_than_source"]
        lo, hi = b["coded_compression_ratio_estimate"]
        t.add_row(
            f"{b['n']:,}" + ("*" if b["is_n_max"] else ""),
            _size(*b["coded_bytes_estimate"]),
            f"{_ratio(lo)}-{_ratio(hi)}x" + ("!" if "coded" in big else ""),
            _size(b["compact_bytes"]),
            f"{_ratio(b['compact_compression_ratio'])}x" + ("!" if "compact" in big else ""),
            _size(b["bytes"]),
            f"{_ratio(b['compression_ratio'])}x" + ("!" if "full" in big else ""),
        )
    if res["budgets"]:
        out_console.print(t)
    from warpgauss.encoding.driver.sizing import CODED_BPP_MEASURED

    note = "coded ~: the default format, at {:g}-{:g} B a Gaussian as measured".format(*CODED_BPP_MEASURED)
    out_console.print(note + ("; * N_max" if any(b["is_n_max"] for b in res["budgets"]) else ""), soft_wrap=False)
    if any(b["larger_than_source"] for b in res["budgets"]):
        out_console.print(f"! a file larger than the {_size(res['source_bytes'])} source: no compression", soft_wrap=False)
    if res["left_out"]:
        names = ", ".join(f"{r['n']:,}" + (" (N_max)" if r["is_n_max"] else "") for r in res["left_out"])
        out_console.print(
            f"left out: {names}, whose coded files could be larger than the {_size(res['source_bytes'])} source; "
            "--budgets N1,N2 tabulates any budget",
            soft_wrap=False,
        )
