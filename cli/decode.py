"""`warpgauss decode`: model -> grid file (.vti for ParaView, .npy, .raw, .h5, .nii/.nii.gz)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from .common import err_console, handle_errors, out_console, parse_shape


@handle_errors
def decode(
    model: Annotated[Path, typer.Argument(help="Model file (.wgs)")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Grid file: .vti, .npy, .h5, .nii, .nii.gz or NAME_XxYxZ_DTYPE.raw")],
    shape: Annotated[str | None, typer.Option(help="Output grid XxYxZ (default: the encoded grid)")] = None,
    normalised: Annotated[bool, typer.Option("--normalised", help="Write [0, 1] values, not source units")] = False,
    device: Annotated[str | None, typer.Option(help="Warp device: cpu, cuda, cuda:N")] = None,
    force: Annotated[bool, typer.Option("--force", help="Overwrite an existing output file")] = False,
    residual: Annotated[
        bool | None,
        typer.Option(
            "--residual/--no-residual",
            help="Apply the model's bounded residual (default: where it has one and the grid is the encoded one); --no-residual: the Gaussians alone",
        ),
    ] = None,
) -> None:
    """Decode a model to a dense grid spanning the encoded extent, at any resolution."""
    from warpgauss._fs import check_writable
    from warpgauss.io import write_volume
    from warpgauss.model import Model

    check_writable(output, force=force)
    m = Model.load(model)
    grid = parse_shape(shape)
    _check_output(output, m, grid, residual)
    with err_console.status(f"decoding {m.n} Gaussians", spinner="dots"):
        info: dict = {}
        data = m.decode(shape_xyz=grid, device=device, normalised=normalised, info=info, residual=residual)
    write_volume(
        output,
        data,
        spacing=m.decoded_spacing(grid),
        origin=m.decoded_origin(grid),
        name=m.header.get("name", "value") or "value",
        force=force,
    )
    nz, ny, nx = data.shape
    if info.get("residual_applied"):
        note = f"; every voxel within {info['max_error']:.6g} of the source (the residual applied)"
    else:
        share = info["bricks_evaluated_share"]
        note = f"; {1 - share:.0%} of it (8^3 bricks no Gaussian reaches) written as 0 without evaluation" if share < 1.0 else ""
        if m.residual is not None:
            note += "; the Gaussians alone (the residual applies on the encoded grid, in source units)"
    out_console.print(f"wrote {output} ({nx}x{ny}x{nz} {data.dtype}){note}")


def _check_output(output: Path, m, grid, residual) -> None:
    """Refuse, before the decode, what the output cannot hold: a .raw name without its
    ``_XxYxZ_DTYPE`` tail (the readers could not take the file back; the one that fits is named),
    a NIfTI-1 file an axis longer than 32,767 voxels."""
    from warpgauss.errors import WarpgaussError
    from warpgauss.readers.common import parse_raw_name

    x, y, z = (int(v) for v in (grid or m.shape_xyz))
    if output.name.lower().endswith((".nii", ".nii.gz")):
        from warpgauss.readers.write import nifti_problem

        problem = nifti_problem((x, y, z))
        if problem is not None:
            raise WarpgaussError(problem)
    if output.suffix.lower() not in (".raw", ".bin") or parse_raw_name(output.name) is not None:
        return
    exact = grid is None or tuple(int(v) for v in grid) == tuple(m.shape_xyz)
    dtype = m.residual.info["dtype"] if (m.residual is not None and residual is not False and exact) else "float32"
    fix = output.with_name(f"{output.stem}_{x}x{y}x{z}_{dtype}{output.suffix}")
    raise WarpgaussError(f"{output.name} does not say the grid's shape and dtype, which a raw file cannot hold; name it {fix.name}")
