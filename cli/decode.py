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
    shape: Annotated[
        str | None, typer.Option(help="Output grid XxYxZ (default: the encoded grid; with --box, the box at its resolution)")
    ] = None,
    box: Annotated[
        str | None,
        typer.Option(
            help="Decode only this region x0:x1,y0:y1,z0:z1: bounds on voxel faces of the encoded grid (integer bounds hold "
            "voxels x0..x1-1, as a slice), fractional with --shape; --shape is then the region's output grid"
        ),
    ] = None,
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
    """Decode a model to a dense grid spanning the encoded extent (or a box of it), at any resolution."""
    from warpgauss.core.files import check_writable
    from warpgauss.field.region import box_shape, check_box, format_box, on_encoded_grid, parse_box
    from warpgauss.format.model import Model
    from warpgauss.readers import write_volume

    check_writable(output, force=force)
    grid = parse_shape(shape)
    region = None if box is None else parse_box(box)
    if region is not None:  # refused from the header alone, before the payload is read
        region = check_box(region, Model.load_header(model)["grid"]["shape_xyz"])
        grid = box_shape(region) if grid is None else grid
    m = Model.load(model)
    on_grid = on_encoded_grid(region, grid, m.shape_xyz)
    _check_output(output, m, grid, residual, on_grid)
    with err_console.status(f"decoding {m.n} Gaussians", spinner="dots"):
        info: dict = {}
        data = m.decode(shape_xyz=grid, box=region, device=device, normalised=normalised, info=info, residual=residual)
    write_volume(
        output,
        data,
        spacing=m.decoded_spacing(grid, region),
        origin=m.decoded_origin(grid, region),
        name=m.header.get("name", "value") or "value",
        force=force,
    )
    nz, ny, nx = data.shape
    note = "" if region is None else f" of the box {format_box(region)}"
    if info.get("residual_applied"):
        note += f"; every voxel within {info['max_error']:.6g} of the source (the residual applied)"
    else:
        share = info.get("bricks_evaluated_share")
        if share is not None and share < 1.0:
            note += f"; {1 - share:.0%} of it (8^3 bricks no Gaussian reaches) written as 0 without evaluation"
        if m.residual is not None:
            where = "a box of whole voxels at the encoded resolution" if region is not None else "the encoded grid"
            note += f"; the Gaussians alone (the residual applies on {where}, in source units)"
    out_console.print(f"wrote {output} ({nx}x{ny}x{nz} {data.dtype}){note}")


def _check_output(output: Path, m, grid, residual, on_grid: bool) -> None:
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
    dtype = m.residual.info["dtype"] if (m.residual is not None and residual is not False and on_grid) else "float32"
    fix = output.with_name(f"{output.stem}_{x}x{y}x{z}_{dtype}{output.suffix}")
    raise WarpgaussError(f"{output.name} does not say the grid's shape and dtype, which a raw file cannot hold; name it {fix.name}")
