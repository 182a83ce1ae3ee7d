"""Transfer functions: value in [0, 1] -> colour and opacity, as a LUT the renderers sample.

A transfer function is a colormap plus an opacity curve over the model's normalised values (0 is
the source's minimum, 1 its maximum; the header keeps both for labels). They come from

* the model header's default (``transfer_function``: a 256-entry RGBA8 LUT and opacity points),
* a named colormap (:func:`colormap_names`) with an opacity curve such as ``"0:0,0.4:0.1,1:1"``,
* our ``.json`` (``{"colormap": "magma"}`` or ``{"colors": [[x, r, g, b], ...]}``, plus
  ``"opacity": [[x, a], ...]``; x normalised unless ``"space": "data"``, colours in 0..1),
* a ParaView colormap/opacity export (``RGBPoints``, ``Points``, ``ColorSpace``; RGB, Lab,
  Diverging and HSV interpolation, opacity midpoint and sharpness as ``vtkPiecewiseFunction``).
  ParaView writes points in data units when the map was edited on data and in the preset's own
  range otherwise: points that lie within the model's value range are taken as data units; any
  other range is stretched over the value range, as ParaView does when it applies a preset.

The same object renders a model and its reference volume, so their images are comparable.
"""

from __future__ import annotations

import colorsys
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import WarpgaussError

LUT_SIZE = 256

# Colormaps at 33 evenly spaced stops (RGB8 hex, 6 characters a stop), sampled from matplotlib's
# tables; linear interpolation between stops stays within about 2 % of the full tables.
_STOPS_HEX = {
    "viridis": (
        "440154470d6048186a482374472d7b4537814240863e49893b528b375b8d33638d2f6b8e2c728e297a8e26828e23898e"
        "21918c1f988b1fa08822a78528ae8032b67a3fbc734ec36b5ec96270cf5784d44b98d83eaddc30c2df23d8e219ece51b"
        "fde725"
    ),
    "magma": (
        "0000040303120a0822130d341d114729115a36106b440f7651127c5d177f6a1c81762181832681902a819c2e7faa337d"
        "b73779c43c75d0416fdc4869e75263ef5d5ef56b5cf9795dfc8961fd9869fea772feb67cfec488fed395fde2a3fcf0b2"
        "fcfdbf"
    ),
    "inferno": (
        "0000040403120b0724150b37210c4a2f0a5b3d09654a0c6b57106e64156e71196e7d1e6d8a226a972766a32c61b0315b"
        "bc3754c73e4cd24644db503be45a31eb6628f1731df68013f98e09fb9d07fcac11fbbc21f9cb35f5db4cf2ea69f3f68a"
        "fcffa4"
    ),
    "plasma": (
        "0d08872206903105973f049c4c02a15901a56600a77201a87e03a88a09a59511a1a01a9caa2395b32c8ebc3587c43e7f"
        "cc4778d35171da5a6ae06363e66c5ceb7655f0804ef58b47f89540fba139fdac33feb82cfdc527fcd225f8df25f4ed27"
        "f0f921"
    ),
    "cividis": (
        "00224e00285b002e6a0533711a386f273e6e32436d3b496c434e6c4b546c535a6d5a5f6e61656f686a716f7073767676"
        "7d7c788482798c8878938e789b9476a39a74aba072b4a76fbcae6cc4b468cdbb63d5c25edec958e7d150f0d846f9e03a"
        "fee838"
    ),
    "turbo": (
        "30123b392a734040a24456c7466be34680f64294ff37a8fa28bceb1ccdd818ddc21fe9af32f2984ef97d6dfe628bff4b"
        "a4fc3cb9f635cdec34dfdf37eecf3af8be39fdac34fe962bfb7e21f46617eb500edf3f08d02f05be2102a91601920b01"
        "7a0403"
    ),
    "coolwarm": (
        "3b4cc0445acc4e68d85875e16282ea6c8ff1779af782a6fb8db0fe98b9ffa3c2feaec9fcb9d0f9c3d5f4ccd9edd5dbe5"
        "dddcdce5d8d1ecd3c5f1ccb8f5c4acf7ba9ff7b093f6a586f4987af08b6eeb7d62e46e56dd5f4bd44e41ca3b37be242e"
        "b40426"
    ),
    "jet": (
        "0000800000a40000c80000ed0000ff0020ff0040ff0060ff0080ff00a0ff00c0ff00e0fb16ffe130ffc749ffad63ff94"
        "7dff7a97ff60b1ff46caff2ce4ff13feed00ffd000ffb200ff9400ff7700ff5900ff3b00ff1e00e80000c400009f0000"
        "800000"
    ),
}

_ALIASES = {"gray": "grayscale", "grey": "grayscale", "greyscale": "grayscale", "cool-warm": "coolwarm", "cool_warm": "coolwarm"}


def colormap_names() -> list[str]:
    """Names :func:`colormap` accepts (each also reversed with a ``_r`` suffix)."""
    return sorted([*_STOPS_HEX, "grayscale"])


def _stops(name: str) -> np.ndarray:
    if name == "grayscale":
        return np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    raw = bytes.fromhex("".join(_STOPS_HEX[name]))
    return np.frombuffer(raw, np.uint8).reshape(-1, 3).astype(np.float64) / 255.0


def colormap(name: str, entries: int = LUT_SIZE) -> np.ndarray:
    """(entries, 3) RGB in [0, 1] of a named colormap over evenly spaced values in [0, 1].

    Args:
        name: One of :func:`colormap_names` (case-insensitive; ``gray``/``grey`` mean grayscale),
            optionally with ``_r`` for the reversed map.
    """
    key = str(name).strip().lower()
    reverse = key.endswith("_r")
    if reverse:
        key = key[:-2]
    key = _ALIASES.get(key, key)
    if key not in _STOPS_HEX and key != "grayscale":
        raise WarpgaussError(f"unknown colormap {name!r}; choose one of {', '.join(colormap_names())} (or NAME_r)")
    st = _stops(key)
    xs = np.linspace(0.0, 1.0, len(st))
    x = np.linspace(0.0, 1.0, entries)
    rgb = np.stack([np.interp(x, xs, st[:, c]) for c in range(3)], axis=1)
    return rgb[::-1].copy() if reverse else rgb


# ------------------------------------------------------------------------------------------------
# Opacity curves
# ------------------------------------------------------------------------------------------------


def parse_opacity(text: str) -> list[tuple[float, float]]:
    """``"0:0,0.5:0.2,1:1"`` (value:opacity pairs, normalised values) -> sorted points.

    ``linear`` means ``0:0,1:1``, ``flat`` or a single number c means constant opacity c.
    """
    s = str(text).strip().lower()
    if s == "linear":
        return [(0.0, 0.0), (1.0, 1.0)]
    if s == "flat":
        return [(0.0, 1.0), (1.0, 1.0)]
    try:
        c = float(s)
    except ValueError:
        pts = []
        for part in s.replace(";", ",").split(","):
            if not part.strip():
                continue
            xy = part.split(":")
            try:
                if len(xy) != 2:
                    raise ValueError
                pts.append((float(xy[0]), float(xy[1])))
            except ValueError:
                raise WarpgaussError(
                    f"--opacity takes value:opacity pairs such as 0:0,0.5:0.2,1:1 (or linear, flat, a number), got {text!r}"
                ) from None
        return _check_points(pts, "--opacity")
    return _check_points([(0.0, c), (1.0, c)], "--opacity")


def _check_points(pts, what: str) -> list[tuple[float, float]]:
    if not pts:
        raise WarpgaussError(f"{what}: no points given")
    arr = np.asarray(pts, np.float64)
    if not np.all(np.isfinite(arr)):
        raise WarpgaussError(f"{what}: points must be finite numbers")
    if np.any(arr[:, 1] < 0) or np.any(arr[:, 1] > 1):
        raise WarpgaussError(f"{what}: opacities must lie in [0, 1]")
    order = np.argsort(arr[:, 0], kind="stable")
    return [(float(x), float(y)) for x, y in arr[order]]


def _piecewise(x: np.ndarray, pts, midsharp=None) -> np.ndarray:
    """Piecewise curve through (x, y) points, constant beyond the ends; with ParaView's per-segment
    (midpoint, sharpness) when ``midsharp`` is given (``vtkPiecewiseFunction`` semantics)."""
    p = np.asarray(pts, np.float64)
    xs, ys = p[:, 0], p[:, 1]
    if len(xs) == 1:
        return np.full_like(x, ys[0])
    if midsharp is None:
        return np.interp(x, xs, ys)
    out = np.interp(x, xs, ys)
    for k in range(len(xs) - 1):
        x1, x2, y1, y2 = xs[k], xs[k + 1], ys[k], ys[k + 1]
        if x2 <= x1:
            continue
        mid, sharp = float(midsharp[k][0]), float(midsharp[k][1])
        mid = min(max(mid, 1e-5), 1 - 1e-5)
        sel = (x >= x1) & (x <= x2)
        s = (x[sel] - x1) / (x2 - x1)
        s = np.where(s < mid, 0.5 * s / mid, 0.5 + 0.5 * (s - mid) / (1.0 - mid))
        if sharp > 0.99:
            v = np.where(s < 0.5, y1, y2)
        elif sharp < 0.01:
            v = (1 - s) * y1 + s * y2
        else:
            e = 1.0 + 10.0 * sharp
            s = np.where(s < 0.5, 0.5 * (2 * s) ** e, np.where(s > 0.5, 1.0 - 0.5 * (2 * (1 - s)) ** e, s))
            ss, sss = s * s, s * s * s
            h1, h2, h3, h4 = 2 * sss - 3 * ss + 1, -2 * sss + 3 * ss, sss - 2 * ss + s, sss - ss
            t = (1.0 - sharp) * (y2 - y1)
            v = np.clip(h1 * y1 + h2 * y2 + h3 * t + h4 * t, min(y1, y2), max(y1, y2))
        out[sel] = v
    return out


# ------------------------------------------------------------------------------------------------
# Colour interpolation (RGB, Lab, Moreland's diverging Msh, HSV)
# ------------------------------------------------------------------------------------------------

_WHITE = np.array([0.9505, 1.0, 1.089])  # D65, as VTK's vtkMath::XYZToLab


def _rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    c = np.where(rgb > 0.04045, ((rgb + 0.055) / 1.055) ** 2.4, rgb / 12.92)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = c @ m.T / _WHITE
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16.0 / 116.0)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], axis=-1)


def _lab_to_rgb(lab: np.ndarray) -> np.ndarray:
    fy = (lab[..., 0] + 16) / 116
    f = np.stack([fy + lab[..., 1] / 500, fy, fy - lab[..., 2] / 200], axis=-1)
    xyz = np.where(f**3 > 0.008856, f**3, (f - 16.0 / 116.0) / 7.787) * _WHITE
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    c = xyz @ m.T
    rgb = np.where(c > 0.0031308, 1.055 * np.abs(c) ** (1 / 2.4) - 0.055, 12.92 * c)
    return np.clip(rgb, 0.0, 1.0)


def _msh(rgb):
    lab = _rgb_to_lab(np.asarray(rgb, np.float64))
    m = float(np.linalg.norm(lab))
    s = math.acos(max(-1.0, min(1.0, lab[0] / m))) if m > 0 else 0.0
    return m, s, math.atan2(lab[2], lab[1])


def _adjust_hue(m: float, s: float, h: float, m_unsat: float) -> float:
    if m >= m_unsat - 0.1:
        return h
    spin = s * math.sqrt(m_unsat**2 - m**2) / (m * math.sin(s))
    return h + spin if h > -math.pi / 3 else h - spin


def _diverging(c1, c2, s: np.ndarray) -> np.ndarray:
    """Moreland's diverging interpolation (Msh space) between two colours, as VTK does."""
    out = np.empty((len(s), 3))
    for k, t in enumerate(s):
        m1, s1, h1 = _msh(c1)
        m2, s2, h2 = _msh(c2)
        if s1 > 0.05 and s2 > 0.05 and abs(h1 - h2) > math.pi / 3 and (abs(abs(h1 - h2) - 2 * math.pi) > math.pi / 3):
            mid = max(m1, m2, 88.0)
            if t < 0.5:
                m2, s2, h2, t = mid, 0.0, 0.0, 2 * t
            else:
                m1, s1, h1, t = mid, 0.0, 0.0, 2 * t - 1
        if s1 < 0.05 and s2 > 0.05:
            h1 = _adjust_hue(m2, s2, h2, m1)
        elif s2 < 0.05 and s1 > 0.05:
            h2 = _adjust_hue(m1, s1, h1, m2)
        m, sa, h = (1 - t) * m1 + t * m2, (1 - t) * s1 + t * s2, (1 - t) * h1 + t * h2
        out[k] = _lab_to_rgb(np.array([m * math.cos(sa), m * math.sin(sa) * math.cos(h), m * math.sin(sa) * math.sin(h)]))
    return out


def _colour_curve(x: np.ndarray, pts: np.ndarray, space: str) -> np.ndarray:
    """RGB at x from (x, r, g, b) points (sorted), constant beyond the ends."""
    xs, cs = pts[:, 0], pts[:, 1:4]
    if len(xs) == 1:
        return np.repeat(cs[:1], len(x), axis=0)
    space = space.lower()
    if space in ("rgb", "step") or space not in ("lab", "lab/ciede2000", "diverging", "hsv"):
        if space == "step":
            idx = np.clip(np.searchsorted(xs, x, side="right") - 1, 0, len(xs) - 1)
            return cs[idx]
        return np.stack([np.interp(x, xs, cs[:, c]) for c in range(3)], axis=1)
    out = np.empty((len(x), 3))
    xc = np.clip(x, xs[0], xs[-1])
    seg = np.clip(np.searchsorted(xs, xc, side="right") - 1, 0, len(xs) - 2)
    for k in range(len(xs) - 1):
        sel = np.nonzero(seg == k)[0]
        if sel.size == 0:
            continue
        width = xs[k + 1] - xs[k]
        t = (xc[sel] - xs[k]) / width if width > 0 else np.ones(sel.size)
        a, b = cs[k], cs[k + 1]
        if space.startswith("lab"):
            la, lb = _rgb_to_lab(a), _rgb_to_lab(b)
            out[sel] = _lab_to_rgb(la[None] * (1 - t[:, None]) + lb[None] * t[:, None])
        elif space == "diverging":
            out[sel] = _diverging(a, b, t)
        else:
            ha, hb = np.array(colorsys.rgb_to_hsv(*a)), np.array(colorsys.rgb_to_hsv(*b))
            if abs(hb[0] - ha[0]) > 0.5:  # the short way round the hue circle (VTK's HSVWrap)
                hb[0] += 1.0 if hb[0] < ha[0] else -1.0
            out[sel] = [colorsys.hsv_to_rgb(*((ha * (1 - u) + hb * u) % [1.0, 2.0, 2.0])) for u in t]
    return out


# ------------------------------------------------------------------------------------------------
# The transfer function
# ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TransferFunction:
    """Colour and opacity over normalised values, sampled at :data:`LUT_SIZE` evenly spaced values.

    Attributes:
        rgb: (K, 3) colour in [0, 1].
        opacity: (K,) opacity in [0, 1] (extinction per unit length once scaled by the render's
            density factor).
        name: What it was made from (for labels and reports).
    """

    rgb: np.ndarray
    opacity: np.ndarray
    name: str = "custom"
    source: dict = field(default_factory=dict)

    def __post_init__(self):
        rgb = np.clip(np.asarray(self.rgb, np.float32), 0.0, 1.0)
        op = np.clip(np.asarray(self.opacity, np.float32), 0.0, 1.0)
        if rgb.ndim != 2 or rgb.shape[1] != 3 or op.shape != (rgb.shape[0],) or rgb.shape[0] < 2:
            raise WarpgaussError("a transfer function needs (K, 3) colours and K opacities, K >= 2")
        object.__setattr__(self, "rgb", rgb)
        object.__setattr__(self, "opacity", op)

    @property
    def rgba(self) -> np.ndarray:
        """(K, 4) float32: colour and opacity."""
        return np.concatenate([self.rgb, self.opacity[:, None]], axis=1).astype(np.float32)

    def __call__(self, values) -> np.ndarray:
        """(..., 4) colour and opacity at normalised values (linear between entries, clamped)."""
        v = np.clip(np.asarray(values, np.float64), 0.0, 1.0)
        x = np.linspace(0.0, 1.0, self.rgb.shape[0])
        return np.stack([np.interp(v, x, self.rgba[:, c]) for c in range(4)], axis=-1)

    def with_colormap(self, name: str) -> TransferFunction:
        """The same opacity with a named colormap's colours."""
        return TransferFunction(colormap(name, len(self.opacity)), self.opacity, str(name), {**self.source, "colormap": str(name)})

    def with_opacity(self, points) -> TransferFunction:
        """The same colours with a piecewise-linear opacity curve through ``points`` (or a string)."""
        pts = parse_opacity(points) if isinstance(points, str) else _check_points(list(points), "opacity")
        x = np.linspace(0.0, 1.0, len(self.opacity))
        src = {**self.source, "opacity": [list(p) for p in pts]}
        return TransferFunction(self.rgb, _piecewise(x, pts), self.name, src)

    def describe(self) -> dict:
        return {"name": self.name, **self.source}


def make_transfer_function(colormap_name: str = "viridis", opacity="linear") -> TransferFunction:
    """A named colormap with an opacity curve (points or a string for :func:`parse_opacity`)."""
    tf = TransferFunction(colormap(colormap_name), np.zeros(LUT_SIZE), str(colormap_name), {"colormap": str(colormap_name)})
    return tf.with_opacity("linear" if opacity is None else opacity)


def from_header(header: dict) -> TransferFunction:
    """The model header's default transfer function (RGBA8 LUT; opacity from its points if given)."""
    t = header.get("transfer_function") or {}
    name = str(t.get("colormap") or "viridis")
    rgb = None
    if isinstance(t.get("lut_rgba8"), str):
        try:
            raw = np.frombuffer(bytes.fromhex(t["lut_rgba8"]), np.uint8)
        except ValueError:
            raw = np.zeros(0, np.uint8)
        if raw.size >= 8 and raw.size % 4 == 0:
            lut = raw.reshape(-1, 4).astype(np.float64) / 255.0
            if lut.shape[0] != LUT_SIZE:
                xs = np.linspace(0, 1, lut.shape[0])
                x = np.linspace(0, 1, LUT_SIZE)
                lut = np.stack([np.interp(x, xs, lut[:, c]) for c in range(4)], axis=1)
            rgb, alpha = lut[:, :3], lut[:, 3]
    if rgb is None:
        try:
            rgb, alpha = colormap(name), np.linspace(0.0, 1.0, LUT_SIZE)
        except WarpgaussError:
            rgb, alpha, name = colormap("viridis"), np.linspace(0.0, 1.0, LUT_SIZE), "viridis"
    tf = TransferFunction(rgb, alpha, name, {"colormap": name, "from": "model header"})
    if isinstance(t.get("opacity"), list) and t["opacity"]:
        try:
            tf = tf.with_opacity([(float(p[0]), float(p[1])) for p in t["opacity"]])
        except (TypeError, ValueError, IndexError, WarpgaussError):
            pass
    return tf


def load_transfer_function(path: str | os.PathLike, value_range: tuple[float, float] = (0.0, 1.0)) -> TransferFunction:
    """Read our ``.json`` transfer function or a ParaView colormap/opacity export.

    Args:
        path: The ``.json`` file.
        value_range: (min, max) in data units: what normalised 0 and 1 stand for.
    """
    p = Path(path)
    if not p.is_file():
        raise WarpgaussError(f"no such transfer-function file: {p}")
    try:
        doc = json.loads(p.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise WarpgaussError(f"{p}: not a JSON transfer function ({e.__class__.__name__}: {e})") from None
    if isinstance(doc, list):
        maps = [d for d in doc if isinstance(d, dict) and ("RGBPoints" in d or "Points" in d)]
        if not maps:
            raise WarpgaussError(f"{p}: a JSON list but no ParaView colormap in it (no RGBPoints)")
        return _from_paraview(maps[0], value_range, p)
    if not isinstance(doc, dict):
        raise WarpgaussError(f"{p}: expected a JSON object (colormap/colors/opacity) or a ParaView export")
    if "RGBPoints" in doc or "Points" in doc:
        return _from_paraview(doc, value_range, p)
    return _from_ours(doc, value_range, p)


def _to_normalised(x: np.ndarray, value_range) -> np.ndarray:
    lo, hi = float(value_range[0]), float(value_range[1])
    return (x - lo) / (hi - lo) if hi > lo else x


def _from_ours(doc: dict, value_range, p: Path) -> TransferFunction:
    known = {"colormap", "colors", "opacity", "space", "name", "color_space"}
    unknown = sorted(set(doc) - known)
    if unknown:
        raise WarpgaussError(f"{p}: unknown key(s) {', '.join(unknown)}; a transfer function has {', '.join(sorted(known))}")
    space = str(doc.get("space", "normalised")).lower()
    if space not in ("normalised", "normalized", "data"):
        raise WarpgaussError(f"{p}: 'space' must be 'normalised' or 'data', got {doc['space']!r}")
    x = np.linspace(0.0, 1.0, LUT_SIZE)
    src: dict[str, Any] = {"file": str(p)}
    if "colors" in doc:
        try:
            pts = np.asarray(doc["colors"], np.float64)
        except (TypeError, ValueError):
            pts = np.zeros((0, 0))
        if pts.ndim != 2 or pts.shape[1] != 4 or len(pts) < 1 or not np.all(np.isfinite(pts)):
            raise WarpgaussError(f"{p}: 'colors' must be a list of [x, r, g, b] points (colours in 0..1)")
        if space == "data":
            pts[:, 0] = _to_normalised(pts[:, 0], value_range)
        pts = pts[np.argsort(pts[:, 0], kind="stable")]
        rgb = _colour_curve(x, pts, str(doc.get("color_space", "rgb")))
        name = str(doc.get("name", p.stem))
    else:
        name = str(doc.get("colormap", "viridis"))
        rgb = colormap(name)
        src["colormap"] = name
    op = doc.get("opacity", [[0.0, 0.0], [1.0, 1.0]])
    try:
        opts = [(float(a), float(b)) for a, b in op]
    except (TypeError, ValueError):
        raise WarpgaussError(f"{p}: 'opacity' must be a list of [x, opacity] points") from None
    if space == "data":
        opts = [(float(_to_normalised(np.float64(a), value_range)), b) for a, b in opts]
    opts = _check_points(opts, f"{p}: opacity")
    src["opacity"] = [list(o) for o in opts]
    return TransferFunction(rgb, _piecewise(x, opts), name, src)


def _pv_range(xs: np.ndarray, value_range) -> tuple[np.ndarray, str]:
    """ParaView points -> normalised x: data units when they lie within the value range, else stretched."""
    lo, hi = float(value_range[0]), float(value_range[1])
    tol = 1e-3 * (hi - lo)
    if xs.size and xs.min() >= lo - tol and xs.max() <= hi + tol and hi > lo and xs.max() > xs.min():
        return (xs - lo) / (hi - lo), "data"
    if xs.size and xs.max() > xs.min():
        return (xs - xs.min()) / (xs.max() - xs.min()), "stretched"
    return np.zeros_like(xs), "constant"


def _from_paraview(d: dict, value_range, p: Path) -> TransferFunction:
    x = np.linspace(0.0, 1.0, LUT_SIZE)
    name = str(d.get("Name", p.stem))
    src: dict[str, Any] = {"file": str(p), "paraview": name}
    if "IndexedColors" in d and "RGBPoints" not in d:
        raise WarpgaussError(f"{p}: a categorical (indexed) ParaView colormap; give a continuous one")
    if "RGBPoints" in d:
        try:
            pts = np.asarray(d["RGBPoints"], np.float64).reshape(-1, 4)
        except (TypeError, ValueError):
            raise WarpgaussError(f"{p}: RGBPoints must be a flat list of x, r, g, b quadruples") from None
        if len(pts) < 1 or not np.all(np.isfinite(pts)):
            raise WarpgaussError(f"{p}: RGBPoints is empty or not finite")
        pts = pts[np.argsort(pts[:, 0], kind="stable")]
        pts[:, 0], src["rgb_range"] = _pv_range(pts[:, 0], value_range)
        space = str(d.get("ColorSpace", "RGB"))
        src["color_space"] = space
        rgb = _colour_curve(x, pts, space)
    else:
        rgb = colormap("grayscale")
    if "Points" in d:
        try:
            op = np.asarray(d["Points"], np.float64).reshape(-1, 4)
        except (TypeError, ValueError):
            raise WarpgaussError(f"{p}: Points must be a flat list of x, opacity, midpoint, sharpness quadruples") from None
        if len(op) < 1 or not np.all(np.isfinite(op)) or op[:, 1].min() < 0 or op[:, 1].max() > 1:
            raise WarpgaussError(f"{p}: opacity Points must be finite with opacities in [0, 1]")
        op = op[np.argsort(op[:, 0], kind="stable")]
        op[:, 0], src["opacity_range"] = _pv_range(op[:, 0], value_range)
        alpha = _piecewise(x, op[:, :2], op[:, 2:4])
        src["opacity"] = op[:, :2].tolist()
    else:
        alpha = x.copy()
        src["opacity"] = [[0.0, 0.0], [1.0, 1.0]]
    return TransferFunction(rgb, alpha, name, src)


def resolve_transfer_function(
    header: dict | None = None,
    *,
    path: str | os.PathLike | None = None,
    colormap_name: str | None = None,
    opacity=None,
    value_range: tuple[float, float] | None = None,
) -> TransferFunction:
    """The transfer function a render uses: a file (or the header default), then overrides.

    Args:
        header: Model header (its default transfer function is the base); None: viridis, linear.
        path: A ``.json`` transfer function or ParaView export, instead of the header's.
        colormap_name: Replace the colours by a named colormap.
        opacity: Replace the opacity curve (points or a string for :func:`parse_opacity`).
        value_range: Data units of normalised 0 and 1 (default: the header's, else (0, 1)).
    """
    if value_range is None:
        v = (header or {}).get("values") or {}
        value_range = (float(v.get("min", 0.0)), float(v.get("max", 1.0)))
    if path is not None:
        tf = load_transfer_function(path, value_range)
    elif header is not None:
        tf = from_header(header)
    else:
        tf = make_transfer_function("viridis", "linear")
    if colormap_name is not None:
        tf = tf.with_colormap(colormap_name)
    if opacity is not None:
        tf = tf.with_opacity(opacity)
    return tf
