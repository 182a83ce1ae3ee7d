"""The encode driver: stage P (:mod:`.load`), sizing (:mod:`.sizing`), the staged run of one field
(:mod:`.run`, rate control in :mod:`.replan`, checkpoints in :mod:`.checkpoints`), the bricked
driver (:mod:`.bricked`), the entry point (:mod:`.encode`) and budget ladders (:mod:`.ladder`)."""

from ..io import ReadOptions
from .bricked import encode_bricked
from .encode import encode, finish_report
from .ladder import encode_ladder
from .load import load_field
from .options import DEFAULT_FORMAT, DEFAULT_RATIO, EncodeOptions, encoding_of, header_for, resolve_refine
from .run import encode_field
from .sizing import resolve_budget, target_bytes

__all__ = [
    "DEFAULT_FORMAT",
    "DEFAULT_RATIO",
    "EncodeOptions",
    "ReadOptions",
    "encode",
    "encode_bricked",
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
