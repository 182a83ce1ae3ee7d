"""The model and its file: :class:`Model` (:mod:`.model`), the self-describing ``.wgs`` container
(:mod:`.wgs`, SPEC section 6) and its payloads: ``coded`` (:mod:`.coded`, with its rate control in
:mod:`.ratefit`), ``compact96`` (:mod:`.compact`) and ``float32``; a bounded residual stored after
the Gaussians (:mod:`.residual`); the primitives as a ParaView point cloud (:mod:`.export`) and
refinement checkpoints (:mod:`.checkpoint`).

A new format version goes into :mod:`.wgs` (the prefix's version, the JSON header's ``encoding``)
with its payload in a module of its own here; the golden files under ``tests/golden`` pin the
bytes of the versions already written.
"""

from .model import Model
from .wgs import read_wgs, read_wgs_header, write_wgs

__all__ = ["Model", "read_wgs", "read_wgs_header", "write_wgs"]
