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
# bzip2 in parts of this many bytes, coded at once on threads (codec "bzip2-parts": the parts' streams
# one after the other): two of bzip2's 900 kB blocks a part. On the three head MRIs' q's at 1e-2 and
# 1e-3 of the range (8.7-23 MB) 0.07-0.43 % larger than one stream (900 kB parts: up to 1.1 %), and
# the bytes do not depend on the machine's cores
BZIP2_PART = 1_800_000
CODECS = ("zstd", "bzip2", "bzip2-parts")


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


def bzip2_parts(raw: bytes, pool=None) -> tuple[bytes, str]:
    """``raw`` coded with bzip2 at level 9 in :data:`BZIP2_PART`-byte parts (on ``pool``'s threads:
    bz2 lets go of the GIL), as (frame, codec): "bzip2" where one part holds it (one stream, as
    before parts), else "bzip2-parts"."""
    import bz2

    parts = [raw[i : i + BZIP2_PART] for i in range(0, len(raw), BZIP2_PART)] or [raw]
    coded = list((pool.map if pool is not None else map)(lambda b: bz2.compress(b, 9), parts))
    return b"".join(coded), "bzip2" if len(parts) == 1 else "bzip2-parts"


def _bunzip(frame: bytes, size: int, parts: bool) -> bytes:
    """bzip2's streams in ``frame`` (one, or one after another with ``parts``) into at most ``size``
    bytes and one to tell; OSError where a stream is cut short."""
    import bz2

    raw, rest = bytearray(), frame
    while True:
        d = bz2.BZ2Decompressor()
        raw += d.decompress(rest, max_length=size + 1 - len(raw))  # never more than declared (and one byte to tell)
        if len(raw) > size:
            return bytes(raw)
        if not d.eof:
            raise OSError
        rest = d.unused_data
        if not parts or not rest:
            return bytes(raw)


def decompress(frame: bytes, size: int, what: str, codec: str = "zstd") -> bytes:
    """A frame's bytes, refused unless it yields exactly ``size`` bytes (checked before allocating
    against what Zstandard can produce from the frame's length)."""
    if codec == "zstd" and size > len(frame) * ZSTD_MAX_RATIO + 1024:  # bzip2 is read into at most the size
        raise WarpgaussError(
            f"the residual's {what} claim {size:,} bytes from a {len(frame):,}-byte frame, more than Zstandard can produce; the file is damaged"
        )
    zstd = zstandard_module()
    try:
        if codec != "zstd":
            raw = _bunzip(frame, size, codec == "bzip2-parts")
        else:
            raw = zstd.ZstdDecompressor().decompress(frame, max_output_size=max(size, 1))
    except (zstd.ZstdError, OSError, EOFError, ValueError):
        raise WarpgaussError(f"the residual's {what} do not decompress: the file is damaged; restore it or re-encode") from None
    if len(raw) != size:
        raise WarpgaussError(f"the residual's {what} hold {len(raw):,} bytes where the header says {size:,}; the file is damaged")
    return raw


# -- coding --------------------------------------------------------------------------------------
