"""The ``.wgs`` model file: a self-describing, checksummed container for N Gaussian primitives.

Layout (little-endian, SPEC section 6)::

    prefix (20 bytes)   magic b"WGAUSS\\x00\\x01" | format version u32 | JSON length L u32 | CRC32(JSON area) u32
    JSON area (L bytes) UTF-8 JSON object (sorted keys, no timestamp), padded with ASCII spaces so that
                        H = 20 + L is a multiple of HEADER_BLOCK (or exactly an explicit header size)
    payload             N x 12 float32 ("float32", 48 bytes per primitive)
                        or N x 3 uint32 ("compact96", 12 bytes per primitive)
                        or a Zstandard frame of quantised columns ("coded", its length in the
                        header's payload description; see :mod:`warpgauss.format.coded`)
    residual            optional: a bounded residual's Zstandard frames, described by the header's
                        ``residual`` entry (:mod:`warpgauss.format.residual`)

The format version is 1, or 2 for a file with a residual, or 3 for a file whose coded payload is in
layout 2 (:mod:`warpgauss.coded_keys`; with or without a residual, as its header says): a reader
refuses a version it predates ("upgrade warpgauss") rather than misread the payload, and reads
every earlier version.

A full-precision file is therefore exactly ``48 N + H`` bytes, and ``H`` is known before the
parameters exist (:func:`header_size` reserves room for the fields written last), so a budget can
be derived from a target compression ratio.

The module owns three header keys and overwrites whatever the caller put there:
``"n"``, ``"payload"`` (encoding, bytes per primitive, parameter layout, SHA-256 of the payload
bytes and, for ``compact96``, the ranges needed to dequantise) and ``"residual"`` (present only
with a residual). Everything else in the header is
the caller's and is written as given (it must be JSON-serialisable; numpy scalars and arrays are
converted).

``compact96`` packs each primitive into three little-endian uint32 words (96 bits), fields
laid out least-significant bit first in this order::

    bits   field
    3x13   centre, uniform over the per-axis bounding box of all centres
    3x7    log-scales, uniform over [min, max] of all log-scales
    2+3x6  quaternion, "smallest three": index of the largest |component| (made positive, since
           q and -q are one rotation), the other three over [-1/sqrt2, 1/sqrt2] on 63 levels
           (odd, so 0 is exact: axis-aligned orientations survive); renormalised on decode
    8      a, uniform over [min, max] of a
    8      w, uniform over [min, max] of w

Other values are rounded to the nearest of ``2**bits`` levels spanning their range (both ends
exact), so the absolute error is at most ``(hi - lo) / (2 * (2**bits - 1))``.

.. note::
   Why 13/7/6/8/8 and not 14 bits of centre and 6 of log-scale: measured with the float64
   reference field on ~4,400 rotated 3:1 primitives at a realistic spacing, each group quantised
   alone, log-scales at 6 bits were the largest error (66.6 dB against the exact model) while
   centres at 14 bits were far below it (88.9 dB in a 256^3 box). Moving one bit per axis from
   centre to log-scale raised the all-groups PSNR against the exact model by 1.8-5.4 dB (e.g.
   62.2 -> 65.4 dB smooth field, 52.1 -> 57.5 dB random values, 51.4 -> 55.8 dB low density)
   and stayed ahead in a 1024^3 box. Both are far above model PSNRs (20-45 dB), so the compact
   variant costs a fraction of a dB.

Reading validates everything (magic, version, lengths, CRC, JSON, sizes, SHA-256, finiteness) and
raises :class:`~warpgauss.errors.WarpgaussError` with a one-line message on any damage. No pickle.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
import zlib
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from ..core.files import atomic_write_bytes, check_writable
from ..errors import WarpgaussError
from .coded_keys import LAYOUT as CODED_KEYS_LAYOUT
from .compact import decode_compact, encode_compact, quant_dict
from .residual import Residual

MAGIC = b"WGAUSS\x00\x01"
FORMAT_VERSION = 1
RESIDUAL_VERSION = 2  # a file with a residual: a reader that predates residuals refuses it by its version
# a coded payload in layout 2 (centres as sorted Morton key gaps, warpgauss.coded_keys), with or
# without a residual (the header's "residual" entry says which): a reader that predates the layout
# refuses the file by its version rather than misreading the payload; every other file is written
# as version 1 or 2, as before
CODED_KEYS_VERSION = 3
VERSIONS = (FORMAT_VERSION, RESIDUAL_VERSION, CODED_KEYS_VERSION)
HEADER_BLOCK = 4096
PREFIX_SIZE = 20  # magic (8) + version (4) + JSON length (4) + CRC32 (4)
PREFIX = struct.Struct("<8sIII")

PARAM_NAMES: tuple[str, ...] = (
    "mu_x",
    "mu_y",
    "mu_z",
    "log_sx",
    "log_sy",
    "log_sz",
    "q_x",
    "q_y",
    "q_z",
    "q_w",
    "a",
    "w",
)

ENCODINGS = {"float32": 48, "compact96": 12, "coded": None}  # bytes per primitive; None: variable

# the widest repr of a float64 (sign, 17 digits, point, e-308): reserves room for any quant value
_FLOAT_PLACEHOLDER = -2.2250738585072014e-308
_N_PLACEHOLDER = 10**19  # wider than any N this format can hold on disk
_SHA_PLACEHOLDER = "0" * 64


# ------------------------------------------------------------------------------------------------
# header
# ------------------------------------------------------------------------------------------------
def _json_default(obj):
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (Path, os.PathLike)):
        return os.fspath(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _header_bytes(header: dict, n: int, payload_info: dict, residual_info: dict | None = None) -> bytes:
    """Canonical (sorted keys, compact, deterministic) UTF-8 JSON of ``header`` + the owned keys."""
    if not isinstance(header, dict):
        raise WarpgaussError(f"the model header must be a dict, got {type(header).__name__}")
    h = dict(header)
    h["n"] = int(n)
    h["payload"] = payload_info
    h.pop("residual", None)
    if residual_info is not None:
        h["residual"] = residual_info
    try:
        text = json.dumps(h, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False, default=_json_default)
        return text.encode("utf-8")
    except (TypeError, ValueError) as e:  # UnicodeEncodeError (lone surrogates) is a ValueError
        raise WarpgaussError(
            f"the model header cannot be stored as JSON ({e}); use str keys and finite numbers, strings, lists, dicts"
        ) from None


def _payload_info(encoding: str, sha256: str, quant: dict | None, payload_bytes: int | None = None) -> dict:
    info: dict[str, Any] = {
        "encoding": encoding,
        "bytes_per_primitive": ENCODINGS[encoding],
        "layout": list(PARAM_NAMES),
        "sha256": sha256,
    }
    if quant is not None:
        info["quant"] = quant
    if ENCODINGS[encoding] is None:
        info["payload_bytes"] = int(payload_bytes or 0)
    return info


def _coded_placeholder() -> dict:
    """A coded payload description with every number at its widest (for header sizes)."""
    from .coded import CODED_BITS, CODED_COLUMNS

    # layout 1's at its widest; layout 2's (widths in bits, a layout key, no raw size) is narrower
    return {"bits": {k: 24 for k in CODED_BITS}, "columns": [[-(1 << 52), 8]] * len(CODED_COLUMNS), "raw_bytes": _N_PLACEHOLDER}


def _round_up(nbytes: int, block: int) -> int:
    return -(-nbytes // block) * block


def header_size(header: dict, n: int, *, compact: bool = False, encoding: str | None = None) -> int:
    """Bytes ``H`` that the prefix plus the JSON area of a file with this header will take.

    Independent of the parameters' values and of ``n`` (the owned fields are measured at their
    widest: a 20-digit N, a 64-hex-digit SHA-256 and, for compact, the widest float repr for every
    quantisation range), so it can be computed before the budget is known; :func:`write_wgs`
    then writes exactly this many header bytes (for "coded", at most this many: its header is
    not padded to a block).

    Args:
        header: The caller's header dict (``"n"`` and ``"payload"`` are ignored and replaced).
        n: Number of primitives (only validated).
        compact: Size for the ``compact96`` payload (its header holds the quantisation ranges).
        encoding: "float32", "compact96" or "coded" (overrides ``compact``).

    Returns:
        ``H``, a multiple of :data:`HEADER_BLOCK`.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise WarpgaussError(f"the primitive count must be a non-negative integer, got {n!r}")
    return _reserved_size(header, resolve_encoding(compact, encoding))


FORMAT_ALIASES = {"full": "float32", "compact": "compact96"}  # the names the command line and the API take


def resolve_encoding(compact: bool, encoding: str | None) -> str:
    """The payload encoding of a format name or alias (:data:`FORMAT_ALIASES`), else of ``compact``."""
    if encoding is None:
        return "compact96" if compact else "float32"
    encoding = FORMAT_ALIASES.get(encoding, encoding)
    if encoding not in ENCODINGS:
        raise WarpgaussError(f"unknown model format {encoding!r}; use coded, full (float32) or compact (compact96)")
    return encoding


def _reserved_size(header: dict, encoding: str) -> int:
    x = _FLOAT_PLACEHOLDER
    quant = {"compact96": lambda: quant_dict([x] * 3, [x] * 3, x, x, x, x, x, x), "coded": _coded_placeholder}.get(encoding, lambda: None)()
    info = _payload_info(encoding, _SHA_PLACEHOLDER, quant, _N_PLACEHOLDER)
    body = _header_bytes(header, _N_PLACEHOLDER, info)
    if ENCODINGS[encoding] is None:  # a variable payload: no block padding (the header is part of the budget)
        return PREFIX_SIZE + len(body)
    return _round_up(PREFIX_SIZE + len(body), HEADER_BLOCK)


# ------------------------------------------------------------------------------------------------
# write / read
# ------------------------------------------------------------------------------------------------
def _validated_params(params) -> np.ndarray:
    p = np.asarray(params)
    if p.ndim != 2 or p.shape[1] != 12:
        raise WarpgaussError(f"model parameters must be an (N, 12) array, got shape {p.shape}")
    if p.shape[0] < 1:
        raise WarpgaussError("a model needs at least one primitive (N >= 1); got an empty parameter array")
    if not (np.issubdtype(p.dtype, np.floating) or np.issubdtype(p.dtype, np.integer)):
        raise WarpgaussError(f"model parameters must be real numbers, got dtype {p.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):  # out-of-range values become inf: reported below
        p = np.ascontiguousarray(p, dtype=np.float32)
    _check_finite(p, "cannot write the model")
    return p


def _check_finite(p: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(p)
    if bad.any():
        row, col = (int(i) for i in np.argwhere(bad)[0])
        raise WarpgaussError(
            f"{what}: {int(bad.sum())} non-finite parameter value(s), first at primitive {row} "
            f"({PARAM_NAMES[col]} = {p[row, col]}); the model is corrupt, re-encode it"
        )


def write_wgs(
    path: str | os.PathLike,
    params: np.ndarray,
    header: dict,
    *,
    compact: bool = False,
    encoding: str | None = None,
    header_size: int | None = None,
    force: bool = False,
    bits: dict | None = None,
    residual: Residual | None = None,
    layout: int | None = None,
) -> int:
    """Write a ``.wgs`` file atomically (nothing partial is ever left at ``path``).

    Args:
        path: Destination file.
        params: (N, 12) finite parameters, N >= 1 (stored as float32).
        header: The caller's header (grid, values, source, encoding, ...); ``"n"`` and
            ``"payload"`` are set here.
        compact: Store the ``compact96`` payload (12 bytes per primitive) instead of float32.
        bits: Coded bit depths (default :data:`warpgauss.format.coded.CODED_BITS`).
        encoding: "float32", "compact96" or "coded" (overrides ``compact``). A coded file stores
            the primitives in its own order (:func:`warpgauss.format.coded.coded_order`); read it back,
            or use :func:`warpgauss.format.coded.project_coded` and that order, for the stored model.
        header_size: Exact ``H`` (prefix + JSON area) to pad to; default: the smallest multiple of
            :data:`HEADER_BLOCK` that fits, which equals :func:`header_size` of this header.
        force: Replace an existing file.
        residual: A bounded residual (:mod:`warpgauss.format.residual`), stored after the primitives.
        layout: The coded payload's layout (:func:`warpgauss.format.coded.encode_coded`; None: the
            newest that holds the model; 1: as warpgauss wrote before format version 3).

    Returns:
        The file size in bytes: ``48 N + H`` (``12 N + H`` compact, payload + H coded), plus the
        residual's bytes.
    """
    dest = check_writable(path, force=force)
    encoding = resolve_encoding(compact, encoding)
    data = wgs_bytes(params, header, encoding=encoding, header_size=header_size, bits=bits, residual=residual, layout=layout)
    if encoding == "coded":  # no file is written that read_wgs would refuse
        from .coded import MIN_PAYLOAD_PER_PRIMITIVE

        n, payload = len(params), payload_size(data) - (0 if residual is None else residual.nbytes)
        if payload < MIN_PAYLOAD_PER_PRIMITIVE * n:
            raise WarpgaussError(
                f"these {n:,} primitives code to {payload / n:.3g} bytes each, below the {MIN_PAYLOAD_PER_PRIMITIVE:g} "
                "a coded file must hold to be read back (many identical primitives?); save them with --format full"
            )
    atomic_write_bytes(dest, data)
    return len(data)


def payload_size(data: bytes) -> int:
    """Payload bytes of a whole file's bytes (what follows the prefix and the header, a residual included)."""
    _, _, hlen, _ = PREFIX.unpack_from(data)
    return len(data) - PREFIX_SIZE - hlen


def wgs_bytes(
    params: np.ndarray,
    header: dict,
    *,
    encoding: str = "float32",
    header_size: int | None = None,
    bits: dict | None = None,
    residual: Residual | None = None,
    layout: int | None = None,
) -> bytes:
    """The bytes :func:`write_wgs` writes (for sizes and in-memory round trips); ``bits``: the
    coded bit depths (default :data:`warpgauss.format.coded.CODED_BITS`); ``residual``: appended after
    the primitives, described by the header's ``residual`` entry; ``layout``: the coded payload's
    layout (None: the newest that holds the model)."""
    p = _validated_params(params)
    n = p.shape[0]
    encoding = resolve_encoding(False, encoding)
    if encoding == "compact96":
        payload, quant = encode_compact(p)
    elif encoding == "coded":
        from .coded import encode_coded

        payload, quant, _ = encode_coded(p, bits, layout)
    else:
        payload, quant = p.astype("<f4", copy=False).tobytes(), None
    tail = b"" if residual is None else residual.payload()
    info = _payload_info(encoding, hashlib.sha256(payload).hexdigest(), quant, len(payload))
    body = _header_bytes(header, n, info, None if residual is None else residual.info)
    need = PREFIX_SIZE + len(body)
    if header_size is None and ENCODINGS[encoding] is None:
        H = need  # coded: the exact header, no padding (at most header_size(), its widest)
    elif header_size is None:
        # _reserved_size() measures the owned fields at their widest, so it is never below need
        H = max(_round_up(need, HEADER_BLOCK), _reserved_size(header, encoding))
    else:
        if isinstance(header_size, bool) or not isinstance(header_size, (int, np.integer)):
            raise WarpgaussError(f"header_size must be an integer number of bytes, got {header_size!r}")
        H = int(header_size)
        if H < need:
            raise WarpgaussError(
                f"the header needs {need} bytes but header_size={H} was requested; "
                f"pass header_size >= {need} (or none for the default {HEADER_BLOCK}-byte blocks)"
            )
    if H - PREFIX_SIZE > 0xFFFFFFFF:
        raise WarpgaussError(f"header of {H} bytes is too large for the format (max 4 GiB); shrink the header")
    area = body + b" " * (H - need)
    if quant is not None and quant.get("layout") == CODED_KEYS_LAYOUT:
        version = CODED_KEYS_VERSION
    else:
        version = FORMAT_VERSION if residual is None else RESIDUAL_VERSION
    prefix = PREFIX.pack(MAGIC, version, len(area), zlib.crc32(area))
    return b"".join([prefix, area, payload, tail])


def read_wgs(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read and fully validate a ``.wgs`` file.

    Args:
        path: The model file.

    Returns:
        ``(params, header)``: (N, 12) float32 parameters (dequantised for ``compact96``) and the
        header dict as stored (including ``"n"`` and ``"payload"``).
    """
    params, header = _read(path, payload=True)
    assert params is not None
    return params, header


def read_wgs_header(path: str | os.PathLike) -> dict:
    """The header of a ``.wgs`` file, validated as :func:`read_wgs` validates it (checksum, sizes,
    what the payload may claim against its size), without reading the payload."""
    return _read(path, payload=False)[1]


def _read(path: str | os.PathLike, payload: bool) -> tuple[np.ndarray | None, dict]:
    p = Path(path)
    try:
        f = open(p, "rb")
    except FileNotFoundError:
        raise WarpgaussError(f"no such model file: {p}") from None
    except IsADirectoryError:
        raise WarpgaussError(f"{p} is a directory; give a .wgs model file") from None
    except OSError as e:
        raise WarpgaussError(f"cannot open model file {p}: {e.strerror}") from None
    with f:
        return _parse(f, os.fstat(f.fileno()).st_size, str(p), payload)


def read_wgs_bytes(data: bytes) -> tuple[np.ndarray, dict]:
    """:func:`read_wgs` of a whole file's bytes held in memory (what :func:`wgs_bytes` returns),
    validated as a file is; errors name "the model bytes" where a file's name would stand."""
    params, header = _parse(io.BytesIO(bytes(data)), len(data), "the model bytes", payload=True)
    assert params is not None
    return params, header


def _read_header(f: BinaryIO, size: int, bad) -> tuple[int, int, dict]:
    """The prefix and the header of a model file: (version, header length, header), checked
    (magic, version, length, CRC32, a JSON object); ``bad(msg)`` makes the error."""
    if size < PREFIX_SIZE:
        raise bad(f"not a warpgauss model file (only {size} bytes, shorter than the {PREFIX_SIZE}-byte prefix)")
    magic, version, hlen, crc = PREFIX.unpack(f.read(PREFIX_SIZE))
    if magic != MAGIC:
        raise bad("not a warpgauss model file (bad magic); give a .wgs file written by warpgauss")
    if version not in VERSIONS:
        raise bad(
            f"unsupported .wgs format version {version} (this warpgauss reads versions {VERSIONS[0]} to {VERSIONS[-1]}); "
            "upgrade warpgauss or re-encode the volume"
        )
    if hlen > size - PREFIX_SIZE:
        raise bad(
            f"declared header length {hlen} exceeds the {size - PREFIX_SIZE} bytes after the prefix; the file is truncated or damaged"
        )
    area = f.read(hlen)
    if len(area) != hlen:
        raise bad("the file changed while being read; try again")
    if zlib.crc32(area) != crc:
        raise bad("header checksum (CRC32) mismatch: the file is damaged; restore it or re-encode")
    try:
        header = json.loads(area.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise bad("the header is not valid UTF-8 JSON: the file is damaged; restore it or re-encode") from None
    if not isinstance(header, dict):
        raise bad("the header is not a JSON object: the file is damaged; restore it or re-encode")
    return version, hlen, header


def _parse(f: BinaryIO, size: int, label: str, payload: bool) -> tuple[np.ndarray | None, dict]:
    """Validate and read the model whose ``size`` bytes ``f`` holds from its start (``label``: its
    name in errors); ``payload`` False: the header only."""

    def bad(msg: str) -> WarpgaussError:
        return WarpgaussError(f"{label}: {msg}")

    version, hlen, header = _read_header(f, size, bad)
    for key in ("n", "payload"):
        if key not in header:
            raise bad(f"the header lacks the required key '{key}'; the file was not written by warpgauss")
    n = header["n"]
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise bad(f"the header's primitive count n = {n!r} is not a non-negative integer; the file is damaged")
    info = header["payload"]
    if not isinstance(info, dict):
        raise bad("the header's 'payload' entry is not an object; the file is damaged")
    for key in ("encoding", "bytes_per_primitive", "layout", "sha256"):
        if key not in info:
            raise bad(f"the header's payload description lacks '{key}'; the file was not written by warpgauss")
    enc = info["encoding"]
    if not isinstance(enc, str) or enc not in ENCODINGS:
        raise bad(f"unknown payload encoding {enc!r} (this warpgauss reads {', '.join(ENCODINGS)}); upgrade warpgauss or re-encode")
    bpp = ENCODINGS[enc]
    if info["bytes_per_primitive"] != bpp or isinstance(info["bytes_per_primitive"], bool):
        raise bad(
            f"payload encoding {enc} has {bpp} bytes per primitive, the header says {info['bytes_per_primitive']!r}; the file is damaged"
        )
    if bpp is None:
        total = info.get("payload_bytes")
        if isinstance(total, bool) or not isinstance(total, int) or total < 0:
            raise bad(f"the header's payload_bytes {total!r} is not a non-negative integer; the file is damaged")
    else:
        total = n * bpp
    if info["layout"] != list(PARAM_NAMES):
        raise bad(f"unsupported parameter layout {info['layout']!r}; expected {list(PARAM_NAMES)}")
    sha = info["sha256"]
    if not isinstance(sha, str) or len(sha) != 64:
        raise bad("the header's payload sha256 is not a 64-digit hex string; the file is damaged")
    if enc in ("compact96", "coded") and "quant" not in info:
        what = "ranges" if enc == "compact96" else "description"
        raise bad(f"the header lacks the {enc} quantisation {what} ('quant'); the file is damaged")
    extra = 0
    keyed = enc == "coded" and isinstance(info["quant"], dict) and info["quant"].get("layout") == CODED_KEYS_LAYOUT
    if keyed != (version == CODED_KEYS_VERSION):
        raise bad(
            f"a version {version} file {'without' if version == CODED_KEYS_VERSION else 'with'} a layout {CODED_KEYS_LAYOUT} coded payload; the file is damaged"
        )
    if version != CODED_KEYS_VERSION and ("residual" in header) != (version == RESIDUAL_VERSION):
        raise bad(f"a version {version} file {'without' if version == RESIDUAL_VERSION else 'with'} a residual; the file is damaged")
    if "residual" in header:  # checked in full by warpgauss.format.residual.check_info before it is read
        claimed = header["residual"].get("payload_bytes") if isinstance(header["residual"], dict) else None
        if isinstance(claimed, bool) or not isinstance(claimed, int) or claimed < 0:
            raise bad(f"the header's residual payload_bytes {claimed!r} is not a non-negative integer; the file is damaged")
        extra = claimed
    expected = PREFIX_SIZE + hlen + total + extra
    if size != expected:
        kind = "truncated" if size < expected else f"{size - expected} trailing bytes"
        what = f"{n} x {bpp}" if bpp is not None else f"{total}-byte coded"
        more = f" + {extra}-byte residual" if extra else ""
        raise bad(
            f"file size {size} != expected {expected} (prefix {PREFIX_SIZE} + header {hlen} + "
            f"{what} payload{more}): {kind}; the file is damaged"
        )
    if n < 1:
        raise bad("the model holds no primitives (n = 0); a model needs at least one, re-encode it")
    if enc == "coded":  # before the payload is read or anything sized by n is allocated
        from .coded import check_claim

        try:
            check_claim(total, n)
        except WarpgaussError as e:
            raise bad(str(e)) from None
    if not payload:
        return None, header
    data = f.read(total)
    if len(data) != total:
        raise bad("the file changed while being read; try again")
    if hashlib.sha256(data).hexdigest() != sha:
        raise bad("payload checksum mismatch: the file is damaged; restore it or re-encode")
    if enc in ("compact96", "coded"):
        try:
            if enc == "compact96":
                params = decode_compact(data, n, info["quant"])
            else:
                from .coded import decode_coded

                params = decode_coded(data, n, info["quant"])
        except WarpgaussError as e:
            raise bad(str(e)) from None
    else:
        params = np.frombuffer(data, dtype="<f4").reshape(n, 12).astype(np.float32)
    try:
        _check_finite(params, "invalid model")
    except WarpgaussError as e:
        raise bad(str(e)) from None
    return params, header
