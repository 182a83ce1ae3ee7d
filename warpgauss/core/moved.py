"""Import paths that moved, kept working for one release with a :class:`DeprecationWarning`.

The modules that stood side by side in ``warpgauss/`` before 0.2 live in folders now (see
CONTRIBUTING.md). Rather than one stub file per old module at the top of the package, one table
(:data:`warpgauss.MOVED`) names each old path and where its names went; :func:`install` puts a
finder for exactly those names on ``sys.meta_path``. ``import warpgauss.wgs``, ``from
warpgauss.coded import encode_coded`` and ``from warpgauss import io`` then give a small module
whose attributes are the new module's (the same objects), and warn once where the old path is
imported. A name the table does not hold is left to the ordinary import system.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import types
import warnings

RELEASE = "0.3"  # the release that drops the old paths


def _caller_stacklevel() -> int:
    """The ``stacklevel`` that points a warning at the first frame outside the import system and
    this module: the line that imported the old path (``warnings`` itself skips the import
    system's frames when it counts)."""
    frame: types.FrameType | None = sys._getframe(1)
    level = 1
    while frame is not None and frame.f_code.co_filename == __file__:
        frame = frame.f_back
        while frame is not None and "importlib" in frame.f_code.co_filename and "_bootstrap" in frame.f_code.co_filename:
            frame = frame.f_back
        level += 1
    return level


def deprecated(old: str, new: str) -> None:
    """Warn that ``old`` moved to ``new`` (once per place, as warnings do)."""
    warnings.warn(
        f"{old} moved to {new}; import it from there (the old path goes in warpgauss {RELEASE})",
        DeprecationWarning,
        stacklevel=_caller_stacklevel(),
    )


class OldPath(types.ModuleType):
    """A moved module under its old name: attribute reads go to the new modules, in order."""

    def __init__(self, name: str, targets: tuple[str, ...]):
        super().__init__(name, f"Moved: see {', '.join(targets)}.")
        self.__path__: list[str] = []  # so that an old path's submodules (warpgauss.driver.run) resolve too
        self._targets = targets

    def __getattr__(self, attr: str):
        if attr.startswith("__"):
            raise AttributeError(attr)
        for target in self._targets:
            module = importlib.import_module(target)
            if hasattr(module, attr):
                return getattr(module, attr)
        raise AttributeError(f"module {self.__name__!r} (moved to {self._targets[0]}) has no attribute {attr!r}")

    def __dir__(self) -> list[str]:
        return sorted({n for t in self._targets for n in dir(importlib.import_module(t))})


class OldPathFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds the old paths of ``table`` (``{"warpgauss.wgs": ("warpgauss.format.wgs",), ...}``;
    a key ending in ``.*`` moves a package's submodules with it)."""

    def __init__(self, table: dict[str, tuple[str, ...]]):
        self.table = table

    def targets(self, fullname: str) -> tuple[str, ...] | None:
        if fullname in self.table:
            return self.table[fullname]
        head, _, leaf = fullname.rpartition(".")
        new = self.table.get(head + ".*")
        return None if new is None else tuple(f"{t}.{leaf}" for t in new)

    def find_spec(self, fullname, path=None, target=None):
        if self.targets(fullname) is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec):
        targets = self.targets(spec.name)
        assert targets is not None
        return OldPath(spec.name, targets)

    def exec_module(self, module) -> None:
        targets = module._targets
        importlib.import_module(targets[0])  # a missing new module fails here, on import, not on first use
        deprecated(module.__name__, " and ".join(targets))


def install(table: dict[str, tuple[str, ...]]) -> None:
    """Put a finder for the old paths of ``table`` first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, OldPathFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, OldPathFinder(table))


def forward(package: str, module: str):
    """A package's ``__getattr__`` for the names its old same-named module held: read from
    ``module`` with a warning (``warpgauss.field.plan_bins`` -> ``warpgauss.field.gaussians``)."""

    def __getattr__(name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        target = importlib.import_module(module)
        if not hasattr(target, name):
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        deprecated(f"{package}.{name}", f"{module}.{name}")
        return getattr(target, name)

    return __getattr__
