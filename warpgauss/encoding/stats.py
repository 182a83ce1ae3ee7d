"""`warpgauss stats`: what a field needs, before encoding it (SPEC section 5).

Occupancy, gradient top-10 % concentration, S(1)/S(16), the seed limit N_max, a table of budgets
with their exact file sizes and compression ratios (full precision and compact; the coded format,
the default, as the range measured on real models), and a one-line
reading of what the numbers mean for this field.
"""

from __future__ import annotations

import time

from ..errors import WarpgaussError
from ..field.analysis import Field, seed_limit

DEFAULT_BUDGETS = (2_000, 20_000, 200_000, 650_000, 1_400_000)


def reading(st: dict, n_max: int) -> str:
    """One line on what the statistics mean for encoding this field."""
    occ, top, s = st["occupancy"], st["grad_top10"], st["s1_s16"]
    parts = []
    if occ < 0.1:
        parts.append(f"sparse ({100 * occ:.1f} % occupied): the budget goes to the occupied part, empty space is cheap")
    if top >= 0.6:
        parts.append(
            "interface-concentrated gradient (the top 10 % of voxels carry "
            f"{100 * top:.0f} % of it): a budget that covers the interface gets most of the gain, more budget adds little"
        )
    if s is None:  # no structure at lag 16 (constant or tiny field)
        parts.append("no structure at 16 voxels: a few Gaussians represent it")
    elif s <= 0.1:
        parts.append(f"smooth over 16 voxels (S(1)/S(16) = {s:.3f}): high PSNR already at high compression ratios")
    elif s >= 0.2 and top < 0.6:
        parts.append(
            f"structure below 16 voxels everywhere (S(1)/S(16) = {s:.3f}, turbulence-like): PSNR grows slowly with "
            "the budget; expect modest PSNR at high ratios"
        )
    if not parts:
        parts.append(f"moderately structured (S(1)/S(16) = {s:.3f}): PSNR grows steadily with the budget")
    if n_max < DEFAULT_BUDGETS[1]:
        parts.append(f"only {n_max:,} Gaussians fit (seed limit)")
    return "; ".join(parts)


def budget_table(f: Field, header: dict, budgets, n_max: int) -> list[dict]:
    """Exact bytes and compression ratios of each feasible budget (and of N_max) in the full and
    compact formats, and the coded format's as a range (its size depends on the refined model:
    :data:`warpgauss.encoding.driver.sizing.CODED_BPP_MEASURED` bytes a Gaussian). ``larger_than_source``
    names the formats whose file would be larger than the source (coded: at the range's top)."""
    from ..format.wgs import header_size

    rows = []
    wanted = sorted({int(b) for b in budgets if 1 <= int(b) <= n_max} | ({n_max} if n_max >= 1 else set()))
    from .driver.sizing import CODED_BPP_MEASURED

    h_full = header_size(header, 1, compact=False)
    h_compact = header_size(header, 1, compact=True)
    for n in wanted:
        full = 48 * n + h_full
        compact = 12 * n + h_compact
        coded = [int(round(b * n)) + header_size(header, n, encoding="coded") for b in CODED_BPP_MEASURED]
        sizes = {"coded": coded[1], "compact": compact, "full": full}
        rows.append(
            {
                "n": n,
                "bytes": full,
                "compression_ratio": f.source_bytes / full,
                "compact_bytes": compact,
                "compact_compression_ratio": f.source_bytes / compact,
                "coded_bytes_estimate": coded,
                "coded_compression_ratio_estimate": [f.source_bytes / coded[1], f.source_bytes / coded[0]],
                "is_n_max": n == n_max,
                "larger_than_source": [k for k, v in sizes.items() if v > f.source_bytes],
            }
        )
    return rows


def _ladder(rows: list[dict], given: bool) -> dict:
    """The table's rows (``budgets``) and the default ones left out for a file larger than the source."""
    if given:
        return {"budgets": rows, "left_out": []}
    keep = [r for r in rows if "coded" not in r["larger_than_source"]]
    why = "its coded file could be larger than the source"
    return {"budgets": keep, "left_out": [{"n": r["n"], "is_n_max": r["is_n_max"], "why": why} for r in rows if r not in keep]}


def field_stats(f: Field, device: str | None = None, budgets=None) -> dict:
    """Statistics of a normalised field (stage P output) with the budget table and the reading.

    ``budgets`` None: :data:`DEFAULT_BUDGETS` and N_max, less those whose coded file (the
    default format) could be larger than the source (``left_out`` lists them: a 48^3 volume was
    offered 200,000 Gaussians); budgets given are all tabulated, each row naming the formats whose
    file would be larger than the source (``larger_than_source``)."""
    from ..core.warp import device_name, resolve_device
    from ..field.analysis import DeviceVolume, structure_stats
    from .driver import EncodeOptions, header_for

    given = budgets is not None
    budgets = DEFAULT_BUDGETS if budgets is None else budgets
    if not budgets or min(int(b) for b in budgets) < 1:
        raise WarpgaussError("--budgets must be positive integers")
    dev = resolve_device(device)
    t0 = time.perf_counter()
    st = structure_stats(DeviceVolume(f, dev))
    n_max = seed_limit(f.eligible, f.occupied)
    header = header_for(f, EncodeOptions())
    return {
        "name": f.name,
        "shape_xyz": list(f.shape_xyz),
        "source_dtype": f.source_dtype,
        "source_bytes": f.source_bytes,
        "value_min": f.vmin,
        "value_max": f.vmax,
        "masked_voxels": int(f.n_voxels - f.n_valid),
        "occupancy": st["occupancy"],
        "occupied_voxels": st["occupied_voxels"],
        "eligible_detail_voxels": st["eligible_detail_voxels"],
        "grad_top10": st["grad_top10"],
        "s1": st["s1"],
        "s16": st["s16"],
        "s1_s16": st["s1_s16"],
        "sampled": st["sampled"],
        "samples": st["samples"],
        "n_max": n_max,
        **_ladder(budget_table(f, header, budgets, n_max), given),
        "reading": reading(st, n_max),
        "device": dev,
        "device_name": device_name(dev),
        "seconds_statistics": time.perf_counter() - t0,
    }
