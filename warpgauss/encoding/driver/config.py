"""One encode configuration: :class:`EncodeConfig`, every setting of :func:`warpgauss.encode` in
frozen groups (the budget as one of N / ratio / bytes, format, seed, refinement, allocation,
reading, run control, bricks, error bound, start), built once from keyword arguments
(:meth:`EncodeConfig.from_kwargs`: ``warpgauss.encode``, ``encode_ladder``, ``encode_series``,
:class:`~warpgauss.Encoder` and the command line, whose ``--config`` file sets the same options)
and read by every path. :data:`FIELDS` is the one table from an argument's name to its place; a
test checks that every argument of ``warpgauss.encode`` has one and that it maps back.
:data:`OPTIONS` is the one table of how the command line offers the settings (``warpgauss
encode``'s options are made from it: panel, help, flags, type; the default is the setting's own),
so that a new setting is written once: a field of its group, a row of :data:`FIELDS` and one of
:data:`OPTIONS`.

What is not a setting stays beside it: progress callbacks, a Dask client (a connection) and an
Encoder's session (device buffers between calls).
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...errors import WarpgaussError
from ...format.residual import Bound
from ...readers import ReadOptions
from ..allocate import AllocationConfig
from ..refine import LossWeights, RefineConfig
from .options import EncodeOptions, resolve_refine, with_stop_rules
from .sizing import CODED_BPP_MEASURED, check_budget_options


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
    read_by_bricks: bool | None = None  # a file's boxes read one by one (None: where it does not fit the host limit)
    volume_on_host: bool | None = None  # the volume in pinned host memory, the model whole on the device (None: see entry.choose_path)


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
    devices: Any = None  # several devices refining one model ("cuda:0,cuda:1" or a list); the first is device
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
    "devices": (None, "devices"),
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
    "read_by_bricks": ("bricking", "read_by_bricks"),
    "volume_on_host": ("bricking", "volume_on_host"),
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


@dataclass(frozen=True)
class Option:
    """A setting as ``warpgauss encode`` offers it: the help panel and text, the flags (none: ``--``
    and the name with dashes), the command line's type, and its parameter name where that is not
    the setting's (``negate``: a flag that turns the setting off, ``--no-self-test``)."""

    panel: str
    help: str
    type: Any
    flags: tuple[str, ...] = ()
    param: str | None = None
    negate: bool = False


_BPP = "{:g}-{:g}".format(*CODED_BPP_MEASURED)  # a coded Gaussian's bytes, as --format's help quotes them

# The command line's options of the settings, in --help order within each panel. The key says
# where the value goes: an argument of warpgauss.encode (a row of FIELDS), or a part of one:
# read.NAME (ReadOptions), refine.NAME (RefineConfig), refine.weights.NAME (LossWeights).
OPTIONS: dict[str, Option] = {
    "example": Option("Input", "Encode a built-in example volume instead of a file", str | None),
    "example_size": Option("Input", "Edge length of the --example volume", int, flags=("--size",), param="size"),
    "read.stride": Option("Input", "Take every K-th voxel on each axis", int),
    "read.shape": Option("Input", "Raw files: XxYxZ when the name does not say", str | None),
    "read.dtype": Option("Input", "Raw files: uint8, int16, float32, ...", str | None),
    "read.endian": Option("Input", "Raw files: little (default) or big", str | None),
    "read.dataset": Option("Input", "HDF5: dataset path (default: first 3D dataset)", str | None),
    "read.fill_value": Option("Input", "Source value marking missing data (masked out)", float | None),
    "budget": Option("Budget and format", "Number of Gaussians N (exact)", int | None, flags=("--budget", "-n")),
    "ratio": Option("Budget and format", "Target compression ratio: a file of at most source bytes / RATIO; default 20", float | None),
    "file_bytes": Option(
        "Budget and format", "File size budget in bytes (header included), instead of --budget or --ratio", int | None, flags=("--bytes",)
    ),
    "compact": Option("Budget and format", "Write the compact 12-byte/primitive format", bool, flags=("--compact",)),
    "format": Option(
        "Budget and format",
        f"File format: coded (default: quantised + Zstandard, about {_BPP} B/Gaussian as measured on refined models, --ratio/--bytes budgets never exceeded, 99-100 % used), full (float32, 48 B) or compact (12 B)",
        str | None,
        flags=("--format",),
        param="fmt",
    ),
    "max_error": Option(
        "Error bound",
        "Every decoded voxel within this of the source (source units): a residual stored after the Gaussians; without a budget the Gaussians get 1/1000 of the source's bytes (8 KiB at least)",
        float | None,
    ),
    "max_error_rel": Option(
        "Error bound", "The bound as a share of the source's value range (e.g. 1e-3), instead of --max-error", float | None
    ),
    "residual_psnr": Option(
        "Error bound",
        "Instead of a bound: the full-grid PSNR (dB) the decode must reach, with the largest point-wise bound that reaches it",
        float | None,
        flags=("--psnr",),
        param="psnr",
    ),
    "seed": Option("Refinement", "Seed: same seed and device give the same model", int),
    "device": Option("Refinement", "Warp device: cpu, cuda, cuda:N (default: CUDA if present)", str | None),
    "devices": Option(
        "Refinement",
        "Refine one model on several GPUs of this machine, e.g. cuda:0,cuda:1 (the first is --device): each draws its share of the samples, the gradients combined every iteration",
        str | None,
    ),
    "iterations": Option("Refinement", "Refinement iterations (default 1500; 0: analytic model only)", int | None),
    "samples": Option(
        "Refinement",
        "Samples per iteration (default 3072, x ceil(N / 350000) for large budgets; on a GPU at least voxels / 128 as a power of two in 16384-131072; the report says what it chose)",
        int | None,
    ),
    "preset": Option(
        "Refinement",
        "paper (1500 x 3072 whatever N), fast (the default's sampling for 300 iterations) or quality (1500 x 12288)",
        str | None,
    ),
    "self_test": Option(
        "Refinement", "Skip the binned-vs-dense self-test", bool, flags=("--no-self-test",), param="no_self_test", negate=True
    ),
    "time_budget": Option(
        "Refinement",
        "Seconds the whole encode may take, reading to writing (the kernels' first compile not counted): refinement gets what the other stages leave, keeps >= 1,500 iterations where they fit and spends spare time on more samples (unless --samples is given)",
        float | None,
    ),
    "target_psnr": Option(
        "Refinement", "dB: skip refinement if the analytic model reaches it, else stop once a validation PSNR does", float | None
    ),
    "plateau_db": Option(
        "Refinement",
        "dB: stop refinement once the validation PSNR gains less than this over 300 iterations",
        float | None,
        flags=("--plateau",),
        param="plateau",
    ),
    "refine.lr": Option("Refinement", "Adam base learning rate (per-group multipliers apply)", float),
    "refine.weights.value_empty": Option(
        "Loss weights", "Loss weight: value term at empty samples (paper: 0)", float, param="w_value_empty"
    ),
    "refine.weights.density": Option("Loss weights", "Loss weight: density towards 1 where occupied", float, param="w_density"),
    "refine.weights.smooth": Option(
        "Loss weights",
        "Loss weight: smoothness at the start, annealed (default 0: off, no partner points; the paper: 0.01)",
        float,
        param="w_smooth",
    ),
    "refine.weights.smooth_final": Option("Loss weights", "Loss weight: smoothness at the end", float, param="w_smooth_final"),
    "refine.weights.anchor": Option("Loss weights", "Loss weight: anchor of a to V(mu)", float, param="w_anchor"),
    "refine.weights.aniso": Option("Loss weights", "Loss weight: anisotropy bound 3:1", float, param="w_aniso"),
    "refine.weights.cap": Option("Loss weights", "Loss weight: scale range", float, param="w_cap"),
    "bricks": Option(
        "Bricks and cluster",
        "Split the grid into bricks, e.g. 2x2x2 (x, y, z), the budget over them up front, each encoded on a Dask worker and merged into one model",
        str | None,
    ),
    "halo": Option(
        "Bricks and cluster",
        "Voxels of halo around each brick (default: the longest side / 32, at least 4); a brick caps sigma at halo / 2",
        int | None,
    ),
    "max_device_memory": Option(
        "Bricks and cluster",
        "Device memory an encode may use, e.g. 24GiB (default: 90 % of a GPU's free memory); a volume whose encode would not fit is split into bricks and read brick by brick",
        str | None,
    ),
    "max_host_memory": Option(
        "Bricks and cluster",
        "Host memory a brick may use, e.g. 16GiB (default: half of what is available); a volume that would not fit is split into bricks and read brick by brick",
        str | None,
    ),
    "read_by_bricks": Option(
        "Bricks and cluster",
        "A bricked file read brick by brick, one box in memory at a time (--read-by-bricks), or whole (--read-whole); default: whole where it fits --max-host-memory (then the seams are refit over the whole grid), else by bricks",
        bool | None,
        flags=("--read-by-bricks/--read-whole",),
    ),
    "volume_on_host": Option(
        "Bricks and cluster",
        "Keep the volume in pinned host memory, read by the GPU's kernels over the bus, and the model whole on the device (--volume-on-host), or the volume on the device (--volume-on-device); default: on the device, a file whose encode does not fit a GPU's --max-device-memory on the host where its model fits, else bricked",
        bool | None,
        flags=("--volume-on-host/--volume-on-device",),
    ),
    "checkpoint": Option("Run control", "Refinement checkpoint file; default OUTPUT.ckpt (deleted when the run ends)", Path | None),
    "checkpoint_every": Option("Run control", "Seconds between checkpoints (Ctrl-C also writes one)", float),
    "resume": Option("Run control", "Continue an interrupted run from its checkpoint (same input and options)", bool, flags=("--resume",)),
    "output": Option("Output", "Model file; default NAME.wgs", Path | None, flags=("-o", "--output")),
    "analytic_output": Option(
        "Output", "Also write the analytic (pre-refinement) model", Path | None, flags=("--save-analytic",), param="save_analytic"
    ),
    "full_eval": Option("Output", "PSNR on the full grid, not 500,000 samples", bool, flags=("--full-eval",)),
    "force": Option("Output", "Overwrite existing output files", bool, flags=("--force",)),
    "motion": Option(
        "Time series",
        "Move a warm start's Gaussians with the field's motion (block Lucas-Kanade) before refining",
        bool,
        flags=("--motion/--no-motion",),
    ),
}

_PARTS: dict[str, Any] = {"read": ReadOptions, "refine": RefineConfig, "refine.weights": LossWeights}


def option_default(where: str) -> Any:
    """The default of the setting at ``where`` (a key of :data:`OPTIONS`), as the command line
    shows it (a negated flag: False)."""
    if OPTIONS[where].negate:
        return False
    group, _, name = where.rpartition(".")
    return EncodeConfig().get(name) if not group else getattr(_PARTS[group](), name)


def config_from_options(values: dict[str, Any], read: dict[str, Any] | None = None) -> EncodeConfig:
    """The configuration of the command line's values (keyed by :data:`OPTIONS`' keys): parts
    gathered into their :class:`ReadOptions` and :class:`RefineConfig`, a negated flag turned
    back. ``read``: reader options the command line sets itself (a series' variable)."""
    from ...readers.common import parse_shape

    kwargs: dict[str, Any] = {}
    parts: dict[str, dict[str, Any]] = {g: {} for g in _PARTS}
    for where, value in values.items():
        group, _, name = where.rpartition(".")
        if OPTIONS[where].negate:
            value = not value
        if group:
            parts[group][name] = value
        else:
            kwargs[name] = value
    parts["read"]["shape"] = parse_shape(parts["read"].get("shape"))
    weights = LossWeights(**parts["refine.weights"])
    return EncodeConfig.from_kwargs(
        **kwargs, read=ReadOptions(**parts["read"], **(read or {})), refine=RefineConfig(**parts["refine"], weights=weights)
    )
