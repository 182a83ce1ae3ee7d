"""Relocation at fixed N (issue #53): primitives whose weight has fallen below
``RefineConfig.relocate_weight`` are moved to where the model's error is, as 3DGS-MCMC relocates
dead Gaussians, instead of growing N.

A relocation runs on the host between two iterations (a few times in a run, see
:meth:`warpgauss.encoding.refine.refiner.Refiner.relocating`): it reads the raw parameters, picks
the dead slots (lowest weight first, at most ``relocate_share`` of the trainable primitives),
draws a new centre for each from the error stratum's quota (a 4^3 brick with probability
proportional to its quota, as the sampler draws, then a uniform voxel inside it and a uniform
offset of up to half a voxel along each axis), and writes the slots back in place
(``array.assign``: the addresses a captured CUDA graph holds do not change). The caller re-bins
right after. The draws come from a numpy generator seeded by (seed, iteration) through
:func:`warpgauss.encoding.allocate.rng_stream` with :data:`RELOCATE_SALT`, so the same seed on
the same device gives the same model.
"""

from __future__ import annotations

import math

import numpy as np

from ...field.analysis import DeviceVolume
from ...field.device import DeviceValues
from ..allocate import rng_stream
from .draw import Sampler
from .state import Primitives

RELOCATE_SALT = 53_017  # keeps relocation's RNG streams apart from the sampler's (SAMPLER_SALT) and the end estimate's


class Relocator:
    """Moves dead primitives of a :class:`.state.Primitives` to where the sampler's error quota is.

    Args:
        state: The primitives under training (slot order).
        sampler: The sampler whose error stratum (``err_cum``, ``bricks``) says where the error is.
        dv: The normalised field on the device (a new primitive's value is its voxel's).
        seed: The refiner's seed.
        weight: A primitive is dead when its weight sigmoid(logit) is below this.
        share: At most ceil(share x trainable primitives) are moved per relocation.
    """

    def __init__(self, state: Primitives, sampler: Sampler, dv: DeviceVolume, seed: int, weight: float, share: float):
        self.state, self.sampler, self.dv, self.seed = state, sampler, dv, int(seed)
        self.weight, self.share = float(weight), float(share)

    def quota(self) -> np.ndarray | None:
        """Inclusive prefix sums of the error stratum's per-brick quota (host copy), or None where
        there is no quota to draw from (no error stratum, none drawn, or no error recorded yet)."""
        smp = self.sampler
        if smp.error_share <= 0 or smp.m_err <= 0:
            return None
        cum = smp.err_cum.numpy().astype(np.int64)
        return cum if cum.size and cum[-1] > 0 else None

    def dead_slots(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(slots to move, slots alive) for raw parameters ``raw`` (N, 12) in slot order: the
        trainable slots whose weight is below the threshold, lowest weight first (ties by model
        index), at most ceil(share x trainable) of them; and the trainable slots not dead."""
        s = self.state
        ids = s.ids.numpy().astype(np.int64)
        trainable = ids < s.n_train  # frozen neighbours and silenced primitives stay where they are
        logit = raw[:, 11].astype(np.float64)
        dead = trainable & (logit < math.log(self.weight / (1.0 - self.weight)))  # sigmoid(logit) < weight
        slots = np.flatnonzero(dead)
        most = math.ceil(self.share * s.n_train)
        slots = slots[np.lexsort((ids[slots], logit[slots]))][:most]
        return slots[np.argsort(ids[slots], kind="stable")], np.flatnonzero(trainable & ~dead)

    def centres(self, cum: np.ndarray, k: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``k`` new centres (x, y, z) in voxels and their voxels (x, y, z indices), drawn from
        the quota prefix sums ``cum``: a brick by its quota, a uniform voxel inside it (inside the
        grid), a uniform offset in [-0.5, 0.5) voxels along each axis, clipped to the grid."""
        from ...kernels.sampling import BRICK

        nz, ny, nx = self.dv.values.shape
        brick = np.searchsorted(cum, rng.integers(0, int(cum[-1]), k), side="right")  # first inclusive sum > r
        bk, bj, bi = np.unravel_index(brick, self.sampler.bricks)
        origin = np.stack([bi, bj, bk], axis=1) * BRICK
        size = np.array([nx, ny, nz])
        voxel = origin + rng.integers(0, np.minimum(BRICK, size - origin))
        mu = np.clip(voxel + rng.uniform(-0.5, 0.5, (k, 3)), 0.0, size - 1.0)
        return mu, voxel

    def move(self, iteration: int) -> int | None:
        """Relocate the dead primitives now (see the module); the number moved, or None where
        the error stratum has no quota to draw from (nothing read back beyond it)."""
        cum = self.quota()
        if cum is None:
            return None
        s = self.state
        raw = s.raw.numpy().reshape(s.n, 12).copy()
        slots, alive = self.dead_slots(raw)
        if slots.size == 0:
            return 0
        rng = np.random.default_rng(rng_stream(self.seed, iteration, salt=RELOCATE_SALT))
        mu, voxel = self.centres(cum, slots.size, rng)
        # isotropic scale: the median smallest-axis log-sigma of the live primitives (the detail
        # the model resolves now), or scale_min without any; kept within the cap term's range
        log_s = float(np.median(raw[alive, 3:6].min(axis=1))) if alive.size else s.log_min
        log_s = min(max(log_s, s.log_min), s.log_cap)
        new = np.zeros((slots.size, 12), np.float64)
        new[:, 0:3] = mu
        new[:, 3:6] = log_s
        new[:, 9] = 1.0  # identity rotation: the quaternion is stored (x, y, z, w)
        nz, ny, nx = self.dv.values.shape
        linear = (voxel[:, 2].astype(np.int64) * ny + voxel[:, 1]) * nx + voxel[:, 0]
        new[:, 10] = np.nan_to_num(DeviceValues(self.dv.values).take_flat(linear))  # gathered on the device, not the volume copied
        new[:, 11] = 0.0  # weight 0.5
        raw[slots] = new
        s.raw.assign(raw)
        for moments in (s.m1, s.m2):  # a fresh start for Adam
            m = moments.numpy().reshape(s.n, 12).copy()
            m[slots] = 0.0
            moments.assign(m)
        reach = s.reach.numpy().copy()  # a deferred step's reach belongs to the old place
        reach[slots] = 0.0
        s.reach.assign(reach)
        return int(slots.size)
