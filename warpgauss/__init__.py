"""warpgauss: fixed-budget anisotropic Gaussian encoding of scientific scalar volumes.

The package imports Warp lazily: reading, validating and refusing a request costs no Warp start-up.
"""

from ._version import __version__
from .core.moved import install as _install_moved
from .encoding import encode, encode_ladder
from .errors import WarpgaussError
from .format.model import Model
from .render.renderers import render_image
from .series import Encoder, encode_series

#: Old import paths (the flat package before 0.2) -> where their names live now. They keep
#: working until 0.3, with a DeprecationWarning (see :mod:`warpgauss.core.moved`); a key ending
#: in ``.*`` carries a moved package's submodules.
MOVED: dict[str, tuple[str, ...]] = {
    f"{__name__}.{old}": tuple(f"{__name__}.{n}" for n in new)
    for old, new in {
        "_fs": ("core.files",),
        "_warp": ("core.warp",),
        "allocate": ("encoding.allocate",),
        "analysis": ("field.analysis",),
        "bench": ("encoding.bench",),
        "boxstats": ("field.boxstats",),
        "bricked": ("encoding.scale.bricks", "encoding.scale.schedule", "encoding.scale.seams"),
        "brickplan": ("encoding.scale.plan",),
        "checkpoint": ("format.checkpoint",),
        "cluster": ("encoding.scale.cluster",),
        "coded": ("format.coded",),
        "compact": ("format.compact",),
        "devicefield": ("field.device",),
        "driver": ("encoding.driver", "encoding.entry", "encoding.scale.driver"),
        "driver.*": ("encoding.driver",),
        "driver.bricked": ("encoding.scale.driver",),
        "driver.encode": ("encoding.entry",),
        "encoder": ("series.insitu",),
        "evaluate": ("field.evaluate",),
        "export": ("format.export",),
        "io": ("readers",),
        "lazy": ("readers.lazy",),
        "limits": ("core.limits",),
        "model": ("format.model",),
        "motion": ("encoding.motion",),
        "optimize": ("encoding.refine",),
        "profiling": ("core.profiling",),
        "ratefit": ("format.ratefit",),
        "raymarch": ("render.raymarch",),
        "refine": ("encoding.refine",),
        "refine.*": ("encoding.refine",),
        "region": ("field.region",),
        "residual": ("format.residual", "format.interpolation", "format.planes"),
        "serve": ("render.serve",),
        "splat": ("render.splat",),
        "stats": ("encoding.stats",),
        "synthetic": ("readers.synthetic",),
        "together": ("core.together",),
        "transfer": ("render.transfer",),
        "viewer": ("render.viewer",),
        "wgs": ("format.wgs",),
    }.items()
}
_install_moved(MOVED)


def psnr(model, volume, *, full: bool = False, device: str | None = None, fill_value: float | None = None) -> float:
    """PSNR (dB) of ``model`` against ``volume`` (a path or a 3D array), on the normalised field.

    The volume is normalised by its own finite min/max, as at encoding time. 500,000 sampled voxel
    centres with a fixed seed, or the full grid with ``full=True`` (SPEC section 7). ``model`` may
    also be a decoded grid of the volume's shape (an array): then every finite voxel of the volume
    counts, both normalised by the volume's min/max.
    """
    import numpy as np

    from .field.evaluate import evaluate_against, psnr_from_mse

    if isinstance(model, Model):
        return evaluate_against(model, volume, full=full, device=device, fill_value=fill_value)["psnr_db"]
    if not isinstance(model, np.ndarray):
        raise WarpgaussError(
            f"psnr takes a Model (warpgauss.Model.load(path) or warpgauss.encode(...)) or a decoded array, got {type(model).__name__}"
        )
    truth = volume if isinstance(volume, np.ndarray) else None
    if truth is None:
        from .readers import read_volume

        truth = read_volume(volume).data
    if model.shape != truth.shape:
        raise WarpgaussError(
            f"the grid's shape {model.shape} is not the volume's {truth.shape}; decode at the volume's shape to compare them"
        )
    t = np.asarray(truth, np.float64)
    valid = np.isfinite(t) if fill_value is None else np.isfinite(t) & (t != fill_value)
    if not valid.any():
        raise WarpgaussError("the volume has no finite voxel to compare against")
    lo, hi = float(t[valid].min()), float(t[valid].max())
    span = hi - lo if hi > lo else 1.0
    err = (np.asarray(model, np.float64)[valid] - t[valid]) / span
    return psnr_from_mse(float(np.mean(err * err)))


__all__ = ["Encoder", "Model", "WarpgaussError", "__version__", "encode", "encode_ladder", "encode_series", "psnr", "render_image"]
