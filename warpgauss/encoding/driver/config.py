"""One encode configuration: :class:`EncodeConfig`, every setting of :func:`warpgauss.encode` in
frozen groups (the budget as one of N / ratio / bytes, format, seed, refinement, allocation,
reading, run control, bricks, error bound, start), built once from keyword arguments
(:meth:`EncodeConfig.from_kwargs`: ``warpgauss.encode``, ``encode_ladder``, ``encode_series``,
:class:`~warpgauss.Encoder` and the command line, whose ``--config`` file sets the same options)
and read by every path. :data:`FIELDS` is the one table from an argument's name to its place; a
test checks that every argument of ``warpgauss.encode`` has one and that it maps back.

What is not a setting stays beside it: progress callbacks, a Dask client (a connection) and an
Encoder's session (device buffers between calls).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Any

from ...errors import WarpgaussError
from ...format.residual import Bound
from ...readers import ReadOptions
from ..allocate import AllocationConfig
from ..refine import RefineConfig
from .options import EncodeOptions, resolve_refine, with_stop_rules
from .sizing import check_budget_options


@dataclass(frozen=True)
class Budget:
    """The budget: N primitives, a compression ratio or a file size in bytes (at most one; none:
    the default ratio)."""

    n: int | None = None
    ratio: float | None = None
    bytes: int | None = None

    def check(self) -> None:
        check_budget_options(self.n, self.ratio, self.bytes)

    @property
    def given(self) -> bool:
        return any(v is not None for v in (self.n, self.ratio, self.bytes))


@dataclass(frozen=True)
class Refinement:
    """How refinement runs: a preset overridden by explicit iterations and samples, the learning
    rates and weights (``refine``), stop rules, the self-test and a time budget."""

    preset: str | None = None
    iterations: int | None = None
    samples: int | None = None
    refine: RefineConfig | None = None
    target_psnr: float | None = None
    plateau_db: float | None = None
    self_test: bool = True
    time_budget: float | None = None

    def resolved(self) -> RefineConfig:
        """The refinement settings these give (refused in one line where they cannot be used)."""
        if self.time_budget is not None and not self.time_budget > 0:
            raise WarpgaussError(f"--time-budget must be a positive number of seconds, got {self.time_budget}")
        return with_stop_rules(resolve_refine(self.refine, self.preset, self.iterations, self.samples), self.target_psnr, self.plateau_db)


@dataclass(frozen=True)
class Reading:
    """Where the volume comes from besides the source argument: reader options, or an example."""

    read: ReadOptions | None = None
    example: str | None = None
    example_size: int | tuple[int, int, int] = 64

    @property
    def stride(self) -> int:
        return (self.read or ReadOptions()).stride


@dataclass(frozen=True)
class RunControl:
    """Checkpoints, evaluation and outputs."""

    checkpoint: str | os.PathLike | None = None
    checkpoint_every: float = 60.0
    resume: bool = False
    evaluate: bool = True
    full_eval: bool = False
    output: str | os.PathLike | None = None
    force: bool = False
    analytic_output: str | os.PathLike | None = None


@dataclass(frozen=True)
class Bricking:
    """Bricks (given, or chosen from the memory limits) and their halo."""

    bricks: Any = None
    halo: int | None = None
    max_device_memory: int | str | None = None
    max_host_memory: int | str | None = None


@dataclass(frozen=True)
class Start:
    """Where refinement starts: the analytic allocation, or a previous timestep's model."""

    warm_start: Any = None
    motion: bool = True


@dataclass(frozen=True)
class EncodeConfig:
    """Every setting of one encode (see the module docstring)."""

    budget: Budget = field(default_factory=Budget)
    format: str | None = None
    compact: bool = False
    seed: int = 0
    device: str | None = None
    refinement: Refinement = field(default_factory=Refinement)
    allocation: AllocationConfig | None = None
    reading: Reading = field(default_factory=Reading)
    run: RunControl = field(default_factory=RunControl)
    bricking: Bricking = field(default_factory=Bricking)
    bound: Bound = field(default_factory=Bound)
    start: Start = field(default_factory=Start)

    @classmethod
    def from_kwargs(cls, **kwargs: Any) -> EncodeConfig:
        """The configuration of ``warpgauss.encode``'s keyword arguments (an unknown name is
        refused in one line); what is not given keeps its default."""
        unknown = sorted(set(kwargs) - set(FIELDS))
        if unknown:
            raise WarpgaussError(
                f"unknown encode option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}; the options are warpgauss.encode's keyword arguments"
            )
        groups: dict[str, dict[str, Any]] = {}
        top: dict[str, Any] = {}
        for name, value in kwargs.items():
            group, attr = FIELDS[name]
            if group is None:
                top[attr] = value
            else:
                groups.setdefault(group, {})[attr] = value
        made = {g: _GROUPS[g](**values) for g, values in groups.items()}
        return cls(**top, **made)

    def to_kwargs(self, every: bool = False) -> dict[str, Any]:
        """``warpgauss.encode``'s keyword arguments for this configuration: those that differ
        from the default (``every``: all of them). ``from_kwargs(**c.to_kwargs()) == c``."""
        default = EncodeConfig()
        out = {}
        for name in FIELDS:
            value = self.get(name)
            if every or not _same(value, default.get(name)):
                out[name] = value
        return out

    def get(self, name: str) -> Any:
        """The value of ``warpgauss.encode``'s argument ``name``."""
        group, attr = FIELDS[name]
        return getattr(self if group is None else getattr(self, group), attr)

    def replace(self, **kwargs: Any) -> EncodeConfig:
        """A copy with some of ``warpgauss.encode``'s arguments changed."""
        return EncodeConfig.from_kwargs(**{**self.to_kwargs(), **kwargs})

    def options(self, refine: RefineConfig, **overrides: Any) -> EncodeOptions:
        """The :class:`EncodeOptions` an encode of this configuration runs with (``refine``: the
        resolved refinement settings; ``overrides``: fields that a path sets itself, such as a
        ladder's N)."""
        opts = EncodeOptions(
            self.budget.n,
            self.budget.ratio,
            self.seed,
            self.compact,
            self.allocation or AllocationConfig(),
            stride=self.reading.stride,
            refine=refine,
            self_test=self.refinement.self_test,
            time_budget=self.refinement.time_budget,
            checkpoint=self.run.checkpoint,
            checkpoint_every=self.run.checkpoint_every,
            resume=self.run.resume,
            format=self.format,
            bytes=self.budget.bytes,
            motion=self.start.motion,
        )
        return dataclasses.replace(opts, **overrides) if overrides else opts


_GROUPS: dict[str, Any] = {
    "budget": Budget,
    "refinement": Refinement,
    "reading": Reading,
    "run": RunControl,
    "bricking": Bricking,
    "bound": Bound,
    "start": Start,
}

# warpgauss.encode's argument -> (group of EncodeConfig or None for a top-level field, attribute)
FIELDS: dict[str, tuple[str | None, str]] = {
    "budget": ("budget", "n"),
    "ratio": ("budget", "ratio"),
    "file_bytes": ("budget", "bytes"),
    "format": (None, "format"),
    "compact": (None, "compact"),
    "seed": (None, "seed"),
    "device": (None, "device"),
    "preset": ("refinement", "preset"),
    "iterations": ("refinement", "iterations"),
    "samples": ("refinement", "samples"),
    "refine": ("refinement", "refine"),
    "target_psnr": ("refinement", "target_psnr"),
    "plateau_db": ("refinement", "plateau_db"),
    "self_test": ("refinement", "self_test"),
    "time_budget": ("refinement", "time_budget"),
    "allocation": (None, "allocation"),
    "read": ("reading", "read"),
    "example": ("reading", "example"),
    "example_size": ("reading", "example_size"),
    "checkpoint": ("run", "checkpoint"),
    "checkpoint_every": ("run", "checkpoint_every"),
    "resume": ("run", "resume"),
    "evaluate": ("run", "evaluate"),
    "full_eval": ("run", "full_eval"),
    "output": ("run", "output"),
    "force": ("run", "force"),
    "analytic_output": ("run", "analytic_output"),
    "bricks": ("bricking", "bricks"),
    "halo": ("bricking", "halo"),
    "max_device_memory": ("bricking", "max_device_memory"),
    "max_host_memory": ("bricking", "max_host_memory"),
    "max_error": ("bound", "max_error"),
    "max_error_rel": ("bound", "max_error_rel"),
    "residual_psnr": ("bound", "psnr"),
    "warm_start": ("start", "warm_start"),
    "motion": ("start", "motion"),
}

# warpgauss.encode's arguments that are not settings: callbacks, a connection, an Encoder's state
NOT_SETTINGS = ("source", "on_stage", "on_stats", "on_progress", "on_bricks", "client", "session", "progress")


def _same(a: Any, b: Any) -> bool:
    """Equality that an array (a warm start's parameters) or a model does not break."""
    if a is b:
        return True
    try:
        return bool(a == b)
    except (ValueError, TypeError):
        return False


def config_of(names: dict[str, Any]) -> EncodeConfig:
    """The configuration of a function's arguments (``locals()`` of ``warpgauss.encode`` or of a
    path that takes some of its arguments): the names in :data:`FIELDS`, the rest ignored."""
    return EncodeConfig.from_kwargs(**{k: v for k, v in names.items() if k in FIELDS})
