"""Stage S2: fixed-budget refinement (closed-form gradients, Adam, stratified samples).

The count never changes: :class:`Refiner` owns the N primitives in the training parameterisation
(log-sigmas, unnormalised quaternion, weight logit) and each :meth:`Refiner.step` draws samples,
re-bins the primitives at times, evaluates the field, turns the loss into per-point gradients,
gathers them onto the primitives over the truncated pairs only, and takes one Adam step. Every
term of the loss (see :mod:`warpgauss.kernels.backward`) has a weight; 0 turns it off.

One module per stage of an iteration (see :mod:`.refiner` for the table): ``draw`` (samples),
``passes`` (forward and backward pair passes), ``update`` (Adam), ``bins`` (re-bin),
``schedule`` and ``stop`` (per-iteration scalars, time budgets, early stops), over the shared
training state of ``state``; ``config`` holds the settings, ``selftest`` the pre-run check.
"""

from .config import AUTO_BATCH_PRIMITIVES, AUTO_MAX_BATCHES, PRESETS, LossWeights, RefineConfig
from .draw import STRATA, stratum_counts
from .passes import MAX_CHUNKS, MIN_CHUNK, PARTIAL_MAX_ENTRIES, SPLIT_MAX_POINTS, chunk_capacity
from .refiner import SELF_TESTS, Refiner, load_kernels
from .schedule import BUDGET_PROBE, BUDGET_SAFETY, BUDGET_SAMPLE_STEPS, MAX_BUDGET_ITERATIONS, SAMPLER_SALT
from .selftest import self_test
from .stop import VALIDATION_POINTS

__all__ = [
    "AUTO_BATCH_PRIMITIVES",
    "AUTO_MAX_BATCHES",
    "BUDGET_PROBE",
    "BUDGET_SAFETY",
    "BUDGET_SAMPLE_STEPS",
    "MAX_BUDGET_ITERATIONS",
    "MAX_CHUNKS",
    "MIN_CHUNK",
    "PARTIAL_MAX_ENTRIES",
    "PRESETS",
    "SPLIT_MAX_POINTS",
    "SAMPLER_SALT",
    "SELF_TESTS",
    "STRATA",
    "VALIDATION_POINTS",
    "LossWeights",
    "RefineConfig",
    "Refiner",
    "chunk_capacity",
    "load_kernels",
    "self_test",
    "stratum_counts",
]
