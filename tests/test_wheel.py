"""The built wheel carries every module at its import path (kernels/ as warpgauss.kernels, cli/ as
warpgauss.cli) and the data files the code reads at run time. .ci/run also installs it in a fresh
venv and encodes from there."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# source folder -> the import path its files have in the wheel (pyproject's package-dir)
MAPPED = {"warpgauss": "warpgauss", "kernels": "warpgauss/kernels", "cli": "warpgauss/cli"}
# files the code opens by path at run time (Path(__file__) neighbours), as the wheel holds them
DATA = ["warpgauss/paraview/warpgauss_reader.py"]


def _expected() -> set[str]:
    want = set(DATA)
    for src, dst in MAPPED.items():
        for f in (ROOT / src).rglob("*.py"):
            if "__pycache__" not in f.parts:
                want.add(f"{dst}/{f.relative_to(ROOT / src).as_posix()}")
    return want


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    pytest.importorskip("setuptools", minversion="70.1")  # bdist_wheel built in, no `wheel` package
    # from a copy of what a clone holds: a build/ folder in the checkout would carry stale modules
    src = tmp_path_factory.mktemp("src")
    skip = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md", *MAPPED):
        (shutil.copytree if (ROOT / name).is_dir() else shutil.copy2)(
            ROOT / name, src / name, **({"ignore": skip} if (ROOT / name).is_dir() else {})
        )
    out = tmp_path_factory.mktemp("dist")
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out), str(src)]
    subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=out)
    (whl,) = out.glob("warpgauss-*.whl")
    return whl


def test_every_module_and_data_file_is_in_the_wheel_at_its_import_path(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = sorted(_expected() - names)
    assert not missing, f"the wheel lacks {missing}: list the package in pyproject's [tool.setuptools] packages"
    assert not [n for n in names if n.startswith(("kernels/", "cli/", "tests/"))], "no stray top-level package"


def test_the_wheel_declares_the_command_and_the_codec_entry_point(wheel):
    with zipfile.ZipFile(wheel) as z:
        (ep,) = [n for n in z.namelist() if n.endswith(".dist-info/entry_points.txt")]
        text = z.read(ep).decode()
    assert "[console_scripts]\nwarpgauss = warpgauss.cli.main:run" in text
    assert "[numcodecs.codecs]\nwarpgauss = warpgauss.codec:WarpGauss" in text


def test_the_expected_set_sees_the_mapped_folders():
    # the check above is only as good as this list: each mapped folder has its __init__ in it
    want = _expected()
    assert {
        "warpgauss/__init__.py",
        "warpgauss/kernels/__init__.py",
        "warpgauss/cli/__init__.py",
        "warpgauss/encoding/driver/__init__.py",
    } <= want
