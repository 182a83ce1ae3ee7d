"""The bounded residual's streams as bytes: integers zigzag-mapped to their narrowest width, split
into byte planes and compressed with Zstandard (:func:`compress`), and read back into at most the
size a frame declares (:func:`decompress` refuses a frame that claims more than Zstandard can
produce from its bytes)."""

from __future__ import annotations

import os
import struct

import numpy as np

from ..errors import WarpgaussError
from .coded import zstandard_module

ZSTD_MAX_RATIO = 1 << 16  # Zstandard never expands past ~32,768 : 1 (an RLE block of 128 KiB in 4 bytes)
ZSTD_LEVEL = 9  # streams up to ZSTD_LARGE_RAW; larger ones level 3 (symbols past a prediction are noise-like)
ZSTD_LARGE_RAW = 4 << 20
# bzip2 in parts of this many bytes, coded and decoded at once on threads (codec "bzip2-parts": a
# table of the parts' lengths, then their streams): two of bzip2's 900 kB blocks a part. On the three head MRIs' q's at 1e-2 and
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
    before parts), else "bzip2-parts": a table (the part size, the count and each part's coded
    length, little-endian uint32) and the parts' streams one after the other, so that a reader
    decodes the parts at once too."""
    import bz2

    parts = [raw[i : i + BZIP2_PART] for i in range(0, len(raw), BZIP2_PART)] or [raw]
    coded = list((pool.map if pool is not None else map)(lambda b: bz2.compress(b, 9), parts))
    if len(coded) == 1:
        return coded[0], "bzip2"
    return struct.pack(f"<II{len(coded)}I", BZIP2_PART, len(coded), *(len(c) for c in coded)) + b"".join(coded), "bzip2-parts"


def _bunzip(frame: bytes, size: int) -> bytes:
    """One bzip2 stream into at most ``size`` bytes and one to tell; OSError where it is cut short."""
    import bz2

    d = bz2.BZ2Decompressor()
    raw = d.decompress(frame, max_length=size + 1)  # never more than declared (and one byte to tell)
    if not d.eof and len(raw) <= size:
        raise OSError
    return raw


def _bunzip_parts(frame: bytes, size: int) -> bytes:
    """A "bzip2-parts" frame (see :func:`bzip2_parts`) into exactly ``size`` bytes, the parts on
    threads, each into at most its own share; OSError where the table does not describe the frame
    and ``size`` or a part does not decode to its share."""
    import bz2

    if len(frame) < 8:
        raise OSError
    part, count = struct.unpack_from("<II", frame)
    if part < 1 or count != max(1, -(-size // part)) or len(frame) < 8 + 4 * count:
        raise OSError
    lengths = struct.unpack_from(f"<{count}I", frame, 8)
    starts = np.cumsum((8 + 4 * count, *lengths)).tolist()
    if starts[-1] != len(frame):
        raise OSError

    def one(i: int) -> bytes:
        want = min(part, size - i * part)
        d = bz2.BZ2Decompressor()
        out = d.decompress(frame[starts[i] : starts[i + 1]], max_length=want + 1)
        if len(out) != want or not d.eof or d.unused_data:
            raise OSError
        return out

    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=max(1, min(count, os.cpu_count() or 1))) as pool:
        return b"".join(pool.map(one, range(count)))


def decompress(frame: bytes, size: int, what: str, codec: str = "zstd") -> bytes:
    """A frame's bytes, refused unless it yields exactly ``size`` bytes (checked before allocating
    against what Zstandard can produce from the frame's length)."""
    if codec == "zstd" and size > len(frame) * ZSTD_MAX_RATIO + 1024:  # bzip2 is read into at most the size
        raise WarpgaussError(
            f"the residual's {what} claim {size:,} bytes from a {len(frame):,}-byte frame, more than Zstandard can produce; the file is damaged"
        )
    zstd = zstandard_module()
    try:
        if codec == "bzip2-parts":
            raw = _bunzip_parts(frame, size)
        elif codec == "bzip2":
            raw = _bunzip(frame, size)
        else:
            raw = zstd.ZstdDecompressor().decompress(frame, max_output_size=max(size, 1))
    except (zstd.ZstdError, OSError, EOFError, ValueError):
        raise WarpgaussError(f"the residual's {what} do not decompress: the file is damaged; restore it or re-encode") from None
    if len(raw) != size:
        raise WarpgaussError(f"the residual's {what} hold {len(raw):,} bytes where the header says {size:,}; the file is damaged")
    return raw


# -- coding --------------------------------------------------------------------------------------
