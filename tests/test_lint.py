"""The house's lint and format (pyproject.toml [tool.ruff], issue 45 item 5): the whole tree passes
`ruff check` and is formatted as `ruff format` writes it, so CI refuses a change that is not."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[1]


@pytest.mark.parametrize("command", [["check", "."], ["format", "--check", "."]])
def test_tree_passes_ruff(command):
    """`python -m ruff check .` and `python -m ruff format --check .` at the project's root exit 0;
    on failure the message is ruff's own list of what to fix (`ruff check --fix`, `ruff format`)."""
    result = subprocess.run([sys.executable, "-m", "ruff", *command], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr
