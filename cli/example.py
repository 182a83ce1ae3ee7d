"""`warpgauss example NAME`: write a built-in example volume to a file."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

import typer

from .common import handle_errors, out_console


@handle_errors
def example(
    name: Annotated[str, typer.Argument(help="vortex, bubbles, turbulence or interface")],
    output: Annotated[
        Path | None,
        typer.Option(
            "-o",
            "--output",
            help="Output file (.raw/.npy/.vti/.h5/.nii.gz); default NAME_XxYxZ_float32.raw. With --steps: a name holding {t} "
            "(e.g. 'run/rho_{t:03d}_64x64x64_float32.raw') or an existing folder",
        ),
    ] = None,
    size: Annotated[str, typer.Option("--size", help="Edge length N (cube) or XxYxZ")] = "64",
    steps: Annotated[
        int | None,
        typer.Option("--steps", help="Write an evolving series of this many timesteps (the field turning about z), one file each"),
    ] = None,
    seed: Annotated[int, typer.Option(help="Generator seed")] = 0,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing output file")] = False,
) -> None:
    """Generate a built-in example volume (deterministic by seed) and write it; with --steps T a
    series of T timesteps that `warpgauss encode 'GLOB'` encodes with warm starts."""
    from warpgauss.core.files import check_writable
    from warpgauss.readers import write_volume
    from warpgauss.readers.synthetic import generate, raw_name

    shape = _parse_size(size)
    if steps is not None:
        _write_series(name, shape, steps, output, seed, force)
        return
    out = output or Path(raw_name(name, shape))
    check_writable(out, force=force)
    data = generate(name, shape, seed=seed)
    write_volume(out, data, force=force)
    out_console.print(f"wrote {out} ({shape[0]}x{shape[1]}x{shape[2]} float32, {data.nbytes} bytes)")


def _write_series(name: str, shape: tuple[int, int, int], steps: int, output: Path | None, seed: int, force: bool) -> None:
    """``steps`` files of :func:`warpgauss.readers.synthetic.generate_series`, every name checked before
    the first is generated."""
    from warpgauss.core.files import check_writable
    from warpgauss.errors import WarpgaussError
    from warpgauss.readers import write_volume
    from warpgauss.readers.synthetic import generate_series, raw_name

    if steps < 1:
        raise WarpgaussError(f"--steps must be a positive number of timesteps, got {steps}")
    stem, rest = raw_name(name, shape).split("_", 1)
    default = f"{stem}_{{t:03d}}_{rest}"  # vortex_000_64x64x64_float32.raw: the reader still finds the shape
    if output is None:
        pattern = default
    elif output.is_dir():
        pattern = str(output / default)
    elif "{t" in str(output):
        pattern = str(output)
    else:
        raise WarpgaussError(
            f"--steps writes one file a timestep: give -o a name holding {{t}} (e.g. {default}) or an existing folder, not {output}"
        )
    names = [pattern.format(t=t) for t in range(steps)]
    if len(set(names)) < steps:
        raise WarpgaussError(f"the output name {pattern!r} gives one name to several timesteps; use {{t}} in it")
    for n in names:
        check_writable(Path(n), force=force)
    for t, data in zip(range(steps), generate_series(name, shape, steps=steps, seed=seed)):
        write_volume(Path(names[t]), data, force=force)
    glob = re.sub(r"\{t(:[^}]*)?\}", "*", pattern)
    out_console.print(f"wrote {steps} timesteps {names[0]} .. {names[-1]} ({shape[0]}x{shape[1]}x{shape[2]} float32 each)")
    out_console.print(f"encode the series: warpgauss encode '{glob}' --budget 2000 -o '{stem}_{{t:03d}}.wgs'")


def _parse_size(size: str) -> tuple[int, int, int]:
    from .common import parse_shape

    if size.isdigit():
        n = int(size)
        return (n, n, n)
    shape = parse_shape(size, "--size")
    if shape is None:
        raise typer.BadParameter(f"--size must be N or XxYxZ, got {size!r}")
    return shape
