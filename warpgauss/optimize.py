"""Stage S2, refinement: the names of :mod:`warpgauss.refine` under their earlier home.

The refiner is a package of one module per stage of an iteration (see :mod:`warpgauss.refine`);
this module re-exports its public names so that ``from warpgauss.optimize import Refiner`` keeps
working. Constants are read where they are defined: patch ``warpgauss.refine.passes.MIN_CHUNK``,
not this module's copy.
"""

from .refine import *  # noqa: F403
from .refine import __all__  # noqa: F401
