"""lighting_sh.json (DESIGN.md): real orthonormal SH coefficients of the lighting, (L+1)^2 rows of RGB;
and a lighting named on the command line (``lighting_argument``: relight --env, synth --env, env make),
one rule for every command: a lighting_sh.json, an equirect map file, or a procedural map's spec."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from pipeline.core.envmap import add_sources
from pipeline.core.procedural_envmaps import envmap_from_spec, parse_env_spec, spec_help
from pipeline.core.sh import order_of, sh_of_sources
from pipeline.errors import UserError
from pipeline.io.images import read_envmap
from pipeline.io.values import number_array, whole_number
from pipeline.workdir import read_json, write_json


def read_lighting_sh(path: str | os.PathLike) -> np.ndarray:
    """Return the coefficients as float64 ((L+1)^2, 3) in k = l^2 + l + m order."""
    path = Path(path)
    doc = read_json(path)
    if not isinstance(doc, dict):
        raise UserError(f"{path}: a lighting file is a JSON object with 'order' and 'coeffs'")
    if doc.get("basis", "real-orthonormal") != "real-orthonormal":
        raise UserError(f"{path}: SH basis {doc.get('basis')!r} is not 'real-orthonormal' (DESIGN.md); convert it")
    if "order" not in doc or "coeffs" not in doc:
        raise UserError(f"{path}: needs 'order' and 'coeffs' ((order+1)^2 rows of [r, g, b])")
    order = whole_number(doc["order"], f"{path}: 'order'", "a whole number >= 0")
    coeffs = number_array(doc["coeffs"], f"{path}: 'coeffs'", "(order+1)^2 rows of [r, g, b] numbers")
    if order < 0 or coeffs.shape != ((order + 1) ** 2, 3) or not np.all(np.isfinite(coeffs)):
        raise UserError(f"{path}: order {order} needs {(order + 1) ** 2} finite rows of [r, g, b], got shape {coeffs.shape}")
    return coeffs


def write_lighting_sh(path: str | os.PathLike, coeffs: np.ndarray, **extra) -> Path:
    """Write ((L+1)^2, 3) coefficients; ``extra`` keys (e.g. provenance) are stored alongside."""
    coeffs = np.asarray(coeffs, dtype=float)
    order = int(round(np.sqrt(coeffs.shape[0]))) - 1
    if coeffs.ndim != 2 or coeffs.shape != ((order + 1) ** 2, 3):
        raise ValueError(f"coefficients must be ((L+1)^2, 3), got {coeffs.shape}")
    return write_json(path, {"order": order, "basis": "real-orthonormal", "coeffs": coeffs.tolist(), **extra})


def read_lighting_sources(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The optional directional sources of a lighting_sh.json (the fit's dual angular part):
    directions (J, 3) unit and intensities (J, 3) (sum L dω of each source); empty when absent."""
    path = Path(path)
    doc = read_json(path)
    items = doc.get("sources", []) if isinstance(doc, dict) else []
    try:
        d = np.asarray([s["direction"] for s in items], float).reshape(-1, 3)
        p = np.asarray([s["intensity"] for s in items], float).reshape(-1, 3)
    except (KeyError, TypeError, ValueError):
        raise UserError(f"{path}: 'sources' must be a list of {{'direction': [x, y, z], 'intensity': [r, g, b]}}") from None
    if len(d) != len(p) or not np.all(np.isfinite(d)) or np.any(p < 0) or np.any(np.abs(np.linalg.norm(d, axis=1) - 1) > 1e-3):
        raise UserError(f"{path}: every source needs a unit 'direction' and a non-negative 'intensity'")
    return d, p


def read_lighting_parts(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A lighting_sh.json split as an angular renderer wants it: (the SH coefficients without the
    sources' projection ((L+1)^2, 3), source directions (J, 3), intensities (J, 3))."""

    coeffs = read_lighting_sh(path)
    dirs, power = read_lighting_sources(path)
    if len(dirs):
        coeffs = coeffs - sh_of_sources(dirs, power, order_of(coeffs.shape[0]))
    return coeffs, dirs, power


KNOWN_LIGHT_HEIGHT = 256  # a directional light of capture.toml [lighting] is drawn into a map this tall


def known_light_map(light, height: int = KNOWN_LIGHT_HEIGHT) -> np.ndarray:
    """The equirect map (H, 2H, 3) of a capture.toml [lighting] entry (io.capture_toml.KnownLight): its
    map file as it is, or its directional light spread over the four pixel centres around it
    (core.envmap.add_sources, as relight draws the fit's sources) on a black map ``height`` rows tall."""

    if light.path is not None:
        return np.asarray(read_envmap(light.path), float)
    return add_sources(np.zeros((height, 2 * height, 3)), np.asarray([light.direction]), np.asarray([light.intensity]))


SH_SUFFIXES = (".json",)
MAP_SUFFIXES = (".exr", ".hdr", ".tif", ".tiff", ".png")


@dataclass(frozen=True)
class LightingArgument:
    """A lighting named on the command line: ``kind`` 'sh' (a lighting_sh.json at ``path``), 'map' (an
    equirect map file at ``path``, DESIGN.md's convention) or 'procedural' (``text`` is a spec of
    pipeline.core.procedural_envmaps; no file)."""

    text: str
    kind: Literal["sh", "map", "procedural"]
    path: Path | None = None

    def envmap(self) -> np.ndarray:
        """The map (H, 2H, 3) float32: the file read and checked, or the procedural map made."""
        if self.kind == "procedural":
            return envmap_from_spec(self.text)
        if self.kind == "sh":
            raise UserError(f"{self.text}: an SH lighting, not a map; give an equirect map or a procedural spec")

        if not self.path.is_file():
            raise UserError(
                f"{self.path}: lighting not found; give an existing file or a procedural map "
                "(`sigrend env make --help` lists them)"
            )
        return read_envmap(self.path)


def lighting_help(sh: bool = True) -> str:
    """What a lighting argument may be, for --help (``sh``: a lighting_sh.json too)."""

    files = (
        "a lighting_sh.json, an equirect EXR/HDR (DESIGN.md convention)" if sh else "an equirect EXR/HDR (DESIGN.md convention)"
    )
    return f"{files} or {spec_help()}"


def lighting_argument(text: str, option: str = "--env", sh: bool = True) -> LightingArgument:
    """``text`` as a lighting (LightingArgument): a name ending in .json is a lighting_sh.json (refused
    unless ``sh``), one ending in an image suffix or naming an existing file is an equirect map, else
    it must be a procedural spec (UserError, one line, naming ``option``, otherwise).  Files are not
    read here (a stage's inputs may not exist yet); LightingArgument.envmap reads them."""

    path = Path(text)
    suffix = path.suffix.lower()
    if suffix in SH_SUFFIXES:
        if not sh:
            raise UserError(f"{option} {text}: an SH lighting_sh.json is not a map here; give {lighting_help(sh=False)}")
        return LightingArgument(text, "sh", path)
    if suffix in MAP_SUFFIXES or path.is_file():
        return LightingArgument(text, "map", path)
    try:
        parse_env_spec(text)
    except ValueError as exc:
        raise UserError(f"{option} {text!r}: no such file, and not a procedural map: {exc}") from None
    return LightingArgument(text, "procedural")
