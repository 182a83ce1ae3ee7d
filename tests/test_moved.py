"""The import paths of the flat package before 0.2 still work for one release, with a warning
that names the new path, and give the very same objects."""

from __future__ import annotations

import importlib
import sys
import warnings

import pytest

import warpgauss


def _fresh(name: str):
    for key in [k for k in sys.modules if k == name or k.startswith(name + ".")]:
        del sys.modules[key]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        exec(compile(f"import {name}", __file__, "exec"), {})  # an import statement, as a user writes it
    module = sys.modules[name]
    return module, [w for w in caught if issubclass(w.category, DeprecationWarning)]


@pytest.mark.parametrize(
    "old, new, name",
    [
        ("warpgauss.wgs", "warpgauss.format.wgs", "read_wgs"),
        ("warpgauss.coded", "warpgauss.format.coded", "encode_coded"),
        ("warpgauss.model", "warpgauss.format.model", "Model"),
        ("warpgauss.io", "warpgauss.readers", "ReadOptions"),
        ("warpgauss.optimize", "warpgauss.encoding.refine", "RefineConfig"),
        ("warpgauss.driver.run", "warpgauss.encoding.driver.run", "encode_field"),
        ("warpgauss.refine.config", "warpgauss.encoding.refine.config", "LossWeights"),
        ("warpgauss.bricked", "warpgauss.encoding.scale.schedule", "choose_schedule"),
        ("warpgauss.residual", "warpgauss.format.residual", "Bound"),
        ("warpgauss.export", "warpgauss.format.export", "write_vtp"),
    ],
)
def test_an_old_path_warns_and_gives_the_same_objects(old, new, name):
    module, caught = _fresh(old)
    assert caught and new in str(caught[-1].message) and old in str(caught[-1].message)
    assert caught[-1].filename == __file__  # the warning points at the line that imported the old path
    assert getattr(module, name) is getattr(importlib.import_module(new), name)


def test_from_the_package_import_an_old_module_works_too():
    with pytest.warns(DeprecationWarning, match="warpgauss.format.ratefit"):
        sys.modules.pop("warpgauss.ratefit", None)
        from warpgauss import ratefit
    from warpgauss.format.ratefit import fit_bytes

    assert ratefit.fit_bytes is fit_bytes


def test_a_moved_name_of_a_package_that_kept_its_name_warns():
    from warpgauss.field.gaussians import plan_bins

    with pytest.warns(DeprecationWarning, match="warpgauss.field.gaussians.plan_bins"):
        assert warpgauss.field.plan_bins is plan_bins
    from warpgauss.field import GaussianField  # the folder's own export: no warning

    assert GaussianField.__module__ == "warpgauss.field.gaussians"


def test_a_name_no_path_ever_had_is_refused():
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("warpgauss.no_such_module")
    with pytest.raises(AttributeError):
        import warpgauss.wgs as w

        _ = w.no_such_name


def test_every_old_path_in_the_table_imports():
    for old in warpgauss.MOVED:
        if old.endswith(".*"):
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            assert importlib.import_module(old) is not None, old
