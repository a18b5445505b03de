"""The package's logger, ``sigrend``: configured once by the command line (pipeline.cli), silent
in Python callers unless they configure logging themselves.  What users must see (summaries,
errors, warnings) is printed or warned; the log says what the program is doing, for ``-v``."""

from __future__ import annotations

import logging
import sys

LOGGER = logging.getLogger("sigrend")


def configure(verbose: bool) -> None:
    """One stderr handler on the package logger, ``sigrend: `` before each line; INFO with
    ``verbose``, else warnings only.  Called once per command line."""
    LOGGER.handlers.clear()
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("sigrend: %(message)s"))
    LOGGER.addHandler(handler)
    LOGGER.setLevel(logging.INFO if verbose else logging.WARNING)
    LOGGER.propagate = False
