"""`sigrend`: one subcommand per stage (export included), plus run, calib, synth, env, planar and bench.

Every subcommand lives in a module that provides ``HELP``, ``add_arguments(parser)`` and
``main(args) -> int | None``; stages get theirs generically from their ``Settings`` dataclass
(see ``pipeline.runner.stage_command``).  Only ``UserError`` is caught here: it becomes one
line on stderr and exit code 2.  Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import importlib
import os
import signal
import sys
import threading
import warnings

from pipeline import STAGES, __version__
from pipeline.errors import UserError
from pipeline.logs import configure as configure_logging
from pipeline.settings import HelpFormatter

STAGE_COMMANDS = (*STAGES, "export")  # `sigrend NAME CAPTURE -w WORK`: the run's stages, then export

# subcommand -> module providing HELP, add_arguments, main (imported only when needed)
COMMANDS = {
    "run": "pipeline.runner",
    "batch": "pipeline.batch",
    "calib": "pipeline.commands.calib",
    "synth": "pipeline.commands.synth",
    "env": "pipeline.commands.env",
    "planar": "pipeline.commands.planar",
    "bench": "pipeline.commands.bench",
}


def _command_module(name: str):
    if name in STAGE_COMMANDS:
        from pipeline.runner import stage_command  # lazy: the runner imports every stage; other commands start without them

        return stage_command(name)
    return importlib.import_module(COMMANDS[name])


class OneLineParser(argparse.ArgumentParser):
    """argparse, with a bad command line as the house's one line (exit 2): the error and where the
    options are listed, without the usage block above it.  Every parser of the command line is one
    (subcommands' parsers take their parent's class), and every ``--help`` is written by
    pipeline.settings.HelpFormatter: each default said once, flags worded as flags."""

    def __init__(self, *args, formatter_class=HelpFormatter, **kwargs):
        super().__init__(*args, formatter_class=formatter_class, **kwargs)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser(selected: str | None = None) -> argparse.ArgumentParser:
    """The full parser; modules are imported only for ``selected`` (or all, for --help)."""
    parser = OneLineParser(prog="sigrend", description="Lighting and BRDF from photos of a known shape, in frequency space.")

    parser.add_argument("--version", action="version", version=f"sigrend {__version__}")
    parser.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        help="say what is being done (each stage's settings at its start); `sigrend -v poses` "
        "also shows COLMAP's own log on the terminal instead of WORK/colmap/colmap.log",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in (*STAGE_COMMANDS, *COMMANDS):
        if selected is not None and name != selected:
            sub.add_parser(name, add_help=False)
            continue
        try:
            mod = _command_module(name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith(("pipeline", "stages", "calib")):
                continue  # not built yet
            raise
        p = sub.add_parser(name, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_module=mod)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM (a scheduler, ``kill``, a closed terminal's session) handled as Ctrl-C: the running
    stage's transaction rolls back, earlier outputs are kept (pipeline.workdir)."""


def _raise_terminated(signum, frame):
    raise Terminated()


DISK_ERRORS = {  # the machine's errors, not sigrend's -> what to do
    errno.ENOSPC: "free some space or give -w a folder on another disk",
    errno.EDQUOT: "free some space or give -w a folder on another disk",
    errno.EROFS: "give -w a writable folder",
    errno.EACCES: "check the permissions of this file or folder (or give -w a writable folder)",
    errno.EPERM: "check the permissions of this file or folder (or give -w a writable folder)",
}


def _format_warning(message, category, filename, lineno, line=None) -> str:
    return f"sigrend: warning: {message}\n"


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the command line (not a caller in Python): warnings as one line each, no source line
        warnings.formatwarning = _format_warning
    argv = sys.argv[1:] if argv is None else list(argv)
    selected = next((a for a in argv if not a.startswith("-")), None)
    if selected not in (*STAGE_COMMANDS, *COMMANDS):
        selected = None
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if in_main_thread else None
    try:
        # warnings (a deprecated option's among them) are held back until the command succeeds: an
        # error stays the one line of stderr (in the main thread only: catch_warnings swaps
        # process-wide state)
        with warnings.catch_warnings(record=True) if in_main_thread else contextlib.nullcontext([]) as deferred:
            args = build_parser(selected).parse_args(argv)
            configure_logging(args.verbose)
            code = args._module.main(args)
        for w in deferred:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        sys.stdout.flush()
    except UserError as exc:
        print(f"sigrend: error: {exc}", file=sys.stderr)
        return UserError.exit_code
    except Terminated:
        print("sigrend: terminated; finished outputs are kept, run again to resume", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("sigrend: interrupted; finished outputs are kept, run again to resume", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `sigrend ... | head`: the reader left; end quietly (Python docs, "SIGPIPE")
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except OSError as exc:
        if exc.errno not in DISK_ERRORS:
            raise
        # the machine, not sigrend: a full disk or quota, a read-only or forbidden folder (the stage's
        # transaction has rolled back, so earlier outputs are intact)
        fix = DISK_ERRORS[exc.errno]
        print(f"sigrend: error: {exc.filename or 'writing the outputs'}: {exc.strerror}; {fix}, then run again", file=sys.stderr)
        return UserError.exit_code
    finally:
        if in_main_thread:
            signal.signal(signal.SIGTERM, previous)
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
