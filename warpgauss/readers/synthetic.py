"""Built-in example volumes that stand in for the paper's datasets (SPEC section 9).

Four fields of the same character as the paper's test volumes, at any size, deterministic by seed:

==============  =============================================================================
``vortex``      smooth, fully occupied velocity magnitude of a few vortex tubes in a
                low-wavenumber solenoidal flow (the paper's Vortex)
``bubbles``     a sparse plume of bubbles with sharp (tanh, ~1 voxel) boundaries, 2-3 %
                occupancy (Bubble Plume)
``turbulence``  a fully occupied, multi-scale, log-normal random field with a k^-5/3 energy
                spectrum (Miranda)
``interface``   a thin, multi-mode perturbed mixing layer, heavy fluid below, ~50 % occupancy
                (Richtmyer-Meshkov)
==============  =============================================================================

Every field is defined in normalised coordinates ``p = (i + 0.5) / L`` per axis, where ``L`` is the
longest axis in voxels, so voxels stay isotropic and a 64^3 and a 128^3 volume show the same field at
two resolutions. What is resolution-dependent by design: the bubble and interface edges (a fixed
number of voxels wide, i.e. as sharp as the grid allows) and the turbulence's smallest scales (its
spectrum runs up to a dissipation cut-off that follows the grid). The large scales of ``turbulence``
come from a size-independent random stream, so they too agree across resolutions.

Band-limited smooth components are evaluated exactly at any resolution with separable partial
DFTs (two small matrix products and one per z-slab), analytic terms in z-slabs, and the turbulence
with one float32 inverse real FFT done in place, so memory stays near two copies of the volume.

Example:
    >>> from warpgauss.readers.synthetic import generate, raw_name
    >>> v = generate("bubbles", 64, seed=1)          # float32, (nz, ny, nx), values in [0, 1]
    >>> v.tofile(raw_name("bubbles", 64))            # bubbles_64x64x64_float32.raw
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from typing import NamedTuple

import numpy as np

from ..errors import WarpgaussError

EXAMPLES: dict[str, str] = {
    "vortex": "smooth, fully occupied velocity magnitude of vortex tubes in a low-wavenumber flow (like Vortex)",
    "bubbles": "sparse plume of sharp-edged bubbles, 2-3 % occupancy (like Bubble Plume)",
    "turbulence": "fully occupied multi-scale log-normal field, k^-5/3 energy spectrum (like Miranda)",
    "interface": "thin multi-mode perturbed mixing layer, heavy fluid below, ~50 % occupancy (like Richtmyer-Meshkov)",
}

MIN_SIZE = 4  # voxels per axis
SLAB_VOXELS = 1 << 20  # voxels per z-slab in slab-wise passes (4 MiB of float32)
SLAB_THREADS = 16  # threads that compute the vortex field's slabs (at most one per core)
TWO_PI = 2.0 * np.pi

# vortex: solenoidal background modes |k| <= VORTEX_K (cycles per L), energy peak near VORTEX_K_PEAK
VORTEX_K = 3
VORTEX_K_PEAK = 1.5
VORTEX_TUBES = (3, 5)  # number of tubes, inclusive range
VORTEX_CORE = (0.09, 0.15)  # Gaussian core radius of a tube, fraction of L
VORTEX_SWIRL = (1.2, 2.2)  # peak swirl speed of a tube, in units of the background rms speed
VORTEX_MEAN_FLOW = 0.6  # uniform flow speed, in units of the background rms speed

# bubbles: a vertical plume (along z) of spheres
BUBBLE_OCCUPANCY = 0.025  # bubbles are added until this fraction of voxels is occupied
BUBBLE_RADIUS = (0.02, 0.045)  # fraction of L at the bottom; grows by BUBBLE_GROWTH at the top
BUBBLE_GROWTH = 0.5
BUBBLE_SPREAD = (0.07, 0.2)  # plume's horizontal std (fraction of the smaller horizontal extent), bottom/top
BUBBLE_VALUE = (0.5, 1.0)  # interior value of a bubble
BUBBLE_TILT = 0.2  # interior gradient: value changes by up to +-this fraction across a bubble
BUBBLE_EDGE = 1.0  # tanh edge width in voxels
BUBBLE_BOX = 4.5  # a bubble is drawn within radius + BUBBLE_BOX edge widths ...
BUBBLE_FLOOR = 1e-3  # ... and values below this are set to exactly 0 (the tanh tail; 0.02 is occupied)
MAX_BUBBLES = 100_000
OCCUPIED = 0.02  # normalised value above which a voxel is occupied (SPEC section 2)

# turbulence: von Karman energy spectrum E(k) ~ (k/k0)^4 / (1 + (k/k0)^2)^(17/6) (k^-5/3 above k0),
# times a dissipation roll-off exp(-(k/kd)^2) with kd a fraction of the grid's Nyquist wavenumber
TURB_K0 = 1.5  # energy-containing wavenumber, cycles per L
TURB_KD = 0.45  # dissipation wavenumber, fraction of the Nyquist wavenumber L/2
TURB_LOW_K = 8  # wavenumber indices up to this come from a size-independent random stream
TURB_LOGNORMAL = 0.4  # V = exp(TURB_LOGNORMAL * g / std(g)): intermittency
FFT_BLOCK = 1 << 22  # complex entries per block of the in-place 2D inverse FFT

# interface: heavy fluid below z = h(x, y) + mixing displacement
IFACE_MODES = (2, 10)  # interface perturbation wavenumbers (cycles per L), inclusive
IFACE_AMPLITUDE = 0.035  # rms interface displacement, fraction of L
IFACE_ASYMMETRY = 6.0  # spikes of heavy fluid narrower than bubbles of light fluid (1/L units)
IFACE_EDGE = 1.0  # tanh half-width of the interface, voxels
MIX_K = 16  # small-scale mixing modes up to this wavenumber (cycles per L) ...
MIX_K_MIN = 6  # ... and from this one
MIX_AMPLITUDE = 0.012  # rms mixing displacement of the interface, fraction of L
MIX_WIDTH = 0.05  # mixing zone half-width (Gaussian envelope), fraction of L
BULK_K = 3  # heavy-fluid density variation: modes up to this wavenumber
BULK_AMPLITUDE = 0.16  # ... depth of the variation (heavy fluid ~ 0.84..1); sets the gradient top-10 % share


def generate(name: str, size: int | tuple[int, int, int] = 64, seed: int = 0) -> np.ndarray:
    """Generate a built-in example volume.

    Args:
        name: One of :data:`EXAMPLES` (``vortex``, ``bubbles``, ``turbulence``, ``interface``).
        size: Voxels per axis: an int for a cube or an ``(x, y, z)`` tuple; at least 4 on each axis.
        seed: Random seed; the same ``(name, size, seed)`` gives a bit-identical array.

    Returns:
        float32 C-order array of shape ``(nz, ny, nx)`` (x fastest) with min exactly 0 and max exactly 1.

    Raises:
        WarpgaussError: Unknown name, a size below 4 voxels on any axis, or a negative seed.
    """
    make = _generator(name)
    shape_xyz = _shape_xyz(size)
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise WarpgaussError(f"seed must be a non-negative int, got {seed!r}")
    rng = np.random.default_rng(int(seed))
    volume = make(shape_xyz, rng)
    return unit_range(volume)


SERIES_TURN_DEGREES = 4.0  # an evolving example turns this much about the z axis per timestep


def generate_series(
    name: str, size: int | tuple[int, int, int] = 64, steps: int = 16, seed: int = 0, turn_degrees: float = SERIES_TURN_DEGREES
) -> Iterator[np.ndarray]:
    """An evolving example: timestep ``t`` is :func:`generate`'s volume turned ``t x turn_degrees``
    about the grid's z axis (linear interpolation, edges held), renormalised to [0, 1]. Timestep
    0 is :func:`generate`'s volume; consecutive steps differ as an advected field does (a rotating
    vortex, a turning interface), which is what a warm start meets.

    Yields:
        ``steps`` float32 arrays ``(nz, ny, nx)``.
    """
    from scipy.ndimage import rotate

    if not isinstance(steps, (int, np.integer)) or steps < 1:
        raise WarpgaussError(f"steps must be a positive int, got {steps!r}")
    base = generate(name, size, seed)
    yield base
    for t in range(1, int(steps)):
        turned = rotate(base, t * float(turn_degrees), axes=(1, 2), reshape=False, order=1, mode="nearest")
        yield unit_range(turned.astype(np.float32))


def raw_name(name: str, size: int | tuple[int, int, int]) -> str:
    """File name in the Open SciVis convention, e.g. ``vortex_128x128x128_float32.raw``.

    Args:
        name: One of :data:`EXAMPLES`.
        size: As for :func:`generate`.

    Returns:
        ``<name>_<nx>x<ny>x<nz>_float32.raw``.
    """
    _generator(name)
    nx, ny, nz = _shape_xyz(size)
    return f"{name}_{nx}x{ny}x{nz}_float32.raw"


# ---------------------------------------------------------------------------------------------
# validation, coordinates, normalisation


def _generator(name: str) -> Callable[[tuple[int, int, int], np.random.Generator], np.ndarray]:
    gens = {"vortex": _vortex, "bubbles": _bubbles, "turbulence": _turbulence, "interface": _interface}
    if name not in gens:
        raise WarpgaussError(f"unknown example {name!r}; available examples: {', '.join(EXAMPLES)}")
    return gens[name]


def _shape_xyz(size: int | tuple[int, int, int]) -> tuple[int, int, int]:
    if isinstance(size, (int, np.integer)):
        dims: tuple = (size,) * 3
    else:
        dims = tuple(size) if isinstance(size, (tuple, list)) else ()
    if len(dims) != 3 or not all(isinstance(d, (int, np.integer)) and not isinstance(d, bool) for d in dims):
        raise WarpgaussError(f"size must be an int or an (x, y, z) tuple of 3 ints, got {size!r}")
    if min(dims) < MIN_SIZE:
        raise WarpgaussError(f"size {size!r} is too small: examples need at least {MIN_SIZE} voxels on each axis")
    return (int(dims[0]), int(dims[1]), int(dims[2]))


def _coords(shape_xyz: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Voxel-centre coordinates (x, y, z) in units of the longest axis L, and L."""
    length = max(shape_xyz)
    x, y, z = ((np.arange(n) + 0.5) / length for n in shape_xyz)
    return x, y, z, length


def _slabs(shape_zyx: tuple[int, int, int]) -> Iterator[tuple[int, int]]:
    """(z0, z1) ranges of about :data:`SLAB_VOXELS` voxels."""
    nz, ny, nx = shape_zyx
    step = max(1, SLAB_VOXELS // (ny * nx))
    for z0 in range(0, nz, step):
        yield z0, min(nz, z0 + step)


def unit_range(v: np.ndarray) -> np.ndarray:
    """Map ``v`` in place to [0, 1] by its min/max: min becomes exactly 0 and max exactly 1.

    (v - lo) / (hi - lo) in float32 is monotone in v, is 0 at lo and x / x = 1 at hi.
    """
    lo, hi = v.min(), v.max()
    span = np.float32(hi - lo)
    if not span > 0:  # cannot happen for these fields; keep the contract anyway
        v.fill(0)
        v.flat[0] = 1
        return v
    for z0, z1 in _slabs(v.shape):
        np.subtract(v[z0:z1], lo, out=v[z0:z1])
        np.divide(v[z0:z1], span, out=v[z0:z1])
    return v


# ---------------------------------------------------------------------------------------------
# band-limited fields by separable partial DFTs


def _random_coefficients(
    rng: np.random.Generator, kmax: int, amplitude: Callable[[np.ndarray], np.ndarray], dims: int = 3, channels: int = 1
) -> np.ndarray:
    """Complex Gaussian coefficients on the integer wavenumbers ``-kmax..kmax`` per axis.

    Args:
        rng: Random stream (drawn from in a size-independent order).
        kmax: Largest wavenumber index per axis.
        amplitude: Maps |k| (cycles per L) to the coefficient's standard amplitude (0 drops a mode).
        dims: 2 for (ky, kx) or 3 for (kz, ky, kx) coefficient grids.
        channels: Leading vector channels (3 for a velocity).

    Returns:
        complex128 array ``(channels, *(2 kmax + 1,) * dims)``.
    """
    k = np.arange(-kmax, kmax + 1, dtype=np.float64)
    kk = np.sqrt(sum(g**2 for g in np.meshgrid(*([k] * dims), indexing="ij")))
    shape = (channels,) + kk.shape
    c = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    return c * amplitude(kk)


def _phase_matrix(coord: np.ndarray, kmax: int) -> np.ndarray:
    """exp(2 pi i k p) as (len(coord), 2 kmax + 1)."""
    k = np.arange(-kmax, kmax + 1, dtype=np.float64)
    return np.exp(1j * TWO_PI * np.outer(coord, k))


def _band_2d(coef: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Re sum_k c_k exp(2 pi i (kx x + ky y)) on the (ny, nx) grid, float64."""
    kmax = (coef.shape[-1] - 1) // 2
    return (_phase_matrix(y, kmax) @ coef @ _phase_matrix(x, kmax).T).real


class _Band3D:
    """A real band-limited field Re sum_k c_k exp(2 pi i k.p), evaluated slab by slab.

    The (kz, ky, kx) sum is done as three matrix products: kx and ky once for the whole (ny, nx)
    plane, kz per z-slab as one float32 GEMM (real and imaginary parts stacked), so the cost is
    ~ 4 (2 kmax + 1) flops per voxel and the field is exact at any resolution.
    """

    def __init__(self, coef: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> None:
        kmax = (coef.shape[-1] - 1) // 2
        nk = 2 * kmax + 1
        plane = np.matmul(_phase_matrix(y, kmax)[None], coef @ _phase_matrix(x, kmax).T)  # (kz, ny, nx)
        self._plane = np.concatenate([plane.real, plane.imag]).reshape(2 * nk, -1).astype(np.float32)
        ez = _phase_matrix(z, kmax)
        self._ez = np.concatenate([ez.real, -ez.imag], axis=1).astype(np.float32)  # (nz, 2 nk)
        self._shape = (z.size, y.size, x.size)

    def slab(self, z0: int, z1: int, out: np.ndarray | None = None) -> np.ndarray:
        """Values on z-slices z0..z1-1 as float32 (z1 - z0, ny, nx), written into ``out`` if given."""
        if out is None:
            out = np.empty((z1 - z0,) + self._shape[1:], np.float32)
        np.matmul(self._ez[z0:z1], self._plane, out=out.reshape(z1 - z0, -1))
        return out


# ---------------------------------------------------------------------------------------------
# vortex


def _vortex(shape_xyz: tuple[int, int, int], rng: np.random.Generator) -> np.ndarray:
    """|u| of a random solenoidal low-wavenumber flow + a mean flow + straight Lamb-Oseen tubes."""
    x, y, z, _ = _coords(shape_xyz)
    nx, ny, nz = shape_xyz

    def spectrum(k: np.ndarray) -> np.ndarray:
        e = (k / VORTEX_K_PEAK) ** 4 * np.exp(-2.0 * (k / VORTEX_K_PEAK) ** 2)  # energy E(k)
        a = np.sqrt(e / np.maximum(k, 1e-9) ** 2)
        return np.where((k > 0) & (k <= VORTEX_K + 1e-9), a, 0.0)

    coef = _random_coefficients(rng, VORTEX_K, spectrum, channels=3)
    k = np.arange(-VORTEX_K, VORTEX_K + 1, dtype=np.float64)
    kvec = np.stack(np.meshgrid(k, k, k, indexing="ij"))[::-1]  # (kx, ky, kz) components on the (kz, ky, kx) grid
    k2 = np.maximum((kvec**2).sum(0), 1e-12)
    coef -= kvec * (kvec * coef).sum(0) / k2  # project out the compressive part: div u = 0
    rms = np.sqrt(0.5 * (np.abs(coef) ** 2).sum())  # expected rms speed of Re sum c e^{i k.p}
    coef /= rms
    bands = [_Band3D(coef[c], x, y, z) for c in range(3)]

    direction = rng.standard_normal(3)
    mean_flow = VORTEX_MEAN_FLOW * direction / np.linalg.norm(direction)
    tubes = [_tube(rng, x, y) for _ in range(rng.integers(VORTEX_TUBES[0], VORTEX_TUBES[1] + 1))]

    out = np.empty((nz, ny, nx), np.float32)

    def slab(z0: int, z1: int) -> None:
        zs = z[z0:z1, None, None].astype(np.float32)
        u = [bands[c].slab(z0, z1) for c in range(3)]
        for c in range(3):
            u[c] += np.float32(mean_flow[c])
        for tube in tubes:
            _add_tube(u, tube, zs)
        np.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2], out=out[z0:z1])

    _each_slab(out.shape, slab)
    return out


def _each_slab(shape_zyx: tuple[int, int, int], fn: Callable[[int, int], None]) -> None:
    """fn(z0, z1) for every slab, on up to :data:`SLAB_THREADS` threads (numpy releases the GIL in
    its array work; each slab writes only its own rows, and its values do not depend on which
    thread computes it or when, so the result is the serial one bit for bit)."""
    slabs = list(_slabs(shape_zyx))
    threads = min(SLAB_THREADS, os.cpu_count() or 1, len(slabs))
    if threads <= 1:
        for z0, z1 in slabs:
            fn(z0, z1)
        return
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(threads, thread_name_prefix="warpgauss-generate") as pool:
        for f in [pool.submit(fn, z0, z1) for z0, z1 in slabs]:
            f.result()


class _Tube(NamedTuple):
    planes: list[tuple[np.ndarray, np.float32]]  # per component of t x (p - c): (ny, nx) at z = 0, d/dz
    inv_a2: np.float32  # 1 / core radius^2
    gamma: np.float32  # circulation / 2 pi


def _tube(rng: np.random.Generator, x: np.ndarray, y: np.ndarray) -> _Tube:
    """A straight vortex tube: axis point c, unit direction t, core a, circulation/2pi; planes of t x (p - c).

    w = t x (p - c) is linear in p: precomputed on the (y, x) plane at z = 0 plus a z coefficient.
    Its length is the distance r to the axis and the swirl velocity is f(r) w with
    f = Gamma / (2 pi r^2) (1 - exp(-r^2 / a^2)) (Lamb-Oseen).
    """
    centre = rng.uniform(0.2, 0.8, 3)
    t = rng.standard_normal(3)
    t /= np.linalg.norm(t)
    core = rng.uniform(*VORTEX_CORE)
    swirl = rng.uniform(*VORTEX_SWIRL) * rng.choice([-1.0, 1.0])
    # peak of (1 - exp(-s^2)) / s at s = r / a = 1.1209: 0.6382; so Gamma/2pi = swirl * a / 0.6382
    gamma = swirl * core / 0.6382
    plane = (y.size, x.size)
    dx = (x - centre[0])[None, :]
    dy = (y - centre[1])[:, None]
    dz0 = -centre[2]
    planes = (  # (t x d) at z = 0, and d/dz of each component
        (t[1] * dz0 - t[2] * dy, t[1]),
        (t[2] * dx - t[0] * dz0, -t[0]),
        (t[0] * dy - t[1] * dx, 0.0),
    )
    return _Tube(
        planes=[(np.broadcast_to(p, plane).astype(np.float32), np.float32(g)) for p, g in planes],
        inv_a2=np.float32(1.0 / core**2),
        gamma=np.float32(gamma),
    )


def _add_tube(u: list[np.ndarray], tube: _Tube, zs: np.ndarray) -> None:
    """Add the tube's swirl velocity to the slab's components ``u`` (at slab heights ``zs``)."""
    w = [plane[None] + dz * zs for plane, dz in tube.planes]
    r2 = w[0] * w[0]
    r2 += w[1] * w[1]
    r2 += w[2] * w[2]
    np.maximum(r2, np.float32(1e-12), out=r2)
    f = np.expm1(r2 * -tube.inv_a2)
    f /= r2
    f *= -tube.gamma
    for c in range(3):
        w[c] *= f
        u[c] += w[c]


# ---------------------------------------------------------------------------------------------
# bubbles


def _bubbles(shape_xyz: tuple[int, int, int], rng: np.random.Generator) -> np.ndarray:
    """Spheres with tanh edges rising in a widening plume, added until the target occupancy."""
    nx, ny, nz = shape_xyz
    length = max(shape_xyz)
    ext = np.array(shape_xyz, np.float64) / length  # extents (x, y, z) in units of L
    out = np.zeros((nz, ny, nx), np.float32)
    target = int(np.ceil(BUBBLE_OCCUPANCY * out.size))
    sway = rng.uniform(0.0, TWO_PI, 2)  # phases of the plume axis' slow sway
    occupied, peak = 0, 0.0
    for _ in range(MAX_BUBBLES):
        h = rng.uniform()  # height fraction
        spread = (BUBBLE_SPREAD[0] + (BUBBLE_SPREAD[1] - BUBBLE_SPREAD[0]) * h) * min(ext[0], ext[1])
        axis = 0.5 * ext[:2] + 0.06 * min(ext[0], ext[1]) * np.sin(TWO_PI * 1.3 * h + sway)
        centre = np.array([*(axis + spread * rng.standard_normal(2)), h * ext[2]])
        radius = rng.uniform(*BUBBLE_RADIUS) * (1.0 + BUBBLE_GROWTH * h)
        value = rng.uniform(*BUBBLE_VALUE)
        tilt = rng.standard_normal(3)
        tilt *= rng.uniform(0.0, BUBBLE_TILT) / np.linalg.norm(tilt)
        centre = np.clip(centre, 0.0, ext)
        threshold = OCCUPIED * max(peak, value)
        added, bubble_peak = _draw_bubble(out, centre * length - 0.5, radius * length, value, tilt, threshold)
        peak = max(peak, bubble_peak)
        occupied += added
        if occupied >= target:
            break
    return out


def _draw_bubble(out: np.ndarray, centre: np.ndarray, radius: float, value: float, tilt: np.ndarray, threshold: float) -> tuple[int, float]:
    """max-composite one bubble into ``out`` within its bounding box.

    Args:
        out: Volume (nz, ny, nx), updated in place.
        centre: Centre (x, y, z) in voxel index units.
        radius: Radius in voxels.
        value: Value at the centre.
        tilt: Interior gradient: value * (1 + tilt . (p - c) / radius) inside (|tilt| <= BUBBLE_TILT).
        threshold: Occupancy threshold for the returned count.

    Returns:
        (voxels newly above ``threshold``, the bubble's largest value).
    """
    half = radius + BUBBLE_BOX * BUBBLE_EDGE
    lo = np.maximum(np.floor(centre - half).astype(int), 0)
    hi = np.minimum(np.ceil(centre + half).astype(int) + 1, out.shape[::-1])
    if np.any(hi <= lo):
        return 0, 0.0
    d = [(np.arange(lo[a], hi[a], dtype=np.float32) - np.float32(centre[a])) for a in range(3)]
    dx, dy, dz = d[0][None, None, :], d[1][None, :, None], d[2][:, None, None]
    r = np.sqrt(dz * dz + dy * dy + dx * dx)
    s = (np.float32(tilt[0]) * dx + np.float32(tilt[1]) * dy + np.float32(tilt[2]) * dz) * np.float32(1.0 / radius)
    np.clip(s, -BUBBLE_TILT, BUBBLE_TILT, out=s)
    s += np.float32(1.0)
    s *= np.float32(value)
    r -= np.float32(radius)
    r *= np.float32(1.0 / BUBBLE_EDGE)
    np.tanh(r, out=r)
    s *= np.float32(0.5) - np.float32(0.5) * r
    s[s < BUBBLE_FLOOR] = 0.0
    box = out[lo[2] : hi[2], lo[1] : hi[1], lo[0] : hi[0]]
    before = np.count_nonzero(box > threshold)
    np.maximum(box, s, out=box)
    return int(np.count_nonzero(box > threshold)) - int(before), float(s.max())


# ---------------------------------------------------------------------------------------------
# turbulence


def _turbulence(shape_xyz: tuple[int, int, int], rng: np.random.Generator) -> np.ndarray:
    """exp(alpha g / sigma) of a Gaussian random field g with a von Karman k^-5/3 energy spectrum.

    g's Fourier coefficients are drawn in the rfft layout (complex64), scaled by sqrt(E(k) / 4 pi k^2)
    and inverse-transformed in place, so peak memory is about one complex half-spectrum plus the
    float32 output. Coefficients with |index| <= :data:`TURB_LOW_K` on every axis come from their own
    random stream in a size-independent order, so the large scales agree across resolutions.
    """
    nx, ny, nz = shape_xyz
    length = max(shape_xyz)
    low_rng, high_rng = (np.random.default_rng(int(s)) for s in rng.integers(0, 2**63 - 1, size=2))
    nxh = nx // 2 + 1
    spec = np.empty((nz, ny, nxh), np.complex64)
    high_rng.standard_normal(dtype=np.float32, out=spec.view(np.float32))
    _fill_low_modes(spec, low_rng, (nz, ny, nx))

    # wavenumbers in cycles per L; the isotropic Nyquist wavenumber is L / 2
    kx = (np.arange(nxh) * (length / nx)).astype(np.float32)
    ky = (np.fft.fftfreq(ny, 1.0 / ny) * (length / ny)).astype(np.float32)
    kz = (np.fft.fftfreq(nz, 1.0 / nz) * (length / nz)).astype(np.float32)
    kd = TURB_KD * length / 2.0
    k2_plane = ky[:, None] ** 2 + kx[None, :] ** 2
    weight = np.where((np.arange(nxh) == 0) | (2 * np.arange(nxh) == nx), 1.0, 4.0)  # variance of a half-plane entry
    variance = 0.0
    for z in range(nz):
        amp = _turb_amplitude(k2_plane + kz[z] ** 2, kd)
        spec[z] *= amp
        variance += float((amp.astype(np.float64) ** 2 * weight).sum())
    scale = np.float32(TURB_LOGNORMAL / np.sqrt(variance))

    _ifft2_inplace(spec)
    out = np.empty((nz, ny, nx), np.float32)
    for z0, z1 in _slabs(out.shape):
        out[z0:z1] = np.fft.irfft(spec[z0:z1], n=nx, axis=-1, norm="forward")
        out[z0:z1] *= scale
        np.exp(out[z0:z1], out=out[z0:z1])
    return out


def _turb_amplitude(k2: np.ndarray, kd: float) -> np.ndarray:
    """sqrt(E(k) / (4 pi k^2)) for the von Karman spectrum with a Gaussian dissipation roll-off (float32)."""
    q = k2 * np.float32(1.0 / TURB_K0**2)  # (k/k0)^2
    amp = q ** np.float32(0.5)  # sqrt((k/k0)^4 / k^2) up to constants = k/k0 / k0
    amp *= (1.0 + q) ** np.float32(-17.0 / 12.0)
    amp *= np.exp(k2 * np.float32(-0.5 / kd**2))
    return amp


def _fill_low_modes(spec: np.ndarray, rng: np.random.Generator, shape_zyx: tuple[int, int, int]) -> None:
    """Overwrite the |index| <= TURB_LOW_K block of the rfft-layout spectrum from ``rng``."""
    nz, ny, nx = shape_zyx
    k = TURB_LOW_K
    block = (2 * k + 1, 2 * k + 1, k + 1)
    re, im = rng.standard_normal(block, dtype=np.float32), rng.standard_normal(block, dtype=np.float32)
    low = (re + 1j * im).astype(np.complex64)
    idx = np.arange(-k, k + 1)

    def fit(n: int) -> tuple[np.ndarray, np.ndarray]:
        ok = (idx >= -(n // 2)) & (idx <= (n - 1) // 2)
        return np.nonzero(ok)[0], idx[ok] % n

    (bz, pz), (by, py) = fit(nz), fit(ny)
    bx = np.arange(min(k, nx // 2) + 1)
    # the FFT samples p = i / n; shift by half a voxel to the voxel centres (i + 0.5) / n used by
    # every example, so that the shared large scales line up across resolutions
    half = (idx[bz] / nz)[:, None, None] + (idx[by] / ny)[None, :, None] + (bx / nx)[None, None, :]
    spec[np.ix_(pz, py, bx)] = low[np.ix_(bz, by, bx)] * np.exp(1j * np.pi * half).astype(np.complex64)


def _ifft2_inplace(spec: np.ndarray) -> None:
    """Unscaled inverse complex FFT over axes (0, 1), in blocks of the last axis to bound temporaries."""
    nz, ny, nxh = spec.shape
    step = max(1, FFT_BLOCK // (nz * ny))
    for j0 in range(0, nxh, step):
        j1 = min(nxh, j0 + step)
        spec[:, :, j0:j1] = np.fft.ifft2(spec[:, :, j0:j1], axes=(0, 1), norm="forward")


# ---------------------------------------------------------------------------------------------
# interface


def _interface(shape_xyz: tuple[int, int, int], rng: np.random.Generator) -> np.ndarray:
    """Heavy fluid (values ~0.84..1) below a multi-mode perturbed, thin (tanh) interface, light (0) above.

    z = h(x, y) is a random superposition of modes with wavenumbers in :data:`IFACE_MODES`; a
    small-scale 3D displacement confined to a Gaussian zone around it folds the interface into
    fingers and detached blobs (mixing). The heavy fluid carries a weak low-wavenumber variation.
    """
    nx, ny, nz = shape_xyz
    x, y, z, length = _coords(shape_xyz)

    def modes(k: np.ndarray) -> np.ndarray:
        return np.where((k >= IFACE_MODES[0]) & (k <= IFACE_MODES[1]), 1.0 / np.maximum(k, 1.0), 0.0)

    def mixing(k: np.ndarray) -> np.ndarray:
        return np.where((k >= MIX_K_MIN) & (k <= MIX_K), 1.0, 0.0)

    def bulk(k: np.ndarray) -> np.ndarray:
        return np.where((k > 0) & (k <= BULK_K), 1.0, 0.0)

    coef_h = _random_coefficients(rng, IFACE_MODES[1], modes, dims=2)[0]
    coef_mix = _random_coefficients(rng, MIX_K, mixing)[0]
    coef_bulk = _random_coefficients(rng, BULK_K, bulk)[0]

    eta = _band_2d(coef_h, x, y)
    eta *= IFACE_AMPLITUDE / max(np.sqrt(0.5 * (np.abs(coef_h) ** 2).sum()), 1e-30)
    # convex map of the displacement: narrow spikes of heavy fluid up, broad bubbles of light fluid down
    # mid-height, less the tanh tail that stays occupied above the interface (-> ~50 % occupancy)
    tail = IFACE_EDGE * np.arctanh(1.0 - 2.0 * OCCUPIED) / length
    height = 0.5 * nz / length - tail + eta + IFACE_ASYMMETRY * (eta**2 - IFACE_AMPLITUDE**2)
    gy, gx = np.gradient(height, 1.0 / length)
    slope = (1.0 / np.sqrt(1.0 + gx**2 + gy**2)).astype(np.float32)  # (z - h) -> normal distance
    h32 = height.astype(np.float32)

    mix = _Band3D(coef_mix * (MIX_AMPLITUDE / np.sqrt(0.5 * (np.abs(coef_mix) ** 2).sum())), x, y, z)
    dens = _Band3D(coef_bulk * (0.5 * BULK_AMPLITUDE / np.sqrt(0.5 * (np.abs(coef_bulk) ** 2).sum())), x, y, z)
    zone = 4.0 * MIX_WIDTH  # beyond this the mixing envelope is < 1e-7
    zlo, zhi = float(height.min()) - zone, float(height.max()) + zone
    inv_edge = np.float32(length / IFACE_EDGE)
    inv_width = np.float32(1.0 / MIX_WIDTH)

    out = np.empty((nz, ny, nx), np.float32)
    for z0, z1 in _slabs(out.shape):
        zs = z[z0:z1, None, None].astype(np.float32)
        d = zs - h32[None]
        phi = d * slope[None]
        if z[z1 - 1] >= zlo and z[z0] <= zhi:
            env = d * inv_width
            env *= env
            np.exp(-env, out=env)
            env *= mix.slab(z0, z1)
            phi -= env
        phi *= inv_edge
        np.tanh(phi, out=phi)
        np.subtract(np.float32(0.5), np.float32(0.5) * phi, out=out[z0:z1])
        out[z0:z1] *= np.float32(1.0 - 0.5 * BULK_AMPLITUDE) + dens.slab(z0, z1)
    return out
