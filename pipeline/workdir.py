"""The work folder: where each stage writes, atomic writes, and the skip-if-fresh rule.

A stage is fresh when all its outputs exist — those its ``outputs()`` names and every file its last
run wrote (an optional one, such as fit/albedo.ply, included) — and its record
(``WORK/<stage>.settings.json``) equals what is asked for now: the settings, sigrend's version and
the content (sha256) of every input file — not file times, which ``cp -p``, ``rsync -a`` or unzip
set to the past; a removed input changes the set.  Hashes are cached in ``WORK/.fingerprints.json``
by (device, inode, size, mtime, ctime), so an unchanged file is not read again (ctime cannot be set
back by copying tools).
Every write goes to a temporary file in the same folder that is renamed into place, so an
interrupted run never leaves a half-written file that a later stage would trust; inside a
``transaction`` (a stage run by pipeline.runner.run_stage) the renames wait for the end of the
stage, so its outputs and its settings record are committed together, last — an interrupted or
failed stage leaves the previous set byte-identical.  Temporary files left by a killed process
are removed by ``remove_stale_temporaries`` at the next stage start.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator

from pipeline.errors import UserError
from pipeline.settings import settings_dict

_UMASK = os.umask(0)
os.umask(_UMASK)


TEMP_MARK = ".tmp"  # temporary names: .<stem>.<random>.tmp<suffix>
SPOOL_MARK = ".spool"  # temporary folders of streamed writes: .<stem>.<random>.spool (pipeline.io.samples)
_pending: contextvars.ContextVar[list | None] = contextvars.ContextVar("pending_renames", default=None)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); on success rename it onto ``path``
    (inside a ``transaction``: when the transaction commits).

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f"{TEMP_MARK}{path.suffix}", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; outputs get the usual permissions
    tmp_path: Path | None = Path(tmp)
    try:
        yield tmp_path
        pending = _pending.get()
        if pending is None:
            os.replace(tmp_path, path)
        else:
            pending.append((tmp_path, path))
            tmp_path = None
    finally:
        if tmp_path is not None and tmp_path.exists():
            tmp_path.unlink()


@contextlib.contextmanager
def collected_writes() -> Iterator[list[tuple[Path, Path]]]:
    """Collect the (temporary, final) renames of the block's ``atomic_path`` writes instead of
    doing them; on an exception the temporaries are removed.  A worker process returns the list
    to its parent, which hands it to ``commit_writes``."""
    pending: list[tuple[Path, Path]] = []
    token = _pending.set(pending)
    try:
        yield pending
    except BaseException:
        for tmp, _ in pending:
            tmp.unlink(missing_ok=True)
        raise
    finally:
        _pending.reset(token)


def written_size(path: str | os.PathLike) -> int:
    """Bytes of ``path`` as the current block wrote it: its temporary when the rename is still
    pending (inside a ``transaction``), else the file itself."""
    for tmp, final in reversed(_pending.get() or []):
        if final == Path(path):
            return tmp.stat().st_size
    return Path(path).stat().st_size


def commit_writes(pending: list[tuple[Path, Path]]) -> None:
    """Rename collected writes into place now, or queue them in the enclosing transaction."""
    current = _pending.get()
    if current is not None:
        current.extend(pending)
        return
    for tmp, path in pending:
        os.replace(tmp, path)


@contextlib.contextmanager
def transaction(invalidate: Path | None = None) -> Iterator[None]:
    """Defer the renames of every ``atomic_path`` write in the block to its end: on success
    ``invalidate`` (a freshness record) is removed, then the files are renamed in the order they
    were written (write the new record last); on an exception, or if the process dies, no file
    of the block has replaced its old version (the temporaries are removed, or left for
    ``remove_stale_temporaries``)."""
    with collected_writes() as pending:
        yield
    if invalidate is not None:
        Path(invalidate).unlink(missing_ok=True)
    commit_writes(pending)


def make_folder(folder: str | os.PathLike, option: str = "-w") -> Path:
    """Create an output folder (and its parents) if needed; UserError naming the command-line
    ``option`` that gave it when it cannot be (a file of that name, no permission, a read-only disk)."""

    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UserError(f"{folder}: this is a file, not a folder; give {option} a folder path") from None
    except OSError as exc:
        raise UserError(f"{folder}: cannot create this folder ({exc.strerror}); give {option} a writable folder") from None
    if not os.access(folder, os.W_OK):
        raise UserError(f"{folder}: the folder is not writable; give {option} a writable folder")
    return folder


LOCK_NAME = ".sigrend.lock"
_held: set[str] = set()


@contextlib.contextmanager
def work_lock(work: str | os.PathLike) -> Iterator[None]:
    """Hold WORK/.sigrend.lock for the block: a second sigrend on the same work folder gets a
    UserError naming the holder instead of interleaving its writes (and its clean-up of
    temporaries) with the first's.  flock(2): the kernel releases the lock when its holder exits,
    killed or not, so a lock is never stale.  Re-entrant within a process."""
    import fcntl

    work = Path(work)
    key = str(work.resolve())
    if key in _held:
        yield
        return
    make_folder(work)
    handle = open(work / LOCK_NAME, "a+")
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            holder = handle.read().strip() or "another process"
            raise UserError(f"{work}: this work folder is in use by {holder}; wait for it to finish or give another -w") from None
        handle.seek(0)
        handle.truncate()
        handle.write(f"sigrend pid {os.getpid()}")
        handle.flush()
        _held.add(key)
        try:
            yield
        finally:
            _held.discard(key)
    finally:
        handle.close()


def remove_stale_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files of writes that a killed process never renamed (``atomic_path``
    names) and the spool folders of streamed writes it never finished (``.*.spool``) under
    ``folder``; returns them."""
    stale = [p for p in Path(folder).rglob(f".*{TEMP_MARK}*") if p.is_file()]
    spools = [p for p in Path(folder).rglob(f".*{SPOOL_MARK}") if p.is_dir()]
    for p in stale:
        p.unlink(missing_ok=True)
    for p in spools:
        shutil.rmtree(p, ignore_errors=True)
    return stale + spools


def read_json(path: str | os.PathLike, *, missing: str = "", unreadable: str = "") -> Any:
    """Parse a JSON file; a missing or malformed file is a ``UserError`` naming it.

    ``missing`` / ``unreadable``: what the user should do, appended to the message.
    """

    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: file not found" + (f"; {missing}" if missing else "")) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})" + (f"; {unreadable}" if unreadable else "")) from None


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write ``obj`` as indented JSON, atomically; returns the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=1) + "\n")
    return path


def write_text(path: str | os.PathLike, text: str) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path


FINGERPRINT_CACHE = ".fingerprints.json"
_HASH_BLOCK = 1 << 20


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_HASH_BLOCK), b""):
            digest.update(block)
    return digest.hexdigest()


def fingerprints(paths: Iterable[Path], work: str | os.PathLike) -> dict[str, str]:
    """{absolute path: sha256 of the content, or "missing"} of ``paths``, cached in ``work``."""
    cache_path = Path(work) / FINGERPRINT_CACHE
    try:
        cache = json.loads(cache_path.read_text())
    except (OSError, ValueError):
        cache = {}
    out, changed = {}, False
    for path in paths:
        key = str(Path(path).resolve())
        try:
            st = os.stat(key)
        except OSError:
            out[key] = "missing"
            continue
        if not os.path.isfile(key):  # a folder: its entries' names
            out[key] = "folder:" + hashlib.sha256("\n".join(sorted(os.listdir(key))).encode()).hexdigest()
            continue
        stamp = [st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns]
        entry = cache.get(key)
        if not entry or entry[0] != stamp:
            entry = cache[key] = [stamp, _sha256(Path(key))]
            changed = True
        out[key] = entry[1]
    if changed:
        Path(work).mkdir(parents=True, exist_ok=True)
        tmp = cache_path.with_name(f".{cache_path.name}.{os.getpid()}{TEMP_MARK}")
        tmp.write_text(json.dumps(cache))
        os.replace(tmp, cache_path)  # the cache is not a stage output: not deferred by a transaction
    return out


def settings_path(work: str | os.PathLike, stage: str) -> Path:
    """Where the settings of ``stage`` are recorded: ``WORK/<stage>.settings.json``."""
    return Path(work) / f"{stage}.settings.json"


def record_settings(
    work: str | os.PathLike, stage: str, settings: Any, provenance: dict | None = None, written: Iterable[Path] = ()
) -> Path:
    """Write the settings a stage ran with, its ``provenance`` (input fingerprints, version, e.g.
    the capture path) and the files it ``written`` (paths inside WORK relative to it) beside its
    outputs."""
    payload = {
        "stage": stage,
        "settings": settings_dict(settings),
        **(provenance or {}),
        "written": sorted({_work_relative(p, work) for p in written}),
    }
    return write_json(settings_path(work, stage), payload)


def _work_relative(path: Path, work: str | os.PathLike) -> str:
    path, work = Path(path).absolute(), Path(work).absolute()
    return str(path.relative_to(work)) if path.is_relative_to(work) else str(path)


def changed_settings(work: str | os.PathLike, stage: str, settings: Any) -> dict[str, tuple]:
    """{name: (recorded value, new value)} of the settings in which ``stage``'s last committed run
    differs from ``settings``; empty when nothing was recorded (or it cannot be read)."""
    try:
        recorded = json.loads(settings_path(work, stage).read_text())["settings"]
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    new = json.loads(json.dumps(settings_dict(settings)))
    if not isinstance(recorded, dict):
        return {}
    return {k: (recorded.get(k), v) for k, v in new.items() if k in recorded and recorded[k] != v}


def is_fresh(work: str | os.PathLike, stage: str, settings: Any, outputs: Iterable[Path], provenance: dict | None = None) -> bool:
    """True when ``stage`` need not run again (see the module docstring)."""
    outputs = [Path(p) for p in outputs]
    if not outputs or not all(p.exists() for p in outputs):
        return False
    rec = settings_path(work, stage)
    try:
        recorded = json.loads(rec.read_text())
        written = recorded.pop("written", [])
    except (OSError, ValueError, AttributeError):
        return False
    if not all((Path(work) / p).exists() for p in written):  # an absolute p stays itself
        return False
    wanted = {"stage": stage, "settings": settings_dict(settings), **(provenance or {})}
    return json.loads(json.dumps(wanted)) == recorded


def default_work(capture: Path) -> Path:
    """The work folder used when none is given: ``<capture>-work`` beside the capture."""
    capture = Path(capture).resolve()
    return capture.parent / f"{capture.name}-work"
