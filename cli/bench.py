"""`warpgauss bench kernels`: microbenchmarks of every kernel of an iteration, decode and the dense reference."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console, parse_int_list

bench_app = typer.Typer(help="Benchmarks.", no_args_is_help=True, add_completion=False)


@bench_app.command("kernels")
@handle_errors
def kernels(
    size: Annotated[int | None, typer.Option(help="Field edge in voxels (default 1024 on CUDA, 48 on the CPU)")] = None,
    n: Annotated[str | None, typer.Option("--n", help="Primitive counts, e.g. 2000,20000,200000,650000,1400000")] = None,
    samples: Annotated[str | None, typer.Option(help="Samples per iteration, e.g. 3072,65536,262144,1048576")] = None,
    repeat: Annotated[int, typer.Option(help="Calls per timing")] = 10,
    dense_max_n: Annotated[
        int | None, typer.Option(help="Time the dense evaluator up to this N (default 650000 on CUDA, 2000 on the CPU)")
    ] = None,
    no_decode: Annotated[bool, typer.Option("--no-decode", help="Skip the full-grid decode timing")] = False,
    device: Annotated[str | None, typer.Option(help="Warp device, e.g. cuda:0 or cpu (default: CUDA if present)")] = None,
    json_out: Annotated[Path | None, typer.Option("--json-out", help="Also write the result as JSON here")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite --json-out")] = False,
) -> None:
    """Time binning, sampling, forward, backward, the fused update, a whole iteration (graph and
    plain launches), decode and the dense evaluator; print a table and optionally write JSON."""
    from warpgauss.core.files import atomic_write_bytes, check_writable
    from warpgauss.core.warp import resolve_device, warp
    from warpgauss.encoding.bench import CPU_DEFAULTS, GPU_DEFAULTS, KernelBenchConfig, format_table, run_kernel_bench
    from warpgauss.errors import WarpgaussError

    if json_out is not None:
        check_writable(json_out, force=force)
    if repeat < 1:
        raise WarpgaussError(f"--repeat must be >= 1, got {repeat}")
    dev = resolve_device(device)
    cuda = warp().get_device(dev).is_cuda
    d = GPU_DEFAULTS if cuda else CPU_DEFAULTS
    cfg = KernelBenchConfig(
        size=size or d["size"],
        ns=parse_int_list(n, "--n") or d["ns"],
        samples=parse_int_list(samples, "--samples") or d["samples"],
        repeat=repeat,
        dense_max_n=dense_max_n if dense_max_n is not None else (650_000 if cuda else 2_000),
        decode=not no_decode,
    )
    result = run_kernel_bench(cfg, dev, log=lambda s: out_console.print(s, soft_wrap=True, markup=False))
    out_console.print("\n" + format_table(result), soft_wrap=True, markup=False)
    if json_out is not None:
        atomic_write_bytes(json_out, (json.dumps(result, indent=2) + "\n").encode())
        out_console.print(f"wrote {json_out}", markup=False)
