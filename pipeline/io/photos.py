"""The photos a command reads: a capture's images/ folder (linearize, poses), or folders and files as
given on the command line (calib intrinsics, response, vignetting)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Literal

from pipeline.errors import UserError
from pipeline.io.camera_decode import DECODED_EXTENSIONS, RAW_EXTENSIONS


def capture_photos(capture: Path, others: Literal["refuse", "skip"] = "refuse") -> list[Path]:
    """The photo files of ``capture/images`` sorted by name (hidden files skipped); UserError on a
    missing folder.  ``others="refuse"`` (linearize, which reads every file): UserError on a file
    of a type linearize cannot read and on an empty folder; ``"skip"`` (poses, after linearize):
    such files are left out."""
    folder = Path(capture) / "images"
    if not folder.is_dir():
        raise UserError(f"{folder}: folder not found; put the photos in CAPTURE/images/")
    files = _visible_files(folder)
    if others == "skip":
        return [p for p in files if p.suffix.lower() in RAW_EXTENSIONS | DECODED_EXTENSIONS]
    for p in files:
        if p.suffix.lower() not in RAW_EXTENSIONS | DECODED_EXTENSIONS:
            raise UserError(
                f"{p}: unknown image type {p.suffix!r}; linearize reads RAW (DNG, CR2, NEF, ARW, ...), "
                "EXR, HDR, TIFF, PNG and JPEG: convert or remove the file"
            )
    if not files:
        raise UserError(f"{folder}: no images; put the photos (RAW, EXR, TIFF, PNG or JPEG) in this folder")
    return files


def _visible_files(folder: Path) -> list[Path]:
    """The files of ``folder`` sorted by name, hidden ones (dot files) skipped."""
    return sorted(p for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))


def photo_files(images: Path | str | Iterable[Path | str], extensions: set[str] | frozenset[str]) -> list[Path]:
    """Files with one of ``extensions`` (lower case, with the dot) among ``images``: a folder (its
    files, sorted, hidden ones skipped), a file, or a list of both; a path named twice is read once."""
    paths = [Path(images)] if isinstance(images, (str, Path)) else [Path(p) for p in images]
    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            files += [p for p in _visible_files(path) if p.suffix.lower() in extensions]
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
