"""Every ```python block of README.md and docs/ runs as written (tests/docs.rs runs the shell
blocks): each page's blocks in order, in one namespace, in a fresh directory."""

import os
import re

import pytest

from conftest import REPO

PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.S | re.M)


def test_the_pages_have_python_blocks():
    assert sum(len(BLOCK.findall(p.read_text())) for p in PAGES) >= 1


@pytest.mark.parametrize("page", [p for p in PAGES if BLOCK.search(p.read_text())], ids=lambda p: p.name)
def test_python_blocks_run_as_written(page, tmp_path):
    os.chdir(tmp_path)
    namespace = {"__name__": "__docs__"}
    for i, code in enumerate(BLOCK.findall(page.read_text())):
        exec(compile(code, f"{page.name}[python block {i}]", "exec"), namespace)
    # the README's walk-through ends with an exported model and decoded outputs
    if page.name == "python.md":
        assert (tmp_path / "m.onnx").is_file()
        assert namespace["out"]["cube"].shape == namespace["x"].shape
