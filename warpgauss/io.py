"""Read and write 3D scalar volumes (the readers live in :mod:`warpgauss.readers`, one module per
format family), and the options stage P reads a file with."""

from __future__ import annotations

from dataclasses import dataclass

from .readers import (  # noqa: F401 - the reading API, as before the readers were a package
    MAX_READ_VOXELS,
    READERS,
    WRITERS,
    Volume,
    parse_raw_name,
    read_volume,
    supported_extensions,
    writable_extensions,
    write_volume,
)


@dataclass
class ReadOptions:
    """How to read a file source (see :func:`warpgauss.io.read_volume`)."""

    shape: tuple[int, int, int] | None = None
    dtype: str | None = None
    endian: str | None = None
    dataset: str | None = None
    variable: str | None = None
    stride: int = 1
    fill_value: float | None = None

    def read(self, path, lazy: bool = False):
        """Read a volume file with these options (:func:`warpgauss.io.read_volume`)."""
        return read_volume(
            path,
            lazy=lazy,
            shape=self.shape,
            dtype=self.dtype,
            endian=self.endian,
            dataset=self.dataset,
            variable=self.variable,
            stride=self.stride,
        )
