"""One timestep of an array with a time axis ``(t, z, y, x)`` in an HDF5 (netCDF-4), classic
netCDF or Zarr file: a series' item, read alone with its spacing, origin and fill value."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import WarpgaussError
from .common import attr_xyz, fill_attr, list_datasets

CONTAINER_SUFFIXES = (".h5", ".hdf5", ".hdf", ".nc", ".cdf", ".zarr")


@dataclass(frozen=True)
class TimeStep:
    """Timestep ``t`` of an array with a time axis ``(t, z, y, x)`` in an HDF5, netCDF or Zarr
    file; :meth:`read` reads that timestep alone."""

    path: str
    key: str
    t: int
    kind: str  # "hdf5" (netCDF-4 too), "netcdf" (classic) or "zarr"
    steps: int

    def read(self) -> np.ndarray:
        if self.kind == "hdf5":
            import h5py

            with h5py.File(self.path, "r") as f:
                return np.asarray(f[self.key][self.t])
        if self.kind == "zarr":
            import zarr

            root: Any = zarr.open(self.path, mode="r")
            arr = root if self.key == "" else root[self.key]
            return np.asarray(arr[self.t])
        from scipy.io import netcdf_file

        with netcdf_file(self.path, "r", mmap=False) as f:
            return np.array(f.variables[self.key].data[self.t])

    def meta(self) -> tuple[tuple[float, float, float], tuple[float, float, float], float | None]:
        """(spacing, origin, fill value) the array declares, as the readers take them."""
        attrs = _attrs(self)
        return attr_xyz(attrs, "spacing", (1.0, 1.0, 1.0)), attr_xyz(attrs, "origin", (0.0, 0.0, 0.0)), fill_attr(attrs)

    def __str__(self) -> str:
        return f"{self.path}:{self.key}[{self.t}]"


def time_arrays(path: Path) -> tuple[str, list[tuple[str, tuple]]]:
    """(kind, [(name, shape)]) of the arrays in a container file, without reading them."""
    if path.is_dir() or path.suffix.lower() == ".zarr":
        import zarr

        from .zarr import array_names

        root: Any = zarr.open(str(path), mode="r")
        if isinstance(root, zarr.Array):
            return "zarr", [("", tuple(root.shape))]
        return "zarr", [(n, tuple(root[n].shape)) for n in sorted(array_names(root))]
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(b"CDF"):
        from scipy.io import netcdf_file

        with netcdf_file(path, "r", mmap=False) as f:
            return "netcdf", [(n, tuple(v.shape)) for n, v in f.variables.items()]
    import h5py

    found: list[tuple[str, tuple]] = []
    with h5py.File(path, "r") as f:
        f.visititems(lambda n, o: found.append((n, tuple(o.shape))) if isinstance(o, h5py.Dataset) else None)
    return "hdf5", found


def time_steps(path, variable: str | None = None) -> list[TimeStep] | None:
    """The timesteps of ``variable`` (default: the first 4D array) of a container file whose
    arrays are ``(t, z, y, x)``; None if the file holds no such array (a single volume)."""
    p = Path(path)
    if not (p.exists() and str(p).lower().endswith(CONTAINER_SUFFIXES)):
        return None
    try:
        kind, found = time_arrays(p)
    except Exception:  # noqa: BLE001 - not a container we can list: the reader will say why
        return None
    shapes = dict(found)
    if variable is not None:
        key = variable.lstrip("/") if kind == "hdf5" else variable
        if key not in shapes:
            raise WarpgaussError(f"{p.name} has no variable {variable!r}; it holds {list_datasets(found)}; pick one with --variable")
        if len(shapes[key]) != 4:
            return None
    else:
        first = next((n for n, sh in found if len(sh) == 4 and sh[0] > 1), None)
        if first is None:
            return None
        key = first
    steps = int(shapes[key][0])
    return [TimeStep(str(p), key, t, kind, steps) for t in range(steps)]


def _attrs(step: TimeStep) -> dict:
    """The attributes of a timestep's array."""
    if step.kind == "hdf5":
        import h5py

        with h5py.File(step.path, "r") as f:
            return dict(f[step.key].attrs)
    if step.kind == "zarr":
        import zarr

        root: Any = zarr.open(step.path, mode="r")
        return dict((root if step.key == "" else root[step.key]).attrs)
    from scipy.io import netcdf_file

    with netcdf_file(step.path, "r", mmap=False) as f:
        return dict(f.variables[step.key]._attributes)
