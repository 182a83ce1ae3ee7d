"""The whole-volume encode's driver: its settings (:mod:`.config`, :mod:`.options`), stage P
(:mod:`.load`), sizing (:mod:`.sizing`), the staged run of one field, whose sequence of calls is
the paper's stage table (:mod:`.run`, rate control in :mod:`.replan`, checkpoints in
:mod:`.checkpoints`), the run report (:mod:`.report`) and budget ladders (:mod:`.ladder`).

A new stage is a function (or a module of its own under :mod:`warpgauss.encoding`) called from
:func:`.run.encode_field` inside ``timer.stage(code, title)``, with a row in the
report's stage table."""

from ...readers import ReadOptions
from .ladder import encode_ladder
from .load import load_field
from .options import DEFAULT_FORMAT, DEFAULT_RATIO, EncodeOptions, encoding_of, header_for, resolve_refine
from .report import finish_report
from .run import encode_field
from .sizing import resolve_budget, target_bytes

__all__ = [
    "DEFAULT_FORMAT",
    "DEFAULT_RATIO",
    "EncodeOptions",
    "ReadOptions",
    "encode_field",
    "encode_ladder",
    "encoding_of",
    "finish_report",
    "header_for",
    "load_field",
    "resolve_budget",
    "resolve_refine",
    "target_bytes",
]
