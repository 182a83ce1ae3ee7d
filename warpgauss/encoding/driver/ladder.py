"""A budget ladder: one field encoded at several budgets, its device volume and statistics shared."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ...core.profiling import StageRecorder
from ...errors import WarpgaussError
from ...field.analysis import check_budget
from ...format.model import Model
from ...readers import ReadOptions
from ..allocate import AllocationConfig
from ..refine import RefineConfig
from .config import config_of
from .load import load_field
from .options import encoding_of, header_for
from .report import finish_report
from .run import encode_field
from .sizing import sizing_bpp


def encode_ladder(
    source: str | os.PathLike | np.ndarray | None = None,
    *,
    budgets: Sequence[int],
    output_pattern: str | None = None,
    force: bool = False,
    seed: int = 0,
    device: str | None = None,
    iterations: int | None = None,
    samples: int | None = None,
    preset: str | None = None,
    refine: RefineConfig | None = None,
    target_psnr: float | None = None,
    plateau_db: float | None = None,
    self_test: bool = True,
    compact: bool = False,
    format: str | None = None,
    example: str | None = None,
    example_size: int | tuple[int, int, int] = 64,
    read: ReadOptions | None = None,
    allocation: AllocationConfig | None = None,
    evaluate: bool = True,
    full_eval: bool = False,
    on_stage: Callable[[str, str], None] | None = None,
    on_progress: Callable[[int, int, dict], None] | None = None,
) -> list[Model]:
    """Encode one volume at several budgets, reading and analysing it once (the paper's ladders).

    Args:
        budgets: Primitive counts; all are checked against the seed limit before any encoding.
        evaluate: Run stage EV for each model (benchmarks that measure PSNR their own way skip it).
        output_pattern: If given, each model is written to ``output_pattern.format(n=N)``.

    The other arguments are those of :func:`encode`.

    Returns:
        One model per budget (ascending), each with its report; ``report["ladder"]`` says what
        was shared.
    """
    from ...core.files import check_writable

    cfg = config_of(locals())
    ladder = sorted({int(b) for b in budgets})
    if not ladder or ladder[0] < 1:
        raise WarpgaussError(f"--ladder needs positive budgets, got {list(budgets)}")
    paths: list[Path | None] = [None] * len(ladder)
    if output_pattern is not None:
        named = [Path(output_pattern.format(n=n)) for n in ladder]
        for p in named:
            check_writable(p, force=force)
        paths = list(named)
    refine = cfg.refinement.resolved()
    first = StageRecorder(on_stage=on_stage)
    with first.stage("P", "load and normalise"):
        f, info = load_field(source, read, example=example, example_size=example_size)
    load_seconds = first.seconds("P")
    from ...format.wgs import header_size

    probe = cfg.options(refine, budget=ladder[-1])
    enc = encoding_of(probe)
    check_budget(f, ladder[-1], header_size(header_for(f, probe), 1 << 40, encoding=enc), sizing_bpp(enc))
    cache: dict = {}
    models = []
    for i, (n, path) in enumerate(zip(ladder, paths)):
        timer = first if i == 0 else StageRecorder(on_stage=on_stage)
        opts = cfg.options(refine, budget=n, self_test=self_test and i == 0)
        model = encode_field(
            f,
            opts,
            device=device,
            timer=timer,
            input_info=info,
            evaluate=evaluate,
            full_eval=full_eval,
            on_progress=on_progress,
            cache=cache,
        )
        if i > 0:
            model.run_report["skipped"].insert(0, {"what": "P", "why": "volume loaded once for the ladder", "seconds_saved": load_seconds})
            if self_test:
                model.run_report["skipped"].append({"what": "self-test", "why": "run once for the ladder, with the first budget"})
        if path is not None:
            with timer.stage("S3", "export"):
                model.save(path, encoding=enc, force=force)
            model.run_report["output"] = str(path)
        finish_report(model, timer)
        model.run_report["ladder"] = {"budgets": ladder, "position": i, "shared": ["P", "S1a"] if i else []}
        models.append(model)
    return models
