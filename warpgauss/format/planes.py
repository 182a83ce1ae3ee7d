"""The bounded residual's streams as bytes: integers zigzag-mapped to their narrowest width, split
into byte planes and compressed with Zstandard (:func:`compress`), and read back into at most the
size a frame declares (:func:`decompress` refuses a frame that claims more than Zstandard can
produce from its bytes)."""

from __future__ import annotations

import numpy as np

from ..errors import WarpgaussError
from .coded import zstandard_module

ZSTD_MAX_RATIO = 1 << 16  # Zstandard never expands past ~32,768 : 1 (an RLE block of 128 KiB in 4 bytes)
ZSTD_LEVEL = 9  # streams up to ZSTD_LARGE_RAW; larger ones level 3 (symbols past a prediction are noise-like)
ZSTD_LARGE_RAW = 4 << 20


def zigzag(d: np.ndarray) -> np.ndarray:
    return ((d << 1) ^ (d >> 63)).view(np.uint64)


def unzigzag(u: np.ndarray) -> np.ndarray:
    return (u >> np.uint64(1)).view(np.int64) ^ -(u & np.uint64(1)).view(np.int64)


def byte_width(u: np.ndarray) -> int:
    top = int(u.max()) if u.size else 0
    return next(w for w in (1, 2, 4, 8) if top < 1 << (8 * w))


def byte_planes(u: np.ndarray, width: int) -> bytes:
    b = u.astype(f"<u{width}").view(np.uint8).reshape(-1, width)
    return b.T.tobytes()  # byte planes: the high bytes, mostly 0, code apart from the low ones


def from_planes(raw: bytes, n: int, width: int) -> np.ndarray:
    b = np.frombuffer(raw, np.uint8).reshape(width, n).T
    return np.ascontiguousarray(b).view(f"<u{width}").reshape(n).astype(np.uint64)


def compress(raw: bytes, level: int | None = None) -> bytes:
    zstd = zstandard_module()
    lvl = level if level is not None else (ZSTD_LEVEL if len(raw) <= ZSTD_LARGE_RAW else 3)
    return zstd.ZstdCompressor(level=lvl, write_checksum=True).compress(raw)


def decompress(frame: bytes, size: int, what: str, codec: str = "zstd") -> bytes:
    """A frame's bytes, refused unless it yields exactly ``size`` bytes (checked before allocating
    against what Zstandard can produce from the frame's length)."""
    if codec == "zstd" and size > len(frame) * ZSTD_MAX_RATIO + 1024:  # bzip2 is read into at most the size
        raise WarpgaussError(
            f"the residual's {what} claim {size:,} bytes from a {len(frame):,}-byte frame, more than Zstandard can produce; the file is damaged"
        )
    zstd = zstandard_module()
    try:
        if codec == "bzip2":
            import bz2

            d = bz2.BZ2Decompressor()
            raw = d.decompress(frame, max_length=size + 1)  # never more than declared (and one byte to tell)
            if not d.eof and len(raw) <= size:
                raise OSError
        else:
            raw = zstd.ZstdDecompressor().decompress(frame, max_output_size=max(size, 1))
    except (zstd.ZstdError, OSError, EOFError, ValueError):
        raise WarpgaussError(f"the residual's {what} do not decompress: the file is damaged; restore it or re-encode") from None
    if len(raw) != size:
        raise WarpgaussError(f"the residual's {what} hold {len(raw):,} bytes where the header says {size:,}; the file is damaged")
    return raw


# -- coding --------------------------------------------------------------------------------------
