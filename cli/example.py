"""`warpgauss example NAME`: write a built-in example volume to a file."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console


@handle_errors
def example(
    name: Annotated[str, typer.Argument(help="vortex, bubbles, turbulence or interface")],
    output: Annotated[
        Path | None, typer.Option("-o", "--output", help="Output file (.raw/.npy/.vti/.h5); default NAME_XxYxZ_float32.raw")
    ] = None,
    size: Annotated[str, typer.Option("--size", help="Edge length N (cube) or XxYxZ")] = "64",
    seed: Annotated[int, typer.Option(help="Generator seed")] = 0,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing output file")] = False,
) -> None:
    """Generate a built-in example volume (deterministic by seed) and write it."""
    from warpgauss._fs import check_writable
    from warpgauss.io import write_volume
    from warpgauss.synthetic import generate, raw_name

    shape = _parse_size(size)
    out = output or Path(raw_name(name, shape))
    check_writable(out, force=force)
    data = generate(name, shape, seed=seed)
    write_volume(out, data, force=force)
    out_console.print(f"wrote {out} ({shape[0]}x{shape[1]}x{shape[2]} float32, {data.nbytes} bytes)")


def _parse_size(size: str) -> tuple[int, int, int]:
    from .common import parse_shape

    if size.isdigit():
        n = int(size)
        return (n, n, n)
    shape = parse_shape(size, "--size")
    if shape is None:
        raise typer.BadParameter(f"--size must be N or XxYxZ, got {size!r}")
    return shape
