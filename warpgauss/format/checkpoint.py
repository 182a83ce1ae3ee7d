"""Refinement checkpoints: the whole training state between two steps, written atomically.

A checkpoint is an ``.npz`` archive (numpy arrays only: no pickle, loaded with
``allow_pickle=False``; zip CRCs catch damage) holding the slot-order training state of
:meth:`warpgauss.encoding.refine.Refiner.state_arrays` plus a JSON record: a fingerprint of the analytic model
and the options (so that a resume with another input or other settings is refused), the
iteration reached, and the refinement seconds of each session so far.
"""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from ..core.files import atomic_path
from ..errors import WarpgaussError

FORMAT = "warpgauss-checkpoint"
VERSION = 5  # 2: deferred-step reach; 3: the uniform stratum's support bricks; 4: the error stratum's sums; 5: cell lists' boxes
META = "__meta__"
MAX_META_BYTES = 1 << 24
ARRAYS = {  # name: (dtype, trailing shape) of every array a checkpoint must hold
    "raw": (np.float32, (12,)),
    "m1": (np.float32, (12,)),
    "m2": (np.float32, (12,)),
    "ids": (np.int32, ()),
    "bounds_lo": (np.float32, (3,)),
    "bounds_hi": (np.float32, (3,)),
    "bounds_cell": (np.float32, ()),
    "cell_start": (np.int32, ()),
    "cell_end": (np.int32, ()),
    "counts": (np.int32, ()),
    "reach": (np.float32, ()),
    "list_centre": (np.float32, (3,)),  # the box each slot is listed with in the forward pass's cell lists
    "list_half": (np.float32, (3,)),
    "support": (np.uint8, ()),  # support bricks of the uniform stratum as last marked (empty when unused)
    "errors_new": (np.int64, ()),  # the error stratum's per-brick sums since the last re-bin (empty when unused)
    "errors": (np.float32, ()),  # and its running sums as of the last re-bin
}


def fingerprint(analytic_params: np.ndarray, settings: dict) -> str:
    """Digest of the analytic model (input, budget, seed, allocation) and the refinement settings."""
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(analytic_params, np.float32).tobytes())
    h.update(json.dumps(settings, sort_keys=True, default=str).encode())
    return h.hexdigest()


def save(path: str | os.PathLike, arrays: dict, meta: dict) -> None:
    """Write a checkpoint atomically (temp file, fsync, rename)."""
    record = {"format": FORMAT, "version": VERSION, **meta}
    blob = np.frombuffer(json.dumps(record, default=float).encode(), np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            meta_arrays: dict[str, Any] = {META: blob}
            np.savez(fh, **arrays, **meta_arrays)
            fh.flush()
            os.fsync(fh.fileno())


def load(path: str | os.PathLike) -> tuple[dict, dict]:
    """Read and validate a checkpoint; raises :class:`WarpgaussError` on anything unexpected."""
    p = Path(path)
    if not p.is_file():
        raise WarpgaussError(f"no checkpoint at {p}; encode without --resume, or give --checkpoint PATH")
    bad = f"{p} is not a readable warpgauss checkpoint"
    try:
        with np.load(p, allow_pickle=False) as z:
            names = set(z.files)
            missing = (set(ARRAYS) | {META}) - names
            if missing:
                raise WarpgaussError(f"{bad} (missing {', '.join(sorted(missing))}); delete it and encode without --resume")
            if z[META].size > MAX_META_BYTES:
                raise WarpgaussError(f"{bad} (oversized record); delete it and encode without --resume")
            meta = json.loads(bytes(z[META]).decode())
            arrays = {k: z[k] for k in ARRAYS}
    except WarpgaussError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, UnicodeDecodeError) as e:
        raise WarpgaussError(f"{bad} ({type(e).__name__}: {str(e).strip() or 'damaged'}); delete it and encode without --resume") from e
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise WarpgaussError(f"{bad} (format or version differs); delete it and encode without --resume")
    n = arrays["raw"].shape[0] if arrays["raw"].ndim == 2 else -1
    for name, (dtype, tail) in ARRAYS.items():
        a = arrays[name]
        if a.dtype != dtype or a.shape[1:] != tail:
            raise WarpgaussError(f"{bad} (array {name} has dtype {a.dtype} and shape {a.shape}); delete it")
        if name not in ("cell_start", "cell_end", "counts", "support", "errors_new", "errors") and a.shape[0] != n:
            raise WarpgaussError(f"{bad} (array {name} holds {a.shape[0]} entries, not {n}); delete it")
    return arrays, meta
