"""The package's logger, ``sigrend``: configured once by the command line (pipeline.cli), silent
in Python callers unless they configure logging themselves.  What users must see (summaries,
errors, warnings) is printed or warned; the log says what the program is doing, for ``-v``.
``progress`` is every progress bar of the project: drawn on a terminal only."""

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


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # a replaced or closed stream
        return False


def progress(iterable=None, *, enabled: bool = True, **kwargs):
    """A tqdm progress bar on stderr, drawn only when stderr is a terminal: in a log file or a pipe
    its carriage-return frames would be noise around the lines that matter (the stage table, the
    errors); there the bar is a plain pass-through and the run says one line per stage (its table,
    and with -v each stage's settings as it starts).  ``enabled=False``: never drawn (a caller
    that runs quietly, e.g. a batch task).  ``kwargs`` are tqdm's (desc, unit, total, leave, ...)."""
    from tqdm import tqdm

    return tqdm(iterable, file=sys.stderr, disable=not (enabled and _is_terminal(sys.stderr)), **kwargs)
