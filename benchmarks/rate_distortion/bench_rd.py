"""Rate-distortion benchmark (issue #8 part 3, issue #18 part 4): warpgauss against SZ3, ZFP, SPERR.

Two modes. With ``--ratios`` (issue #18 part 4, "rate-distortion, honestly") every codec is run at
the same FIXED compression ratios:

- ``wg``: warpgauss with the library's defaults, what ``warpgauss encode VOLUME --ratio R`` does
  (coded format, default refinement, sampled EV; no preset unless ``--preset`` is given; no
  refinement checkpoints, which the CLI writes every 60 s): one encode per ratio, nothing shared
  between them but the loaded field (S1a runs in every encode). The refiner's self-test runs once
  per process, in the warm-up encode, so no row includes it (``self_test_s`` 0). The model is
  saved to a temporary ``.wgs``; the achieved ratio uses that file's size, and PSNR the full-grid
  decode of the reloaded file. encode_s: the encode call plus the save (reading the volume
  excluded; ``stages`` and ``save_s`` split it); decode_s: load + full-grid decode;
- ``sz3-matched``: the absolute bound searched until the ratio is within ``--match-tol`` of R;
- ``zfp-rate-matched``: fixed rate 8 x itemsize / R bits per value (the ratio is against the
  SOURCE dtype), corrected from the measured bytes (partial blocks, header) until within the
  tolerance; a ratio whose rate is below ``--zfp-min-rate`` (0.25: at 9 bits per 4^3 block or
  fewer zfp codes only the block exponents, at fewer than 9 zfpy 1.0.1 aborts) is listed under the
  volume's ``unreachable`` instead;
- ``sperr``: SPERR (PyPI ``numcodecs-wasm-sperr``), ``Sperr(mode="bpp", bpp=8 x itemsize / R)``
  on the float32 field normalised by min/max, the bpp corrected from the measured encoded bytes
  (the container header) until the ratio is within the tolerance.

TTHRESH is left out: its wasm decoder overflows on volumes of this size. ``--codecs none`` runs
warpgauss only (a GPU host without the codecs), ``--no-warpgauss`` the reference codecs only.

The ladder mode (no ``--ratios``) matches the codecs to warpgauss budgets instead. For each
volume (the built-in example fields generated at ``--size``, and the real volumes in
``../shared/data`` when present) it measures PSNR against compression ratio, plus encode and
decode seconds, for:

- ``wg-full``: warpgauss, full-precision file (48 N + H bytes), one model per budget of a ladder
  (one read and one S1a analysis for the whole ladder, as ``encode --ladder``);
- ``wg-compact``: the same models saved with ``compact=True`` (12 N + H), reloaded and decoded;
- ``sz3-matched``: SZ3 (PyPI ``pysz``), absolute error bound searched (log-log regula falsi from
  the SZ3 curve's bracket) until its ratio is within ``--match-tol`` of each warpgauss
  full-precision ratio; ``sz3``: SZ3 at a few error bounds;
- ``zfp-rate`` (fixed rate, bits/value), ``zfp-rate-matched`` (the rate giving each warpgauss
  ratio) and ``zfp-acc`` (fixed accuracy, absolute tolerance), PyPI ``zfpy``.

Every codec is scored by the same function: PSNR = 10 log10(1 / MSE) on the FULL grid, values
normalised to [0, 1] by the volume's finite min/max (warpgauss's normalisation), masked voxels
excluded. Ratio = source bytes (voxels x source dtype size, warpgauss's definition) / compressed
bytes for every codec; SZ3 and ZFP compress the float32 volume. Encode seconds exclude reading
the volume (stage P) and evaluation; warpgauss's include analysis (S1a, shared by the ladder but
counted in every row), allocation and refinement (with the one-off self-test in the first row).
Decode seconds: the full-grid decode (warpgauss: ``Model.decode``; compact: load + decode).

The JSON is rewritten atomically after every row, so a run that is stopped keeps what it measured.
On a large volume (512^3, 1024^3) ``--volume-dir`` generates the example fields side by side into
``.npy`` files first, and ``--workers K`` runs the single-threaded SZ3/ZFP calls K at a time in
separate processes that map those files, after every warpgauss row (so the GPU encodes never share
the host with them):

    python benchmarks/rate_distortion/bench_rd.py --device cuda:0 --size 512 --preset paper --real none \\
        --budgets 16000,128000,512000 --volume-dir /tmp/vol --workers 12 --out rate_distortion/bench_rd_fields512_h100.json

    python benchmarks/rate_distortion/bench_rd.py --size 128 --budgets 1000,4000,16000 --preset fast \\
        --real nAChR_M2_water.plt,1jzv.ccp4 --out benchmarks/results/rate_distortion/bench_rd_fields128_cpu.json

Fixed ratios, the codecs on the CPU and warpgauss on the GPU (``plot_rd.py`` merges the two):

    python benchmarks/rate_distortion/bench_rd.py --no-warpgauss --ratios 10,30,100,300,1000 --fields vortex,interface \\
        --size 512 --volume-dir /tmp/vol512 --real mean_reg2mean.nii.gz,mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz,inia19-t1-brain.nii.gz \\
        --max-voxels 100000000 --codecs sz3,zfp,sperr --workers 2 --out benchmarks/results/rate_distortion/bench_rd_codecs_cpu.json

    python benchmarks/rate_distortion/bench_rd.py --device cuda:0 --codecs none --ratios 10,30,100,300,1000 --fields vortex,interface \\
        --size 512 --volume-dir /tmp/vol --real mean_reg2mean.nii.gz,mni_icbm152_t1_tal_nlin_sym_09a_converted.nii.gz,inia19-t1-brain.nii.gz \\
        --max-voxels 100000000 --out $OUT/bench_rd_h100.json
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime as dt
import json
import math
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import warpgauss
from warpgauss.core.profiling import StageRecorder
from warpgauss.core.warp import device_name, resolve_device, warp
from warpgauss.encoding.allocate import AllocationConfig
from warpgauss.encoding.driver import EncodeOptions, ReadOptions, encode_field, encoding_of, load_field, resolve_refine
from warpgauss.errors import WarpgaussError
from warpgauss.field.analysis import seed_limit
from warpgauss.format.model import Model
from warpgauss.readers.synthetic import EXAMPLES, generate

DATA_DIR = Path(__file__).resolve().parents[3] / "shared" / "data"
SZ3_BOUNDS = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 1e-4)  # x (max - min)
ZFP_RATES = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)  # bits per value
ZFP_MIN_RATE = 0.25  # the lowest fixed rate run: at 9 bits per 4^3 block (0.14) zfp codes only the block exponents,
# at 0.1875 the maximum error still exceeds the range, and below 9 bits zfpy 1.0.1 aborts (malloc: invalid size)
ZFP_TOLERANCES = (1e-1, 3e-2, 1e-2, 3e-3, 1e-3, 1e-4)  # x (max - min)


# ---------------------------------------------------------------------------- scoring


class Truth:
    """The reference every codec is scored against: the raw values, their min/max and the valid set.

    PSNR is accumulated in float64 over z-slabs, so scoring a 1024^3 volume needs no float64 copy.
    """

    SLAB = 1 << 22  # voxels per slab

    def __init__(self, raw: np.ndarray, vmin: float, vmax: float, valid: np.ndarray | None):
        self.vmin, self.vmax = float(vmin), float(vmax)
        self.raw = raw
        self.valid = valid
        # what SZ3 and ZFP compress: float32 in source units, masked voxels set to the minimum
        self.codec_input = np.ascontiguousarray(raw, dtype=np.float32)
        if valid is not None:
            self.codec_input = np.where(valid, self.codec_input, np.float32(self.vmin)).astype(np.float32)

    def psnr(self, recon: np.ndarray, normalised: bool = False) -> float:
        """PSNR (dB) of a full-grid reconstruction (source units, or [0, 1] with ``normalised``)."""
        span = self.vmax - self.vmin
        nz = self.raw.shape[0]
        step = max(1, self.SLAB // max(1, int(np.prod(self.raw.shape[1:]))))
        total, count = 0.0, 0
        for z0 in range(0, nz, step):
            z1 = min(nz, z0 + step)
            if normalised:
                err = recon[z0:z1].astype(np.float64) - (self.raw[z0:z1].astype(np.float64) - self.vmin) / span
            else:  # float32 differences of float32 values are exact or within an ulp of the error itself
                err = np.subtract(recon[z0:z1], self.raw[z0:z1], dtype=np.float32).astype(np.float64) / span
            if self.valid is not None:
                err = err[self.valid[z0:z1]]
            total += float(np.dot(err.ravel(), err.ravel()))
            count += err.size
        mse = total / max(count, 1)
        return float(10.0 * math.log10(1.0 / max(mse, 1e-20)))


# ---------------------------------------------------------------------------- codecs


def sz3_run(data: np.ndarray, eb: float):
    """SZ3 absolute error bound ``eb``: (compressed bytes, decoded array, encode s, decode s)."""
    from pysz import sz, szConfig, szErrorBoundMode

    conf = szConfig()
    conf.errorBoundMode = szErrorBoundMode.ABS
    conf.absErrorBound = float(eb)
    t0 = time.perf_counter()
    comp, _ = sz.compress(data, conf)
    t1 = time.perf_counter()
    dec, _ = sz.decompress(comp, np.float32, data.shape)
    t2 = time.perf_counter()
    return int(comp.nbytes), dec.reshape(data.shape), t1 - t0, t2 - t1


def zfp_run(data: np.ndarray, **mode):
    """ZFP (``rate=`` bits/value or ``tolerance=``): (bytes, decoded array, encode s, decode s)."""
    import zfpy

    t0 = time.perf_counter()
    comp = zfpy.compress_numpy(data, **mode)
    t1 = time.perf_counter()
    dec = zfpy.decompress_numpy(comp)
    t2 = time.perf_counter()
    return len(comp), dec.reshape(data.shape), t1 - t0, t2 - t1


def _sperr_class():
    """``numcodecs_wasm_sperr.Sperr``. numcodecs (0.16.6) parses zfpy's version as integers when
    it is first imported, which fails on zfpy 1.0.1.post0 (and a failed import leaves numcodecs
    half-initialised): the import runs with zfpy's ".postN" hidden from it."""
    import importlib.metadata as md
    import re

    real = md.version
    md.version = lambda name: re.sub(r"\.post\d+$", "", real(name)) if name == "zfpy" else real(name)
    try:
        from numcodecs_wasm_sperr import Sperr
    finally:
        md.version = real
    return Sperr


def sperr_run(data: np.ndarray, **mode):
    """SPERR (``mode="bpp", bpp=`` bits per value, or ``mode="pwe", pwe=`` a point-wise error):
    (encoded bytes, decoded array, encode s, decode s)."""
    codec = _sperr_class()(**mode)
    t0 = time.perf_counter()
    comp = np.asarray(codec.encode(data))
    t1 = time.perf_counter()
    dec = np.asarray(codec.decode(comp))
    t2 = time.perf_counter()
    return int(comp.nbytes), dec.reshape(data.shape), t1 - t0, t2 - t1


def rate_matched(data, source_bytes, target, tol, rate, run, min_rate=0.0, max_steps=6):
    """Search a fixed-rate codec's rate (bits per value) until its ratio is within ``tol`` of
    ``target``, from ``rate`` (the nominal 8 x itemsize / target).

    The bytes are close to proportional to the rate (plus a header, and for ZFP the padding of
    partial 4^3 blocks, which it codes whole), so each step scales the rate by the wanted over
    the measured bytes. ZFP's rate is rounded to whole bits per block: the search stops when a
    rate gives bytes already measured, and keeps the closest. A rate below ``min_rate`` is not run.

    Returns (rate, nbytes, decoded, enc_s, dec_s, runs, reached), or None when even the first
    rate is below ``min_rate``.
    """
    want = source_bytes / target
    best, measured, runs = None, set(), 0
    for _ in range(max_steps):
        if rate < min_rate:
            break
        nbytes, dec, te, td = run(data, rate)
        runs += 1
        ratio = source_bytes / nbytes
        if best is None or abs(math.log(ratio / target)) < abs(math.log(best[1] / target)):
            best = (rate, ratio, nbytes, dec, te, td)
        dec = None
        if abs(ratio / target - 1.0) <= tol or nbytes in measured:
            break
        measured.add(nbytes)
        rate = rate * want / nbytes
    if best is None:
        return None
    rate, ratio, nbytes, dec, te, td = best
    return rate, nbytes, dec, te, td, runs, abs(ratio / target - 1.0) <= tol


def sz3_matched(data, source_bytes, target, rng, tol, max_steps=40, seen=(), run=sz3_run):
    """Search SZ3's absolute error bound until its ratio is within ``tol`` of ``target``.

    The ratio grows with the bound, close to a power law, so the search interpolates log(ratio)
    against log(bound) between the nearest bounds below and above the target (regula falsi,
    falling back to the geometric midpoint when one side stalls), and steps by 10x until it has
    both. ``seen`` holds (bound, ratio) pairs already measured on this volume (the SZ3 curve):
    they bracket the target from the start, which saves most of the runs on a large volume.

    Returns (eb, nbytes, decoded, enc_s, dec_s, steps, reached): steps counts the runs made here.
    """
    lo_eb, hi_eb = 1e-9 * rng, 2.0 * rng  # the search never leaves this range
    lo = max(((e, r) for e, r in seen if r < target and e >= lo_eb), default=None)
    hi = min(((e, r) for e, r in seen if r >= target and e <= hi_eb), default=None)
    best = None
    last_side = stall = 0
    for step in range(1, max_steps + 1):
        if lo and hi:
            if hi[0] / lo[0] < 1.0 + 1e-6:
                break
            t = math.log(target / lo[1]) / math.log(hi[1] / lo[1]) if hi[1] > lo[1] else 0.5
            t = 0.5 if stall >= 2 else min(max(t, 0.02), 0.98)
            eb = math.exp(math.log(lo[0]) + t * math.log(hi[0] / lo[0]))
        elif lo:
            eb = min(lo[0] * 10.0, hi_eb)
        elif hi:
            eb = max(hi[0] / 10.0, lo_eb)
        else:
            eb = 1e-2 * rng
        nbytes, dec, te, td = run(data, eb)
        ratio = source_bytes / nbytes
        if best is None or abs(math.log(ratio / target)) < abs(math.log(best[1] / target)):
            best = (eb, ratio, nbytes, dec, te, td, step)
        if abs(ratio / target - 1.0) <= tol:
            break
        side = -1 if ratio < target else 1
        stall = stall + 1 if side == last_side else 0
        last_side = side
        if side < 0:
            lo = (eb, ratio)
            if eb >= hi_eb:
                break  # even the largest bound gives less than the target ratio
        else:
            hi = (eb, ratio)
            if eb <= lo_eb:
                break  # even the smallest bound gives more than the target ratio
    eb, ratio, nbytes, dec, te, td, step = best
    return eb, nbytes, dec, te, td, step, abs(ratio / target - 1.0) <= tol


def codec_task(task: dict) -> dict:
    """Run one reference-codec setting on one volume and score it: the benchmark row.

    ``task`` names the volume by file (``raw``: an ``.npy`` of the source values, ``valid``:
    an optional ``.npy`` mask), so a worker process maps it rather than receiving a copy.
    """
    raw = np.load(task["raw"], mmap_mode="r")
    valid = np.load(task["valid"]) if task.get("valid") else None
    truth = Truth(raw, task["vmin"], task["vmax"], valid)
    data, sb, rng, kind = truth.codec_input, task["source_bytes"], task["vmax"] - task["vmin"], task["kind"]
    if kind == "sz3":
        cb, d, te, tdec = sz3_run(data, task["eb"])
        row = {"codec": "sz3", "param": f"eb={task['eb'] / rng:.3g}R", "abs_error_bound": task["eb"]}
    elif kind == "sz3-matched":
        seen = [tuple(x) for x in task.get("seen", ())]
        eb, cb, d, te, tdec, steps, ok = sz3_matched(data, sb, task["target"], rng, task["tol"], seen=seen)
        row = {
            "codec": "sz3-matched",
            "param": f"eb={eb / rng:.3g}R",
            "abs_error_bound": eb,
            "matched_to": {**task["matched_to"], "within_tol": ok, "search_steps": steps},
        }
    elif kind == "zfp-rate":
        cb, d, te, tdec = zfp_run(data, rate=task["rate"])
        row = {"codec": "zfp-rate", "param": f"rate={task['rate']:.3g}", "rate_bits_per_value": task["rate"]}
        if "matched_to" in task:
            row.update(codec="zfp-rate-matched", matched_to=task["matched_to"])
    elif kind == "zfp-acc":
        cb, d, te, tdec = zfp_run(data, tolerance=task["tol"])
        row = {"codec": "zfp-acc", "param": f"tol={task['tol'] / rng:.3g}R", "tolerance": task["tol"]}
    elif kind in ("zfp-matched", "sperr"):  # fixed rate, searched to a target ratio
        normalised = kind == "sperr"
        if normalised:  # SPERR compresses the field normalised by min/max: scored as such
            data = np.subtract(data, np.float32(task["vmin"]), dtype=np.float32)
            data *= np.float32(1.0 / rng)
            truth.codec_input = None
        run = (lambda x, r: sperr_run(x, mode="bpp", bpp=float(r))) if normalised else (lambda x, r: zfp_run(x, rate=r))
        found = rate_matched(data, sb, task["target"], task["tol"], task["rate"], run, min_rate=task.get("min_rate", 0.0))
        if found is None:
            raise ValueError(f"{kind}: rate {task['rate']} below the minimum {task.get('min_rate')}")
        rate, cb, d, te, tdec, steps, ok = found
        del data
        row = {
            "codec": "sperr" if normalised else "zfp-rate-matched",
            "param": f"{'bpp' if normalised else 'rate'}={rate:.4g}",
            "rate_bits_per_value": rate,
            "nominal_rate": task["rate"],
            "matched_to": {**task["matched_to"], "within_tol": ok, "search_steps": steps},
        }
        row.update({"ratio": sb / cb, "bytes": cb, "psnr_db": truth.psnr(d, normalised=normalised), "encode_s": te, "decode_s": tdec})
        return row
    else:
        raise ValueError(f"unknown codec task {kind!r}")
    row.update({"ratio": sb / cb, "bytes": cb, "psnr_db": truth.psnr(d), "encode_s": te, "decode_s": tdec})
    return row


# ---------------------------------------------------------------------------- volumes


def example_path(volume_dir: Path, name: str, size: int) -> Path:
    return Path(volume_dir) / f"{name}_{size}.npy"


def _generate_one(job: tuple[str, int, str]) -> tuple[str, float]:
    name, size, path = job
    t0 = time.perf_counter()
    vol = generate(name, size, seed=0)
    tmp = Path(path).with_name(Path(path).name + ".tmp.npy")
    np.save(tmp, vol)
    os.replace(tmp, path)
    return name, time.perf_counter() - t0


def generate_examples(names: list[str], size: int, volume_dir: Path, workers: int) -> dict[str, float]:
    """Write each example field at ``size`` to ``volume_dir`` (one process per field): name -> seconds.

    A 1024^3 field takes minutes of single-threaded numpy; generating the fields side by side and
    mapping the files later keeps that off the benchmark's critical path.
    """
    Path(volume_dir).mkdir(parents=True, exist_ok=True)
    jobs = [(n, size, str(example_path(volume_dir, n, size))) for n in names if not example_path(volume_dir, n, size).is_file()]
    if not jobs:
        return {}
    if workers <= 1 or len(jobs) == 1:
        return dict(_generate_one(j) for j in jobs)
    with _pool(min(workers, len(jobs))) as pool:
        return dict(pool.map(_generate_one, jobs))


@dataclass
class _ReadVolume(ReadOptions):
    """ReadOptions that give a volume already read (at stride 1) instead of reading its file:
    ``load_field(path, _ReadVolume(stride=s, volume=vol))`` is ``load_field(path, ReadOptions(stride=s))``
    without the second read, and without the file's reader (a host with no pyvista, no NIfTI)."""

    volume: object = None

    def read(self, path, lazy=False, max_voxels=None):
        vol, s = self.volume, self.stride
        if s == 1:
            return vol
        spacing = tuple(float(v) * s if np.isfinite(v) else float(s) for v in vol.spacing)  # as io._finish
        return dataclasses.replace(vol, data=vol.data[::s, ::s, ::s], spacing=spacing)


def real_cache_path(volume_dir: Path, fname: str) -> Path:
    return Path(volume_dir) / f"{fname}.npz"


def save_real(path: Path, vol) -> None:
    """A real volume as read here (values in the source dtype, spacing, origin, name, dtype, fill
    value), for a host that cannot read its file format (no pyvista for NIfTI)."""
    meta = {k: getattr(vol, k) for k in ("spacing", "origin", "name", "source_dtype", "path", "fill_value")}
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez_compressed(tmp, data=vol.data, meta=np.array(json.dumps(meta, default=float)))
    os.replace(tmp, path)


def load_real(path: Path):
    from warpgauss.readers import Volume

    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        data = z["data"]
    meta["spacing"], meta["origin"] = tuple(meta["spacing"]), tuple(meta["origin"])
    return Volume(data=data, **meta)


def volumes(args):
    """(label, load_field source kwargs, raw array in source units, its .npy path or None) per volume.

    With ``--volume-dir`` a real volume is read from ``<dir>/<file name>.npz`` when that exists,
    else from ``--data-dir`` and then written there (so that a host that cannot read the format
    gets the same values, spacing and name: the same header, the same byte budget).
    """
    from warpgauss.readers import read_volume

    for name in [x for x in args.fields.split(",") if x]:
        path = example_path(args.volume_dir, name, args.size) if args.volume_dir else None
        if path is not None and path.is_file():
            raw = np.load(path, mmap_mode="r")  # written by generate_examples: a plain float32 array
        else:
            raw, path = generate(name, args.size, seed=0), None
        yield f"{name} {args.size}^3", {"source": np.asarray(raw)}, raw, path
    real = args.real
    data_dir = Path(getattr(args, "data_dir", None) or DATA_DIR)
    if real in ("", "none"):
        return
    if real == "all":
        if not data_dir.is_dir():
            print(f"no {data_dir}: no real volumes", flush=True)
            return
        names = sorted(p.name for p in data_dir.iterdir() if p.name != "README.md")
    else:
        names = real.split(",")
    for fname in names:
        path = data_dir / fname
        cache = real_cache_path(args.volume_dir, fname) if args.volume_dir else None
        if cache is not None and cache.is_file():
            vol = load_real(cache)
            print(f"{fname}: read from {cache}", flush=True)
        elif path.is_file():
            vol = read_volume(path)
            if cache is not None:
                Path(args.volume_dir).mkdir(parents=True, exist_ok=True)
                save_real(cache, vol)
        else:
            print(f"skip {fname}: not in {data_dir}" + (f" nor {cache}" if cache else ""), flush=True)
            continue
        stride = 1
        while np.prod(vol.data.shape) / stride**3 > args.max_voxels:
            stride += 1
        raw = vol.data[::stride, ::stride, ::stride]
        shape = "x".join(str(s) for s in raw.shape[::-1])
        yield (
            f"{fname} {shape}" + (f" (stride {stride})" if stride > 1 else ""),
            {
                "source": str(path),
                "read": _ReadVolume(stride=stride, volume=vol),
            },
            raw,
            None,
        )


# ---------------------------------------------------------------------------- benchmark


def _write(result: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    tmp.write_text(json.dumps(result, indent=2, default=str) + "\n")
    os.replace(tmp, out)


def _print(label: str, row: dict) -> None:
    print(
        f"{label[:34]:34s} {row['codec']:17s} {row['param']:>16s}  ratio {row['ratio']:9.2f}  "
        f"PSNR {row['psnr_db']:7.2f} dB  enc {row['encode_s']:8.3f} s  dec {row['decode_s']:7.3f} s",
        flush=True,
    )


def _available(module: str) -> str | None:
    try:
        from importlib.metadata import version

        if module == "numcodecs_wasm_sperr":
            _sperr_class()
        else:
            __import__(module)
        return version({"pysz": "pysz", "zfpy": "zfpy", "numcodecs_wasm_sperr": "numcodecs-wasm-sperr"}[module])
    except Exception:  # noqa: BLE001 - not installed (or broken): the codec is skipped
        return None


def _pool(workers: int):
    """Worker processes that import this file afresh (spawn: no copy of a parent's CUDA context)."""
    import multiprocessing as mp
    import sys
    from concurrent.futures import ProcessPoolExecutor

    here = str(Path(__file__).resolve().parent)
    if here not in sys.path:  # the workers import this module by name
        sys.path.insert(0, here)
    return ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"))


def bench_warpgauss(label, src, raw, args, dev, add) -> tuple[dict, Truth, list[tuple[int, float, float]]]:
    """warpgauss rows for one volume: one model per budget, the volume read and analysed once.

    Returns the volume's entry fields, its Truth and (N, full ratio, compact ratio) per budget.
    """
    t0 = time.perf_counter()
    f, info = load_field(src["source"], src.get("read"))
    load_s = time.perf_counter() - t0
    truth = Truth(raw, f.vmin, f.vmax, f.mask)
    n_max = seed_limit(f.eligible, f.occupied)
    meta = {
        "shape_xyz": list(f.shape_xyz),
        "source_dtype": f.source_dtype,
        "source_bytes": f.source_bytes,
        "stride": info["stride"],
        "value_range": [f.vmin, f.vmax],
        "masked_voxels": info["masked_voxels"],
        "n_max": n_max,
        "load_seconds": load_s,
    }
    sb = f.source_bytes
    refine = resolve_refine(None, args.preset, args.iterations, None)
    budgets = sorted({b for b in args.budgets if b <= n_max})
    meta["warpgauss_budgets"] = budgets
    cache: dict = {}
    ratios = []
    for i, n in enumerate(budgets):
        opts = EncodeOptions(budget=n, seed=0, allocation=AllocationConfig(), refine=refine, self_test=i == 0)
        timer = StageRecorder()
        model = encode_field(f, opts, device=dev, timer=timer, input_info=info, evaluate=False, cache=cache)
        stages = {s.name: s.seconds for s in timer.stages}
        enc = sum(stages.values()) + (cache["seconds"] if "S1a" not in stages else 0.0)
        if (model.source_bytes / model.file_size(False)) < args.min_ratio:
            print(
                f"{label}: budget {n} gives ratio {(model.source_bytes / model.file_size(False)):.2f} < {args.min_ratio}: skipped",
                flush=True,
            )
            continue
        ref = model.report["refinement"]
        t0 = time.perf_counter()
        dec = model.decode(device=dev, normalised=True)
        dec_s = time.perf_counter() - t0
        common = {"n": n, "iterations": ref.get("iterations_done", 0), "samples": ref.get("samples"), "stages": stages}
        add(
            {
                "codec": "wg-full",
                "param": f"N={n}",
                "ratio": (model.source_bytes / model.file_size(False)),
                "bytes": model.file_size(False),
                "psnr_db": truth.psnr(dec, normalised=True),
                "encode_s": enc,
                "decode_s": dec_s,
                **common,
            }
        )
        del dec
        with tempfile.TemporaryDirectory() as td:
            p = Path(td) / "m.wgs"
            t0 = time.perf_counter()
            nbytes = model.save(p, compact=True)
            save_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            cm = Model.load(p)
            dec = cm.decode(device=dev, normalised=True)
            dec_s = time.perf_counter() - t0
        assert nbytes == model.file_size(True), (nbytes, model.file_size(True))
        add(
            {
                "codec": "wg-compact",
                "param": f"N={n}",
                "ratio": sb / nbytes,
                "bytes": nbytes,
                "psnr_db": truth.psnr(dec, normalised=True),
                "encode_s": enc + save_s,
                "decode_s": dec_s,
                **common,
            }
        )
        ratios.append((n, (model.source_bytes / model.file_size(False)), sb / nbytes))
        del dec, model
    return meta, truth, ratios


def _volume_meta(f, info, load_s: float) -> dict:
    return {
        "shape_xyz": list(f.shape_xyz),
        "source_dtype": f.source_dtype,
        "source_bytes": f.source_bytes,
        "stride": info["stride"],
        "value_range": [f.vmin, f.vmax],
        "masked_voxels": info["masked_voxels"],
        "n_max": seed_limit(f.eligible, f.occupied),
        "load_seconds": load_s,
    }


def volume_meta(src) -> tuple[dict, np.ndarray | None]:
    """The volume entry's fields and the valid-voxel mask (None: all valid), warpgauss not run."""
    t0 = time.perf_counter()
    f, info = load_field(src["source"], src.get("read"))
    return _volume_meta(f, info, time.perf_counter() - t0), f.mask


def bench_warpgauss_ratios(label, src, raw, args, dev, add, ratios=None) -> tuple[dict, Truth]:
    """warpgauss rows for one volume at the fixed ratios ``args.ratios``, one full encode each.

    The options are those of ``warpgauss encode VOLUME --ratio R`` (coded format, default
    refinement, sampled EV, self-test once per process and device: the warm-up's); only the
    loaded field is shared between the encodes (stage P is not timed). Each model is saved to a
    temporary ``.wgs``: its size gives the ratio, and its reload's full-grid decode the PSNR.
    """
    t0 = time.perf_counter()
    f, info = load_field(src["source"], src.get("read"))
    meta = _volume_meta(f, info, time.perf_counter() - t0)
    truth = Truth(raw, f.vmin, f.vmax, f.mask)
    truth.codec_input = None  # only the reference codecs compress it
    sb = f.source_bytes
    refine = resolve_refine(None, args.preset, args.iterations, None)
    meta["warpgauss_ratios"] = list(args.ratios)
    for r in args.ratios if ratios is None else ratios:
        opts = EncodeOptions(ratio=r, seed=0, allocation=AllocationConfig(), refine=refine, self_test=True, format=args.format)
        timer = StageRecorder()
        t0 = time.perf_counter()
        try:
            model = encode_field(f, opts, device=dev, timer=timer, input_info=info, evaluate=not args.no_evaluate)
        except WarpgaussError as e:  # e.g. no room for a Gaussian at this ratio
            print(f"{label}: ratio {r:g}: {e}", flush=True)
            meta.setdefault("unreachable", []).append({"codec": "wg", "target_ratio": r, "error": str(e)})
            continue
        enc_s = time.perf_counter() - t0
        rep = model.report
        with tempfile.TemporaryDirectory() as td:
            p = Path(td) / "m.wgs"
            t0 = time.perf_counter()
            model.save(p, encoding=encoding_of(opts))
            save_s = time.perf_counter() - t0
            nbytes = p.stat().st_size
            del model
            t0 = time.perf_counter()
            loaded = Model.load(p)
            dec = loaded.decode(device=dev, normalised=True)
            dec_s = time.perf_counter() - t0
        ref = rep["refinement"]
        stages = {s.name: s.seconds for s in timer.stages}
        add(
            {
                "codec": "wg",
                "param": f"N={loaded.n}",
                "target_ratio": r,
                "ratio": sb / nbytes,
                "bytes": nbytes,
                "psnr_db": truth.psnr(dec, normalised=True),
                "encode_s": enc_s + save_s,
                "decode_s": dec_s,
                "n": loaded.n,
                "format": rep["budget"]["format"],
                "save_s": save_s,
                "self_test_s": 0.0 if (ref.get("self_test") or {}).get("reused", True) else ref["self_test"].get("seconds", 0.0),
                "stages": stages,
                "iterations": ref.get("iterations_done", 0),
                "samples": ref.get("samples"),
                "refinement_s": ref.get("seconds"),
                "refinement_stop": ref.get("stop"),
                "report_psnr_db": rep.get("psnr_db"),  # EV: 500,000 sampled voxels (what the CLI prints)
                "budget": rep["budget"],
                "skipped": rep.get("skipped"),
            }
        )
        del dec, loaded
    return meta, truth


def codec_plan(args, meta: dict, ratios, files: dict) -> tuple[list[dict], list[dict]]:
    """The reference-codec runs for one volume: (independent runs, SZ3 runs matched to warpgauss).

    The matched SZ3 runs go second so that the SZ3 curve's (bound, ratio) pairs can bracket them.
    """
    sb, (vmin, vmax) = meta["source_bytes"], meta["value_range"]
    rng = vmax - vmin
    n_voxels = int(np.prod(meta["shape_xyz"]))
    base = {"source_bytes": sb, "vmin": vmin, "vmax": vmax, **files}
    first, matched = [], []
    if "sz3" in args.codecs:
        first += [{**base, "kind": "sz3", "eb": rel * rng} for rel in args.sz3_bounds]
        for n, full, compact in ratios:
            for fmt, target in (("full", full), ("compact", compact)):
                if fmt == "compact" and not args.match_compact:
                    continue
                matched.append(
                    {
                        **base,
                        "kind": "sz3-matched",
                        "target": target,
                        "tol": args.match_tol,
                        "matched_to": {"n": n, "format": fmt, "ratio": target},
                    }
                )
    if "zfp" in args.codecs:
        for n, full, compact in ratios:
            for fmt, target in (("full", full), ("compact", compact)):
                rate = 8.0 * sb / (n_voxels * target)
                if rate < args.zfp_min_rate:  # zfpy 1.0.1 corrupts the heap (malloc abort) at 0.107 bits/value
                    print(f"zfp rate {rate:.3g} < {args.zfp_min_rate} bits/value (N={n}, {fmt}): not run", flush=True)
                    continue
                first.append({**base, "kind": "zfp-rate", "rate": rate, "matched_to": {"n": n, "format": fmt, "ratio": target}})
        first += [{**base, "kind": "zfp-rate", "rate": r} for r in args.zfp_rates]
        first += [{**base, "kind": "zfp-acc", "tol": rel * rng} for rel in args.zfp_tols]
    return first, matched


def ratio_plan(args, meta: dict, files: dict) -> tuple[list[dict], list[dict], list[dict]]:
    """The reference-codec runs for one volume at the fixed ratios ``args.ratios``:
    (independent runs, SZ3 runs searched to each ratio, the ratios a codec cannot reach).

    The SZ3 curve (``--sz3-bounds``) runs first: its (bound, ratio) pairs bracket the searches.
    """
    sb, (vmin, vmax) = meta["source_bytes"], meta["value_range"]
    rng = vmax - vmin
    n_voxels = int(np.prod(meta["shape_xyz"]))
    base = {"source_bytes": sb, "vmin": vmin, "vmax": vmax, "tol": args.match_tol, **files}
    first, matched, unreachable = [], [], []
    if "sz3" in args.codecs:
        first += [{**base, "kind": "sz3", "eb": rel * rng} for rel in args.sz3_bounds]
        matched += [{**base, "kind": "sz3-matched", "target": r, "matched_to": {"target_ratio": r}} for r in args.ratios]
    for codec, kind, min_rate in (("zfp", "zfp-matched", args.zfp_min_rate), ("sperr", "sperr", 0.0)):
        if codec not in args.codecs:
            continue
        for r in args.ratios:
            rate = 8.0 * sb / (n_voxels * r)  # bits per value: 8 x source itemsize / R
            if rate < min_rate:
                name = "zfp-rate-matched"
                unreachable.append(
                    {
                        "codec": name,
                        "target_ratio": r,
                        "rate_needed": rate,
                        "min_rate": min_rate,
                        "max_ratio": 8.0 * sb / (n_voxels * min_rate),
                    }
                )
                print(f"{name}: ratio {r:g} needs {rate:.3g} bits/value < {min_rate} (--zfp-min-rate): not run", flush=True)
                continue
            first.append({**base, "kind": kind, "target": r, "rate": rate, "min_rate": min_rate, "matched_to": {"target_ratio": r}})
    return first, matched, unreachable


def task_key(x: dict) -> tuple:
    """What a codec run is, the same for a planned task and the row it produced (``--resume``)."""
    m = x.get("matched_to")
    fixed = bool(m) and "target_ratio" in m  # a --ratios run: the target says what it is
    kind = x.get("kind") or {"zfp-rate-matched": "zfp-matched" if fixed else "zfp-rate"}.get(x["codec"], x["codec"])
    if fixed:
        return (kind, ("ratio", float(m["target_ratio"])))
    match = (int(m["n"]), m["format"]) if m else None
    if kind == "sz3-matched":
        return (kind, match)
    names = {"sz3": ("eb", "abs_error_bound"), "zfp-rate": ("rate", "rate_bits_per_value"), "zfp-acc": ("tol", "tolerance")}[kind]
    value = x[names[0]] if names[0] in x else x[names[1]]
    return (kind, match, float(value))


def _reused_ratios(entry: dict) -> list[tuple[int, float, float]] | None:
    """(N, full ratio, compact ratio) of every budget of a previous run's volume entry, or None
    when some budget's warpgauss rows are missing (then the volume is measured again)."""
    rows = {(r["codec"], r.get("n")): r for r in entry.get("rows", ()) if r["codec"] in ("wg-full", "wg-compact")}
    budgets = entry.get("warpgauss_budgets")
    if not budgets or any(("wg-full", n) not in rows or ("wg-compact", n) not in rows for n in budgets):
        return None
    return [(n, rows[("wg-full", n)]["ratio"], rows[("wg-compact", n)]["ratio"]) for n in budgets]


def run_codecs(plans: list[tuple[str, list[dict], list[dict]]], workers: int, add, seen: dict | None = None) -> None:
    """Run every volume's codec plan, in ``workers`` processes (0: here, one after the other).

    ``add(label, row)`` records a row. Each matched SZ3 run starts from the (bound, ratio) pairs of
    its volume's SZ3 curve (and those of ``seen[label]``, measured earlier).
    """
    seen = {label: list((seen or {}).get(label, ())) for label, _, _ in plans}

    def done(label, row):
        if row["codec"] == "sz3":
            seen[label].append((row["abs_error_bound"], row["ratio"]))
        add(label, row)

    if workers <= 0:
        for label, first, _ in plans:
            for task in first:
                done(label, codec_task(task))
        for label, _, matched in plans:
            for task in matched:
                done(label, codec_task({**task, "seen": seen[label]}))
        return
    from concurrent.futures import as_completed

    with _pool(workers) as pool:
        futures = {pool.submit(codec_task, t): label for label, first, _ in plans for t in first}
        for fut in as_completed(futures):
            done(futures[fut], fut.result())
        futures = {pool.submit(codec_task, {**t, "seen": seen[label]}): label for label, _, matched in plans for t in matched}
        for fut in as_completed(futures):
            done(futures[fut], fut.result())


def _floats(text: str) -> tuple[float, ...]:
    return tuple(float(x) for x in text.split(",") if x)


CODEC_MODULES = {"sz3": "pysz", "zfp": "zfpy", "sperr": "numcodecs_wasm_sperr"}


def _missing_wg(entry: dict | None, args) -> list[float] | None:
    """The ratios of ``args.ratios`` a previous run's volume entry has no warpgauss row for
    (nor found unreachable), or None when there is no usable entry. Its rows are kept."""
    if not entry or "source_bytes" not in entry:
        return None
    if args.no_warpgauss:
        return []
    have = {float(r["target_ratio"]) for r in entry.get("rows", ()) if r["codec"] == "wg"}
    have |= {float(u["target_ratio"]) for u in entry.get("unreachable", ()) if u["codec"] == "wg"}
    return [r for r in args.ratios if float(r) not in have]


def _result(args, argv, dev: str, wp, refine, versions: dict, warm: float | None, gen_s: dict) -> dict:
    """The result file's head: the device, the versions, the command and the settings of the run."""
    fixed = bool(args.ratios)
    settings = {
        "match_tol": args.match_tol,
        "codec_workers": args.workers,
        "codec_timing": "single-threaded codec calls"
        + (f", {args.workers} at a time in separate processes (after all warpgauss rows)" if args.workers > 0 else ""),
        "psnr": "10 log10(1/MSE), full grid, normalised by the volume's finite min/max, masked voxels excluded; same function for every codec",
        "ratio": "source bytes (voxels x source dtype size) / compressed bytes; SZ3 and ZFP compress float32 in source units, "
        "SPERR the float32 field normalised by min/max",
    }
    if fixed:
        settings.update(
            {
                "mode": "fixed ratios",
                "ratios": list(args.ratios),
                "warpgauss": None
                if args.no_warpgauss
                else {
                    "options": "warpgauss encode VOLUME --ratio R"
                    + (f" --preset {args.preset}" if args.preset else "")
                    + (f" --iterations {args.iterations}" if args.iterations is not None else "")
                    + (f" --format {args.format}" if args.format else ""),
                    "format": encoding_of(EncodeOptions(format=args.format)),
                    "preset": args.preset,
                    "evaluate": not args.no_evaluate,
                    "encode_s": "encode call (S1a to EV, reading excluded) + save of the .wgs",
                    "decode_s": "Model.load + full-grid decode",
                },
                "iterations": refine.iterations,
                "samples": refine.samples,
                "zfp_min_rate": args.zfp_min_rate,
            }
        )
    else:
        settings.update(
            {
                "preset": args.preset,
                "iterations": refine.iterations,
                "samples": refine.samples,
                "budgets": args.budgets,
                "min_ratio": args.min_ratio,
            }
        )
    return {
        "benchmark": "rate-distortion at fixed ratios: warpgauss (defaults, coded) vs SZ3, ZFP (fixed rate) and SPERR (bpp)"
        if fixed
        else "rate-distortion: warpgauss (full precision, compact) vs SZ3 (abs error bound) vs ZFP (fixed rate, fixed accuracy)",
        "command": "python benchmarks/rate_distortion/bench_rd.py " + " ".join(argv if argv is not None else __import__("sys").argv[1:]),
        "device": dev,
        "device_name": device_name(dev),
        "cpu_count": os.cpu_count(),
        "host": platform.node(),
        "warp_version": wp.config.version,
        "warpgauss_version": warpgauss.__version__,
        "codec_versions": {"pysz": versions["pysz"], "zfpy": versions["zfpy"], "numcodecs-wasm-sperr": versions["numcodecs_wasm_sperr"]},
        "codecs": args.codecs,
        "warpgauss_run": not args.no_warpgauss,
        "numpy_version": np.__version__,
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "warmup_seconds": warm,
        "generation_seconds": gen_s,
        "settings": settings,
        "volumes": {},
        "complete": False,
    }


def _choose_codecs(ap: argparse.ArgumentParser, args) -> dict:
    """--codecs checked and narrowed to those installed (``args.codecs`` becomes a list); the
    reference codecs' versions (None: not installed)."""
    fixed = bool(args.ratios)
    if args.codecs is None:
        args.codecs = "sz3,zfp,sperr" if fixed else "sz3,zfp"
    wanted = [c for c in args.codecs.split(",") if c and c != "none"]
    unknown = [c for c in wanted if c not in CODEC_MODULES]
    if unknown or ("sperr" in wanted and not fixed):
        ap.error(f"--codecs: {', '.join(unknown) or 'sperr'} not known{'' if unknown else ' without --ratios'}")
    versions = {m: _available(m) for m in ("pysz", "zfpy", "numcodecs_wasm_sperr")}
    args.codecs = [c for c in wanted if versions[CODEC_MODULES[c]]]
    for c in [c for c in wanted if c not in args.codecs]:
        print(f"{c}: not installed (pip install -e '.[bench]'): skipped", flush=True)
    return versions


def _resumed(args, result: dict) -> dict:
    """The volumes of the run ``--resume`` names (none without it), noted in ``result``."""
    if not args.resume:
        return {}
    before = json.loads(Path(args.resume).read_text())
    result["resumed_from"] = str(args.resume)
    # where the reused rows (the warpgauss ones at least) were measured; this run's fields say
    # where the rows it adds were
    result["previous_run"] = {k: before.get(k) for k in ("device", "device_name", "host", "cpu_count", "warp_version", "date", "command")}
    return before["volumes"]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fields", default=",".join(EXAMPLES), help="example fields (comma list; '' for none)")
    ap.add_argument("--size", type=int, default=256, help="example field size (cube edge)")
    ap.add_argument("--real", default="all", help="files in --data-dir: 'all', a comma list, or 'none'")
    ap.add_argument("--data-dir", type=Path, default=DATA_DIR, help="where the real volumes are (default: ../shared/data)")
    ap.add_argument("--max-voxels", type=int, default=256**3, help="stride real volumes down to at most this many voxels")
    ap.add_argument(
        "--ratios",
        type=_floats,
        default=(),
        help="fixed-ratio mode: every codec at these compression ratios (e.g. 10,30,100,300,1000); "
        "warpgauss with its defaults (coded format), instead of the budget ladder",
    )
    ap.add_argument("--no-warpgauss", action="store_true", help="run the reference codecs only (with --ratios)")
    ap.add_argument("--format", default=None, help="--ratios: warpgauss file format (default: the library's, coded)")
    ap.add_argument(
        "--no-evaluate",
        action="store_true",
        help="--ratios: skip warpgauss's stage EV (the CLI runs it; it can keep the analytic model over a worse refined one)",
    )
    ap.add_argument("--budgets", default="2000,8000,32000,128000", help="warpgauss ladder (capped at each volume's N_max)")
    ap.add_argument("--min-ratio", type=float, default=2.0, help="drop budgets whose full-precision ratio is below this")
    ap.add_argument(
        "--preset",
        default=None,
        help="warpgauss refinement preset (ladder default: fast, 300 x 3,072; --ratios default: none, the library's defaults)",
    )
    ap.add_argument("--iterations", type=int, default=None, help="override the preset's iterations (0: analytic)")
    ap.add_argument(
        "--codecs",
        default=None,
        help="reference codecs to run: sz3, zfp, sperr ('none' or '' for none; default sz3,zfp, with --ratios "
        "sz3,zfp,sperr; those not installed are skipped)",
    )
    ap.add_argument("--match-tol", type=float, default=0.02, help="relative ratio tolerance of the SZ3 (and fixed-rate) searches")
    ap.add_argument("--match-compact", action="store_true", help="also match SZ3 to the compact ratios")
    ap.add_argument("--sz3-bounds", type=_floats, default=SZ3_BOUNDS, help="SZ3 curve: error bounds x (max - min)")
    ap.add_argument("--zfp-rates", type=_floats, default=ZFP_RATES, help="ZFP fixed-rate curve: bits per value")
    ap.add_argument("--zfp-tols", type=_floats, default=ZFP_TOLERANCES, help="ZFP fixed-accuracy curve: tolerances x (max - min)")
    ap.add_argument("--zfp-min-rate", type=float, default=ZFP_MIN_RATE, help="lowest ZFP fixed rate run (bits per value)")
    ap.add_argument(
        "--workers",
        type=int,
        default=0,
        help="processes for the codec runs (0: in this process) and for --volume-dir generation; "
        "the codec runs start after every warpgauss row, so they never share the machine with one",
    )
    ap.add_argument(
        "--volume-dir",
        type=Path,
        default=None,
        help="read the example fields from <dir>/<name>_<size>.npy, generating the missing ones first",
    )
    ap.add_argument("--generate-only", action="store_true", help="with --volume-dir: write the fields and stop")
    ap.add_argument(
        "--resume",
        type=Path,
        default=None,
        help="a previous run's JSON: keep its rows, skip the warpgauss budgets it measured and run only the codec settings it lacks",
    )
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="benchmarks/results/rate_distortion/bench_rd_cpu.json")
    return ap


def main(argv=None) -> dict:
    ap = _parser()
    args = ap.parse_args(argv)
    fixed = bool(args.ratios)
    if args.no_warpgauss and not fixed:
        ap.error("--no-warpgauss needs --ratios")
    if not fixed and args.preset is None:
        args.preset = "fast"
    args.budgets = [int(b) for b in args.budgets.split(",") if b]
    fields = [x for x in args.fields.split(",") if x]
    gen_s = {}
    if args.volume_dir is not None:
        t0 = time.perf_counter()
        gen_s = generate_examples(fields, args.size, args.volume_dir, args.workers)
        print(
            f"generated {sorted(gen_s) or 'nothing'} at {args.size}^3 in {time.perf_counter() - t0:.1f} s "
            f"({', '.join(f'{k} {v:.1f} s' for k, v in gen_s.items())})",
            flush=True,
        )
        if args.generate_only:
            return {"generated": gen_s}
    versions = _choose_codecs(ap, args)

    wp = warp()
    dev = resolve_device(args.device)
    warm = None
    if not args.no_warpgauss:
        t0 = time.perf_counter()
        warpgauss.encode(generate("vortex", 16), budget=50, device=dev, iterations=2, samples=64)  # compile kernels
        warm = time.perf_counter() - t0
    refine = resolve_refine(None, args.preset, args.iterations, None)
    out = Path(args.out)
    result = _result(args, argv, dev, wp, refine, versions, warm, gen_s)

    def add(label, row):
        result["volumes"][label]["rows"].append(row)
        _print(label, row)
        _write(result, out)

    prev = _resumed(args, result)
    plans, seen = [], {}
    with tempfile.TemporaryDirectory(prefix="bench_rd_") as work:
        for k, (label, src, raw, path) in enumerate(volumes(args)):
            ratios = None if fixed else _reused_ratios(prev.get(label, {}))
            missing = _missing_wg(prev.get(label), args) if fixed else None
            if missing:  # some warpgauss ratios measured: keep those rows (and the codec rows), run the rest
                print(f"{label}: rows reused from {args.resume}; warpgauss at {', '.join(f'{r:g}' for r in missing)}", flush=True)
                result["volumes"][label] = json.loads(json.dumps(prev[label]))
                meta, truth = bench_warpgauss_ratios(label, src, raw, args, dev, lambda row, lb=label: add(lb, row), missing)
                valid = truth.valid
                del truth
                result["volumes"][label].update({**meta, "unreachable": prev[label].get("unreachable", []) + meta.get("unreachable", [])})
                meta = {k_: v for k_, v in result["volumes"][label].items() if k_ != "rows"}
            elif missing is not None or ratios is not None:
                # its warpgauss rows are measured: keep them (and its codec rows)
                result["volumes"][label] = json.loads(json.dumps(prev[label]))
                meta = {k_: v for k_, v in prev[label].items() if k_ != "rows"}
                valid = load_field(src["source"], src.get("read"))[0].mask if meta.get("masked_voxels") else None
                print(f"{label}: rows reused from {args.resume}", flush=True)
            elif fixed and args.no_warpgauss:
                result["volumes"][label] = {"rows": []}
                meta, valid = volume_meta(src)
                result["volumes"][label].update(meta)
            elif fixed:
                result["volumes"][label] = {"rows": []}
                meta, truth = bench_warpgauss_ratios(label, src, raw, args, dev, lambda row, lb=label: add(lb, row))
                result["volumes"][label].update(meta)
                valid = truth.valid
                del truth
            else:
                result["volumes"][label] = {"rows": []}
                meta, truth, ratios = bench_warpgauss(label, src, raw, args, dev, lambda row, lb=label: add(lb, row))
                result["volumes"][label].update(meta)
                valid = truth.valid
                del truth
            _write(result, out)
            if not args.codecs:
                del raw
                continue
            files = {"raw": str(path) if path is not None else None, "valid": None}
            if path is None:  # the workers map the volume from a file
                files["raw"] = str(Path(work) / f"{k}.npy")
                np.save(files["raw"], np.ascontiguousarray(raw))
            if valid is not None:
                files["valid"] = str(Path(work) / f"{k}_valid.npy")
                np.save(files["valid"], valid)
            rows = result["volumes"][label]["rows"]
            done = {task_key(r) for r in rows if not r["codec"].startswith("wg")}
            if fixed:
                first, matched, unreachable = ratio_plan(args, meta, files)
                entry = result["volumes"][label]
                entry["unreachable"] = [u for u in entry.get("unreachable", []) if u["codec"] == "wg"] + unreachable
            else:
                first, matched = codec_plan(args, meta, ratios, files)
            plans.append((label, [t for t in first if task_key(t) not in done], [t for t in matched if task_key(t) not in done]))
            seen[label] = [(r["abs_error_bound"], r["ratio"]) for r in rows if r["codec"] == "sz3"]
            del raw
        t0 = time.perf_counter()
        run_codecs(plans, args.workers, add, seen)
        result["codec_wall_seconds"] = time.perf_counter() - t0
    result["complete"] = True
    _write(result, out)
    v = result["codec_versions"]
    print(
        f"\n{result['device_name']}, Warp {result['warp_version']}, pysz {v['pysz']}, zfpy {v['zfpy']}, "
        f"numcodecs-wasm-sperr {v['numcodecs-wasm-sperr']} -> {out}"
    )
    return result


if __name__ == "__main__":
    main()
