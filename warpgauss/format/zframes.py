"""What the coded payload's layouts share (:mod:`.coded`, :mod:`.coded_keys`): the columns, the
code bound, the Morton interleave and the Zstandard frame of byte planes."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from ..errors import WarpgaussError

# the frame of planes is coded at each level and the smaller kept: level 1 was the smaller on three
# refined models of four, level 9 on the fourth (mni_icbm152 at CR 1000, 688 Gaussians: 9.67 and
# 9.31 B a Gaussian); both take 2-11 ms a megabyte of planes, where level 19 took 135
ZSTD_LEVELS = (1, 9)
CODED_COLUMNS = ("mu_x", "mu_y", "mu_z", "log_sx", "log_sy", "log_sz", "q_index", "q_0", "q_1", "q_2", "a", "w")
_MAX_CODE = 1 << 52  # |code| bound: every code and difference is exact in float64 and int64


def zstandard_module():
    try:
        import zstandard
    except ImportError:  # pragma: no cover - a dependency of the package
        raise WarpgaussError("the coded model format needs the 'zstandard' package: pip install zstandard") from None
    return zstandard


def _part1by2(v: np.ndarray) -> np.ndarray:
    """Spread the low 21 bits of v to every third bit (Morton interleave of one axis)."""
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


PARALLEL_MIN_BYTES = 1 << 18  # raw planes from which the Zstandard levels run on threads


def _compress_planes(planes: list[bytes], raw: int) -> bytes:
    """One Zstandard frame of ``planes`` (``raw`` bytes in all), a block ended after each plane, at
    each of :data:`ZSTD_LEVELS`; the smallest (the first of equals)."""
    zstd = zstandard_module()

    def frame(level: int) -> bytes:
        co = zstd.ZstdCompressor(level=level, write_checksum=True).compressobj(size=raw)
        out = []
        for plane in planes:
            out.append(co.compress(plane))
            out.append(co.flush(zstd.COMPRESSOBJ_FLUSH_BLOCK))
        out.append(co.flush())
        return b"".join(out)

    # the levels on threads of their own (Zstandard releases the GIL): the same frames, in parallel
    if raw >= PARALLEL_MIN_BYTES and len(ZSTD_LEVELS) > 1:
        with ThreadPoolExecutor(max_workers=len(ZSTD_LEVELS)) as ex:
            frames = list(ex.map(frame, ZSTD_LEVELS))
    else:
        frames = [frame(level) for level in ZSTD_LEVELS]
    return min(frames, key=len)  # the first of equals
