"""Refinement settings: the loss weights, the schedule and optimiser options, and the presets."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass, field
from typing import Any

from ...errors import WarpgaussError

# quality: measured on the H100 (benchmarks/results/refine/quality_grid_h100.json, vortex and interface
# at 128^3 with 20,000 Gaussians, split-cell kernels): 1,500 x 12,288 gives +2.7 / +1.0 dB over
# the paper configuration in 7.1 / 4.7 s of refinement (paper: 2.2 / 1.7 s); doubling the samples
# again adds only 0.3-0.6 dB for twice the time, and doubling iterations instead gains the same.
# fast: the default's sampling (samples by the volume and N, voxel centres with importance weights,
# half the samples where the error is) for 300 iterations, the learning rate decaying to 0.3 of its
# start (the default's 0.1 decays too early for so short a run). The paper's 300 x 3,072 kept 4-71 %
# of the default's gain over the analytic model; this keeps 69-91 % (one H200, CR 100, share of the
# default's gain: vortex / interface 512^3 0.687 / 0.867, mni_icbm152 / mean_reg2mean / inia19
# 0.904 / 0.910 / 0.893, where a decay to 0.1 kept 0.666 / 0.844 / 0.886 / 0.902 / 0.892, to 0.2
# 0.686 / 0.865 / 0.903 / 0.910 / 0.894, to 0.5 0.655 / 0.833 / 0.904 / 0.904 / 0.873, and a
# learning rate of 0.012 / 0.016 0.672 / 0.835 / 0.908 / 0.912 / 0.885 and 0.676 / 0.776 / 0.912 /
# 0.907 / 0.870; benchmarks/results/speed/profile_fastlr*_h200.json). The paper's mode:
# --preset paper --iterations 300.
PRESETS: dict[str, dict[str, Any]] = {  # paper and quality: exactly these settings, no sample count raised for large budgets
    "paper": {
        "iterations": 1500,
        "samples": 3072,
        "auto_samples": False,
        "jitter": 0.5,
        "importance": False,
        "error_share": 0.0,
        "weights": {"smooth": 0.01, "smooth_final": 0.0001},  # the paper's smoothness, strong to weak
    },
    "fast": {"iterations": 300, "lr_decay": 0.3},
    "quality": {"iterations": 1500, "samples": 12288, "auto_samples": False},
}
AUTO_BATCH_PRIMITIVES = 350_000  # the default raises the samples by one batch per this many primitives
AUTO_MAX_BATCHES = 16
# on a CUDA device the default also draws one sample per this many voxels an iteration, as a power
# of two within these bounds (see RefineConfig.samples_rule for the measurements)
# (64 and 262,144 since the smoothness term is off by default, issue #52: as many points an
# iteration as the samples and their partners were, see RefineConfig.samples_rule)
GPU_VOXELS_PER_SAMPLE = 64
GPU_MIN_SAMPLES = 16_384
GPU_MAX_SAMPLES = 262_144
# RefineConfig's relocation settings (issue #53), left out of to_dict() while relocation is off
RELOCATE_FIELDS = ("relocate_every", "relocate_until", "relocate_weight", "relocate_share")


@dataclass
class LossWeights:
    """Weights of the loss terms (0 switches a term off).

    Measured (vortex, interface, bubbles at 40^3 with 1,200 Gaussians, 200-600 iterations, PSNR of
    the refined model): the density term costs 0.3-2.5 dB at 0.01 and more at 0.1, so it is kept
    only as a weak regulariser (0.001) against runaway overlap; smoothness at 1.0 costs 1-2 dB
    and off gains 0.2-0.5 dB, so it is off (0; the paper preset anneals it from 0.01 to 0.0001):
    its partner points were half of every iteration's pair work. One H200, the three MRIs of
    ``../shared/data`` at CR 10 / 30 / 100 / 300 / 1000, full-grid PSNR of the coded file, against
    0.01 -> 0.0001 (``benchmarks/results/accuracy/sweep_nosmooth_mri_h200.json``): mean_reg2mean
    +0.43 / +0.23 / +0.07 / +0.06 / +0.10 dB, mni_icbm152 +0.00 / +0.00 / -0.05 / +0.12 / +0.01,
    inia19 +1.60 / +0.67 / +0.20 / +0.08 / +0.03, encodes 10-30 % shorter; but the smooth vortex
    at 256^3 loses 0.92 / 0.60 dB at CR 30 / 100 (+0.02 at 300; interface -0.01 / +0.16 / -0.05;
    ``sweep_nosmooth_fields256_h200.json``), where the points, not the term, were what it used,
    so a GPU draws twice the samples instead (:meth:`RefineConfig.samples_rule`); the anchor is
    neutral at 0.001 and costs 0.7-3 dB at 0.1; ``value_empty`` 0 (the paper supervises occupied
    samples only) loses 0.7 dB on the interface field, because full-field PSNR counts empty space,
    so empty samples are fitted too (1). The anisotropy and cap terms are stiff penalties that act
    only outside their bounds.
    """

    value_empty: float = 1.0
    density: float = 0.001
    smooth: float = 0.0
    smooth_final: float = 0.0001
    anchor: float = 0.001
    aniso: float = 1.0
    cap: float = 1.0


@dataclass
class RefineConfig:
    """Refinement schedule and optimiser settings.

    The base learning rate is the paper's 8e-3; each parameter group multiplies it and the rate
    decays geometrically to ``lr_decay`` of its start by the last iteration. Measured against a
    flat 8e-3 for every group (same fields as :class:`LossWeights`, 600 iterations): +3.7 dB
    vortex, +1.6 dB interface, +2.2 dB bubbles.

    Attributes:
        iterations: Adam steps (paper: 1,500; the "fast" preset: 300).
        samples: Samples per iteration (paper: 3,072), each with a smoothness partner.
        lr: Base learning rate (paper: 8e-3).
        lr_position, lr_scale, lr_rotation, lr_value, lr_weight: Per-group multipliers.
        lr_decay: Learning rate at the last iteration relative to the first (geometric decay).
        touch_ref: Sample-primitive contacts per primitive per iteration at and above which the
            full rates apply; below, rates scale by sqrt(contacts / touch_ref) (0 disables).
            When samples are few for N (3,072 samples for 1.4M primitives touch each one about
            0.4 times an iteration) every touch is a one-sample gradient that Adam turns into a
            full-size step. Measured on vortex 64^3 with 20,000 Gaussians and 128 samples (0.8
            contacts): full rates 37.7 -> 38.1 dB, 1/8 rate 45.9 dB, 1/4 45.5 dB; with 2,048
            samples (12.5 contacts) full rates reach 53.9 dB.
        replan_every: Iterations between re-planning the bin levels from the current radii.
        rebin_every: Iterations between re-sorting the primitives into their bin cells.
        graph: Capture one iteration as a CUDA graph and replay it (CUDA devices only).
        auto_samples: Raise ``samples`` for large budgets: one batch of ``samples`` per
            :data:`AUTO_BATCH_PRIMITIVES` primitives (see :meth:`for_budget`); off in the named
            presets and when samples were set explicitly.
        uniform_support: Draw the uniform 25 % of the samples over the model's support (the 4^3
            bricks some primitive's 5-sigma box, widened by 2 voxels, reaches, re-marked at every
            re-bin) rather than the whole grid; outside every 5-sigma box a sample scores exactly 0
            with no gradient.
        budget_samples: In time-budget mode, spend time the schedule does not need on more
            samples per iteration (see :meth:`Refiner.run`); off when samples were set explicitly.
        budget_min_iterations: Iterations a time budget secures before it raises the samples.
        target_psnr: Stop once the validation PSNR (see :meth:`Refiner.set_validation`),
            checked every ``check_every`` iterations, reaches this many dB.
        plateau_db: Stop once the validation PSNR gained less than this over the last
            ``plateau_window`` iterations.
        partner_distance: Range of the partner offset in voxels.
        jitter: Largest offset of a training sample from its voxel centre along each axis, in
            voxels; its target is the trilinear interpolation there. The paper's 0.5 trains on
            the trilinear interpolant of the grid, a blurred field, where the full-grid PSNR we
            report scores the voxel values: 0 (the default) samples the voxel centres and fits
            their values. Measured on an H100 (``benchmarks/results/accuracy/``, default
            settings, coded files, full-grid PSNR), voxel centres with importance weights
            against the paper's sampling: three head MRIs at CR 10 / 30 / 100 / 300 / 1000
            +2.20 / +1.09 / +0.34 / +0.52 / -0.10 dB (mean_reg2mean), +1.90 / +1.45 / +1.05 /
            +0.86 / +1.00 (mni_icbm152), +2.61 / +1.31 at CR 10 / 30 (inia19); the float32
            models of the same N +2.9 / +1.6 / +0.7 / +0.4 / -0.1 and +2.2 / +1.6 / +1.2 /
            +0.9 / +0.8 dB; vortex 256^3 at CR 30 / 300 +0.6 / -0.2 dB; the interface field at
            256^3, CR 30, ends training at 62.6 dB sample PSNR against the paper's 47.0. Centres
            without the weights lost 15 dB once (vortex, CR 30). Sharp edges (CPU, float32,
            ``sharp_cpu.json``): bubbles +16.2 dB, mni_icbm152 at stride 4 +2.4, but the frog
            label map (categorical, 96 % zeros) -1.2 dB at stride 4 and +1.65 at stride 6.
        importance: Weight each sample by the inverse of its voxel's probability to be drawn
            (see :mod:`warpgauss.kernels.sampling`), so that the value loss (and the sample PSNR
            the loss history reports) estimates the full-grid MSE rather than the strata's mix;
            the paper weights every sample alike (False).
        error_share: Share of the samples drawn where the model's error is (with ``importance``):
            a 4^3 brick by its summed RMS error, estimated from the samples' weighted squared
            errors since the start (decayed by ``error_decay`` at every re-bin), then one of its
            voxels uniformly; the other strata keep their proportions in the rest. Their
            probability joins the importance weights, so the loss still estimates the
            full-grid MSE. 0: none (the paper; every preset). Measured on an H200
            (``benchmarks/results/accuracy/sweep_*_err_h200.json``, coded files at CR 10-1000,
            0 -> 0.5): mni_icbm152 +0.40 to +5.48 dB, inia19 +0.32 to +4.42, mean_reg2mean
            +0.02 to +0.09, vortex 512^3 +0.09 to +0.23, interface 512^3 +5.40 at CR 100 (at CR
            300 -6.2 through the re-plan's cut, now capped: ``replan.REPLAN_MAX_CUT``); 0.75 was
            up to 0.5 dB better on the MRIs, not measured on the fields. Not drawn where its
            map would see under :data:`warpgauss.encoding.refine.draw.ERROR_MIN_SAMPLES_A_CELL` samples a
            cell (a GPU encode beyond about 1,400^3; the report's ``refinement.error_stratum``).
        error_decay: Weight of a brick's earlier error sums at each re-bin (every
            ``rebin_every`` iterations).
        cell_lists: The point-major forward pass reads, per level, the primitives listed in the
            point's cell (each primitive listed in every point cell its widened box reaches, built
            at each re-bin) instead of walking the 3^3 neighbour bin cells of every level: the
            same pairs, a fifth to a tenth of the candidates (issue #52).
        split_cells: Forward pass with one thread per (point, neighbour cell) instead of per
            point, the partial sums stored and added in a fixed order; None picks it on CUDA
            devices up to :data:`SPLIT_MAX_POINTS` points an iteration (where one thread per point
            leaves a GPU idle; above it the point-major pass is faster, see
            :func:`warpgauss.encoding.refine.passes.picks_split` for dense models) and never on the CPU
            (where it only adds work). Either way reruns are bit-identical. Above
            :data:`PARTIAL_MAX_ENTRIES` partials the point-major pass is used.
        quantise: Bit depths of the coded format (:data:`warpgauss.format.coded.CODED_BITS`) the model
            is stored with, or None. The run ends by moving every primitive onto the format's
            grids (so the model evaluated and returned is the one stored); from
            ``quantise_from`` x ``iterations`` on, evaluation reads the parameters on those
            grids while Adam steps the unquantised ones (straight-through).
        quantise_mode: "straight-through" (see ``quantise``) or "refit": at ``quantise_from``
            the centres, scales and rotations move onto their grids and stay, and the remaining
            iterations refit a and w to them. Measured (rate_distortion/coded_loss_mri_cpu.json): refit from 80 %
            recovers 1.2 of 2.1 dB on a 51 dB synthetic model at fixed grids, but loses 0.34 /
            0.30 dB on mni_icbm152 / mean_reg2mean where the single projection loses 0.10 / 0.28.
        quantise_from: Share of the iterations after which refinement is quantisation-aware.
            1.0 (the default) projects once, after the last iteration: measured on two head
            MRIs (600 iterations, CPU, ``benchmarks/results/rate_distortion/coded_loss_mri_cpu.json``), refining the
            last fifth straight-through lost 0.93 / 0.72 dB against the float model where the
            single projection lost 0.38 / 0.11 dB, and projecting at every re-bin of the last
            fifth lost 0.44 dB on the first.
        relocate_every: Iterations between relocations of dead primitives (0, the default: none;
            issue #53): at every such iteration before ``relocate_until`` x ``iterations``, the
            trainable primitives whose weight is below ``relocate_weight`` (the lowest first, at
            most ``relocate_share`` of them) restart where the error stratum's quota is (see
            :mod:`warpgauss.encoding.refine.relocate`), and the primitives are re-binned. Needs an
            error stratum (``error_share`` > 0 and drawn); without one nothing moves. Not measured yet.
        relocate_until: Share of the iterations after which no relocation happens.
        relocate_weight: A primitive is dead when its weight is below this.
        relocate_share: At most this share of the trainable primitives moves per relocation.
    """

    iterations: int = 1500
    samples: int = 3072
    lr: float = 8e-3
    lr_position: float = 7.5
    lr_scale: float = 5.625
    lr_rotation: float = 5.625
    lr_value: float = 3.75
    lr_weight: float = 3.75
    lr_decay: float = 0.1
    touch_ref: float = 12.0
    beta1: float = 0.9
    beta2: float = 0.999
    eps: float = 1e-15
    replan_every: int = 100
    rebin_every: int = 10
    graph: bool = True
    partner_distance: tuple[float, float] = (0.5, 1.5)
    jitter: float = 0.0
    importance: bool = True
    error_share: float = 0.5
    error_decay: float = 0.7
    split_cells: bool | None = None
    cell_lists: bool = True
    budget_samples: bool = True
    auto_samples: bool = True
    uniform_support: bool = True
    budget_min_iterations: int = 1500
    target_psnr: float | None = None
    plateau_db: float | None = None
    check_every: int = 100
    plateau_window: int = 300
    quantise: dict | None = None
    quantise_from: float = 1.0
    quantise_mode: str = "straight-through"
    relocate_every: int = 0
    relocate_until: float = 0.5
    relocate_weight: float = 0.02
    relocate_share: float = 0.05
    weights: LossWeights = field(default_factory=LossWeights)

    def to_dict(self) -> dict:
        """The settings as a dict (the model header's ``encoding.refinement``, the checkpoint
        fingerprint); without relocation (``relocate_every`` 0) its settings are left out, so that
        headers, and the budgets their size enters, are the bytes they were before it existed."""
        d = asdict(self)
        if not self.relocate_every:
            for name in RELOCATE_FIELDS:
                del d[name]
        return d

    def samples_rule(self, n: int, voxels: int | None = None, device: str | None = None) -> tuple[int, str]:
        """Samples per iteration for ``n`` primitives in a volume of ``voxels`` on ``device``, and why.

        With ``auto_samples`` (the default; off in the presets and when samples were given):
        ``samples`` x ceil(n / :data:`AUTO_BATCH_PRIMITIVES`) (at most :data:`AUTO_MAX_BATCHES`
        x), and on a CUDA device at least one sample per :data:`GPU_VOXELS_PER_SAMPLE` voxels,
        rounded to a power of two within [:data:`GPU_MIN_SAMPLES`, :data:`GPU_MAX_SAMPLES`].

        Measured on an H100 with 1.4M Gaussians (``benchmarks/results/tradeoff_*_h100.json``):
        1,500 x 3,072 samples touch each primitive about 0.25 times an iteration and score below
        128,000 Gaussians on smooth fields (vortex 1024^3: 53.4 against 59.6 dB); 4x the samples
        (12,288, what the primitive rule gives at 1.4M) reach 60.1 dB, +1.8 to +8.9 dB on the
        four example fields at 512^3 and 1024^3, for 1.5-2.0x the refinement time. The device
        rule (``benchmarks/results/refine/samples_sweep_*_h100.json``, three head MRIs of 4.4-11.5M voxels
        at ratio 100, coded): 3,072 -> 16,384 -> 65,536 samples gained +1.2 to +1.9 dB, then
        -0.3 to +0.6 dB, and 131,072 another 0.1-0.2 dB; refinement 1.9-4.0 s at 3,072 and
        4.6-10.0 s at 65,536. On the CPU (one thread runs a kernel) the primitive rule alone.
        Since the smoothness term is off by default (no partner points) the rule draws twice
        the samples it did (one per 64 voxels, up to 262,144): the points an iteration of
        before, which gained, against the term on at half as many (one H200, same runs,
        ``benchmarks/results/accuracy/sweep_nosmooth_*_h200.json``): mean_reg2mean CR 10 / 30 /
        100 / 300 / 1000 +1.39 / +0.32 / +0.40 / +0.23 / +0.30 dB, mni_icbm152 -0.45 (the rate
        control chose 110,170 Gaussians for 136,505) / +0.64 / +0.32 / +0.18 / +0.07, inia19 +3.77
        / +1.53 / +0.59 / +0.31 / +0.17, vortex 256^3 CR 30 / 100 / 300 +0.31 / -0.15 / +0.21,
        interface 256^3 +0.14 / +0.44 / +0.14, in about the same time; the term off at the old
        count was 10-45 % faster but lost 0.92 / 0.60 dB on the vortex.
        """
        if not self.auto_samples or self.iterations == 0:
            return self.samples, "as set" if not self.auto_samples else "no refinement"
        k = min(AUTO_MAX_BATCHES, max(1, -(-int(n) // AUTO_BATCH_PRIMITIVES)))
        s, why = (
            self.samples * k,
            (f"{self.samples:,} x {k} (one batch per {AUTO_BATCH_PRIMITIVES:,} primitives)" if k > 1 else f"{self.samples:,}"),
        )
        if voxels is not None and device is not None and str(device).startswith("cuda"):
            g = 1 << max(0, round(math.log2(max(1, int(voxels)) / GPU_VOXELS_PER_SAMPLE)))
            g = min(GPU_MAX_SAMPLES, max(GPU_MIN_SAMPLES, g))
            if g > s:
                s, why = (
                    g,
                    (
                        f"{g:,}: on a GPU one sample per {GPU_VOXELS_PER_SAMPLE} voxels ({int(voxels):,}), "
                        f"as a power of two within {GPU_MIN_SAMPLES:,}-{GPU_MAX_SAMPLES:,}"
                    ),
                )
        return s, why

    def for_budget(self, n: int, voxels: int | None = None, device: str | None = None) -> RefineConfig:
        """These settings with :meth:`samples_rule`'s samples per iteration."""
        s, _ = self.samples_rule(n, voxels, device)
        return self if s == self.samples else dataclasses.replace(self, samples=s)

    def validate(self) -> None:
        """Refuse settings that would diverge or fail late, naming the option."""

        def finite(x) -> bool:
            return isinstance(x, (int, float)) and math.isfinite(x)

        positive = ("lr", "lr_position", "lr_scale", "lr_rotation", "lr_value", "lr_weight", "lr_decay", "eps")
        for name in positive:
            v = getattr(self, name)
            if not (finite(v) and v > 0):
                raise WarpgaussError(f"{name} must be a positive finite number, got {v}")
        for name in ("beta1", "beta2"):
            v = getattr(self, name)
            if not (finite(v) and 0 <= v < 1):
                raise WarpgaussError(f"{name} must be in [0, 1), got {v}")
        for name in ("touch_ref",):
            v = getattr(self, name)
            if not (finite(v) and v >= 0):
                raise WarpgaussError(f"{name} must be >= 0, got {v}")
        for name in ("replan_every", "rebin_every", "check_every", "plateau_window", "budget_min_iterations"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise WarpgaussError(f"{name} must be a positive integer, got {v}")
        if not (finite(self.quantise_from) and 0 <= self.quantise_from <= 1):
            raise WarpgaussError(f"quantise_from must be in [0, 1], got {self.quantise_from}")
        if self.quantise_mode not in ("straight-through", "refit"):
            raise WarpgaussError(f"quantise_mode must be straight-through or refit, got {self.quantise_mode!r}")
        if self.quantise is not None:
            from ...format.coded import check_bits

            check_bits(self.quantise)
        if not (finite(self.error_share) and 0 <= self.error_share < 1):
            raise WarpgaussError(f"error_share must be in [0, 1), got {self.error_share}")
        if not (finite(self.error_decay) and 0 <= self.error_decay <= 1):
            raise WarpgaussError(f"error_decay must be in [0, 1], got {self.error_decay}")
        if not (finite(self.jitter) and 0 <= self.jitter <= 1):
            raise WarpgaussError(f"jitter must be in [0, 1] voxels, got {self.jitter}")
        if not (isinstance(self.relocate_every, int) and not isinstance(self.relocate_every, bool) and self.relocate_every >= 0):
            raise WarpgaussError(f"relocate_every must be an integer >= 0 (0: no relocation), got {self.relocate_every}")
        if not (finite(self.relocate_until) and 0 <= self.relocate_until <= 1):
            raise WarpgaussError(f"relocate_until must be in [0, 1], got {self.relocate_until}")
        if not (finite(self.relocate_weight) and 0 < self.relocate_weight < 1):
            raise WarpgaussError(f"relocate_weight must be in (0, 1), got {self.relocate_weight}")
        if not (finite(self.relocate_share) and 0 < self.relocate_share <= 1):
            raise WarpgaussError(f"relocate_share must be in (0, 1], got {self.relocate_share}")
        lo, hi = self.partner_distance
        if not (finite(lo) and finite(hi) and 0 <= lo <= hi):
            raise WarpgaussError(f"partner_distance must be 0 <= min <= max, got {self.partner_distance}")
        for name, v in asdict(self.weights).items():
            if not (finite(v) and v >= 0):
                raise WarpgaussError(f"loss weight {name} must be a finite number >= 0, got {v} (--w-{name.replace('_', '-')})")
