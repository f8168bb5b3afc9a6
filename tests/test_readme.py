"""The README's and the guides' Python examples run as written (they are the public API a reader
meets first)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
GUIDES = sorted((ROOT / "docs").rglob("*.md"))


def python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(encoding="utf-8"), re.S)


def run_blocks(path: Path) -> dict[str, object]:
    namespace: dict[str, object] = {}
    for block in python_blocks(path):  # later blocks use names from earlier ones, as a reader would
        exec(compile(block, str(path), "exec"), namespace)
    return namespace


def test_readme_python_examples_run():
    assert len(python_blocks(README)) >= 2
    res = run_blocks(README)["res"]
    assert not res.converged and res.stop_reason.name == "DEADLINE"  # as the comment there says


@pytest.mark.parametrize(
    "guide",
    [g for g in GUIDES if python_blocks(g)],
    ids=lambda g: str(g.relative_to(ROOT)),
)
def test_guide_python_examples_run(guide):
    run_blocks(guide)


def test_some_guides_have_python_examples():
    assert sum(bool(python_blocks(g)) for g in GUIDES) >= 2
