"""The photos a command reads (calib intrinsics, response, vignetting): folders and files as given on
the command line."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from pipeline.errors import UserError


def photo_files(images: Path | str | Iterable[Path | str], extensions: set[str] | frozenset[str]) -> list[Path]:
    """Files with one of ``extensions`` (lower case, with the dot) among ``images``: a folder (its
    files, sorted, hidden ones skipped), a file, or a list of both; a path named twice is read once."""
    paths = [Path(images)] if isinstance(images, (str, Path)) else [Path(p) for p in images]
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            files += sorted(p for p in path.iterdir()
                            if p.is_file() and p.suffix.lower() in extensions and not p.name.startswith("."))
        elif path.is_file():
            if path.suffix.lower() not in extensions:
                raise UserError(f"{path}: not a photo this command reads ({', '.join(sorted(extensions))})")
            files.append(path)
        else:
            raise UserError(f"{path}: no such file or folder")
    unique = list({p.resolve(): p for p in reversed(files)}.values())[::-1]  # first mention kept
    if not unique:
        where = ", ".join(str(p) for p in paths)
        raise UserError(f"{where}: no photos found ({', '.join(sorted(extensions))})")
    return unique
