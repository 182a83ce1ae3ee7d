"""Stage S4 of a whole-volume encode: a bounded residual (``--max-error``, ``--psnr``) coded
against the source's own values after the Gaussians, and what it refuses up front."""

from __future__ import annotations

import numpy as np

from ...errors import WarpgaussError
from ...field.device import is_device_array
from ...format.model import Model
from ...format.residual import Bound
from ...readers import ReadOptions


def check_bounded_request(source, read: ReadOptions | None, bricks, warm_start, session) -> None:
    """Refuse, before any work, what a bounded residual cannot go with."""
    if read is not None and read.stride > 1:
        raise WarpgaussError("--max-error bounds every source voxel; --stride drops voxels, so the two do not combine")
    if bricks is not None:
        raise WarpgaussError("--max-error does not combine with --bricks yet; encode the volume whole")
    if is_device_array(source):
        raise WarpgaussError("--max-error takes a file or a numpy array, not a device array")
    if warm_start is not None or session is not None:
        raise WarpgaussError("--max-error does not combine with a series or an Encoder yet; encode each volume on its own")


def attach_residual(model: Model, source, read, example, example_size, bound: Bound, device) -> None:
    """Stage S4: code the bounded residual of the (stored) model against the source's own values
    and attach it to the model; the report's ``residual`` says what it holds."""
    import time

    from ...format.interpolation import residual_device
    from ...format.residual import code_for_psnr, code_residual, prediction, verify
    from ...readers.lazy import valid_mask

    t0 = time.perf_counter()
    data, fill = raw_source(source, read, example, example_size)
    if tuple(reversed(data.shape)) != model.shape_xyz:
        raise WarpgaussError(f"internal: the source's shape {data.shape} is not the model grid {model.shape_xyz}")
    lo, hi = model.value_range
    valid = valid_mask(data, fill)
    masked = None if valid.all() else valid
    pred, fragile = prediction(model, device)
    passes = residual_device(device, data.size)
    t1 = time.perf_counter()
    if bound.psnr is not None:
        res, facts, check = code_for_psnr(data, masked, pred, fragile, bound.psnr, (lo, hi), fill_value=fill, device=passes)
    else:
        res, facts = code_residual(data, masked, pred, fragile, bound.absolute(lo, hi), (lo, hi), fill_value=fill, device=passes)
        t_check = time.perf_counter()
        check = verify(res, pred, data, valid, (lo, hi), passes)
        facts["seconds"]["verify"] = time.perf_counter() - t_check
    t2 = time.perf_counter()
    model.residual = res
    gauss = model.file_size(encoding=model.format or "coded") - res.nbytes
    model.run_report["residual"] = {
        **facts,
        "bound": res.info["bound"],
        "bound_rel": res.info["bound_rel"],
        "gaussian_bytes": gauss,
        "residual_bytes": res.nbytes,
        "file_bytes": gauss + res.nbytes,
        "compression_ratio": model.source_bytes / (gauss + res.nbytes),
        **check,
        "predict_seconds": t1 - t0,
        "code_seconds": t2 - t1,
    }


def raw_source(source, read: ReadOptions | None, example, example_size) -> tuple[np.ndarray, float | None]:
    """The source's own values (its dtype, in memory) and fill value, for a bounded residual."""
    from ...readers.timesteps import TimeStep

    read = read or ReadOptions()
    fill = read.fill_value
    if example is not None:
        from ...readers.synthetic import generate

        return generate(example, example_size, seed=0), fill
    if isinstance(source, np.ndarray):
        return source, fill
    if isinstance(source, TimeStep):
        return source.read(), fill if fill is not None else source.meta()[2]
    vol = read.read(source, lazy=False)
    if fill is None and getattr(vol, "fill_value", None) is not None:
        fill = vol.fill_value
    return np.asarray(vol.data), fill
