"""The documentation: the README is a front door (two set-up commands first, at most 150 lines)
and every `warpgauss ...` command shown in README.md, CONTRIBUTING.md and docs/ exists."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from warpgauss.cli.main import app

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").rglob("*.md"))]


def _code(text: str) -> list[str]:
    """The code of a Markdown page: indented and fenced lines, and inline `spans`."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or line.startswith("    "):
            out.append(line)
        else:
            out.extend(re.findall(r"`([^`]+)`", line))
    return out


def _shown_commands() -> set[tuple[str, ...]]:
    """(command,) or (group, sub-command) of every `warpgauss` call in the pages' code."""
    found = set()
    for page in PAGES:
        for code in _code(page.read_text()):
            for part in re.split(r"&&|;|\|", code):
                m = re.match(r"\s*warpgauss((?:\s+--?[a-z][\w-]*)*)\s+([a-z][\w-]*)(?:\s+([a-z][\w-]*))?", part)
                if m:
                    cmd, sub = m.group(2), m.group(3)
                    found.add((cmd, sub) if cmd == "bench" and sub else (cmd,))
    return found


def test_readme_is_a_front_door():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 150
    code = [line.strip() for line in lines if line.startswith("    ")]
    assert code[0].startswith("pip install -e") and "warpgauss encode --example" in code[0]
    assert code[1] == "python3 -m pytest -q"  # .ci/run takes the first pytest line


def test_the_pages_show_commands():
    shown = _shown_commands()
    assert {("encode",), ("decode",), ("render",), ("stats",), ("info",)} <= shown, shown


@pytest.mark.parametrize("command", sorted(_shown_commands()))
def test_every_command_shown_in_the_docs_exists(command):
    r = CliRunner().invoke(app, [*command, "--help"])
    assert r.exit_code == 0, f"warpgauss {' '.join(command)} --help: {r.output}"


def _python_blocks() -> list[tuple[str, int, str, str | None]]:
    """Every Python block of README.md and docs/: (page, index, code, why it is not run or None)."""
    out = []
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]:
        text = path.read_text()
        for i, m in enumerate(re.finditer(r"(<!-- not run by the tests: (.*?) -->\n)?```python\n(.*?)```", text, re.S)):
            out.append((str(path.relative_to(ROOT)), i, m.group(3), m.group(2)))
    return out


def test_every_python_block_is_run_or_says_why_not():
    blocks = _python_blocks()
    assert len(blocks) >= 6
    for page, i, _, why in blocks:
        assert why is None or len(why) > 20, (page, i, why)


@pytest.mark.parametrize("page, index, code", [(p, i, c) for p, i, c, why in _python_blocks() if why is None])
def test_the_python_blocks_run_as_printed(page, index, code, tmp_path, monkeypatch):
    """The docs' Python runs as printed (the README's failed: a loaded model has no report), with a
    short refinement so that the test stays small (the options it shows are unchanged)."""
    import functools

    import warpgauss

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(warpgauss, "encode", functools.partial(warpgauss.encode, iterations=20, samples=256, device="cpu", self_test=False))
    scope: dict = {}
    exec(compile(code, f"{page} block {index}", "exec"), scope)  # noqa: S102 - our own documentation, not a file read at run time
    assert (tmp_path / "v.wgs").is_file() and scope["grid"].shape == (64, 64, 64)
