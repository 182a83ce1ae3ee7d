"""The two fields an encode compares: the source, normalised and masked (stage P,
:mod:`.analysis`; on a device, :mod:`.device`; a box's statistics there, :mod:`.boxstats`), and
the Gaussians' truncated field (:mod:`.gaussians`), with the regions a model is asked for
(:mod:`.region`) and the PSNR between the two (stage EV, :mod:`.evaluate`).

    from warpgauss.field import GaussianField, normalise
"""

from ..core.moved import forward
from .analysis import Field, denormalise, normalise
from .evaluate import evaluate_against, evaluate_field, psnr_from_mse
from .gaussians import DECODE_SLAB_VOXELS, GaussianField, grid_points

__all__ = [
    "DECODE_SLAB_VOXELS",
    "Field",
    "GaussianField",
    "denormalise",
    "evaluate_against",
    "evaluate_field",
    "grid_points",
    "normalise",
    "psnr_from_mse",
]

# warpgauss.field was one module (now .gaussians): its other names still read, with a warning
__getattr__ = forward(__name__, f"{__name__}.gaussians")
