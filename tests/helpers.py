"""Assertions shared by the tests (importable as ``helpers``: pyproject's pytest ``pythonpath``)."""

from __future__ import annotations


def assert_one_line_error(stderr: str, *fragments: str, code: int | None = None, expected: int = 2) -> None:
    """The house's contract for a user error: one line on stderr (``sigrend: error: ...`` or
    argparse's ``sigrend CMD: error: ...``), no traceback, every fragment in it; with ``code``,
    that exit code is ``expected`` (2)."""
    lines = stderr.strip().splitlines()
    assert code is None or code == expected, (code, stderr)
    assert "Traceback" not in stderr, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith("sigrend") and "error:" in lines[0], stderr
    for fragment in fragments:
        assert fragment in lines[0], (fragment, stderr)
