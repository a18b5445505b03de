"""CAPTURE/capture.toml: optional per-capture facts the photos do not carry themselves.

Every section is optional; paths are relative to the capture folder.

    [camera]
    path = "camera.json"            # intrinsics from `sigrend calib intrinsics` (COLMAP model)

    [response]                      # how 8-bit files are linearized (default: the sRGB curve)
    path = "response.json"          # inverse camera response from `sigrend calib response`; or
    curve = "linear"                # "srgb" or "linear" (machine-vision cameras with a linear output)

    [vignetting]
    path = "vignetting.exr"         # flat-field gain map from `sigrend calib vignetting`

    [white_balance]
    multipliers = [2.0, 1.0, 1.5]   # R, G, B gains used for every image (default: camera as-shot WB
                                    # of the first image); or
    gray_patch = [x0, y0, x1, y1]   # a gray card in the first image (pixels, x right, y down, end exclusive)

    [exposure]                      # overrides of EXIF, per image file name, or "default" for all
    default = {time = 0.01, iso = 100, fnumber = 8.0}   # time also as "1/250"
    "IMG_0003.jpg" = {time = 0.04}  # seconds, ISO arithmetic, f-number; any subset

    [brackets]                      # several exposures of one view, merged into one HDR image
    view_00 = ["IMG_0001.jpg", "IMG_0002.jpg", "IMG_0003.jpg"]   # output linear/view_00.exr

    [lighting]                      # known lighting per photo (light stages, several lightings of one object):
    default = "light/studio.exr"    # an equirect map (DESIGN.md convention) for every photo without its own;
    "IMG_0007.jpg" = {direction = [0.3, -0.2, 0.93], intensity = [4.0, 4.0, 4.0]}  # or a directional light:
                                    # unit direction towards it (object frame), irradiance at normal incidence
                                    # in the photos' units (a number or [r, g, b])

    [board]                         # ChArUco board (written by `sigrend synth`, read by calib and poses)
    pattern = "charuco"             # or "chessboard" (calib intrinsics only: no dictionary, no markers)
    dictionary = "DICT_5X5_100"     # a cv2.aruco predefined dictionary name
    squares = [7, 5]                # squares along x (columns) and y (rows)
    square_length = 0.04            # metres
    marker_length = 0.03            # metres
    board_to_object = [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]   # 4x4, board frame -> object frame

    [chart]                         # a colour reference in one photo: fixes the base colour's colour and level
    colorchecker = "IMG_0003.jpg"   # an X-Rite ColorChecker Classic (24 patches) in this photo, found by cv2.mcc; or
    grey_card = {image = "IMG_0003.jpg", box = [x0, y0, x1, y1], reflectance = 0.18}  # a grey card's region
                                    # (pixels, x right, y down, end exclusive; reflectance one number or [r, g, b])
    normal = "camera"               # which way the chart faces: "camera" (its photo's camera, default) or
                                    # [x, y, z] in the object frame (e.g. [0, 0, 1]: lying on the table)

A board file for ``sigrend calib intrinsics --board`` holds the same ``[board]`` table (or its keys
at the top level); OpenCV's 9 x 6-corner chessboard is ``pattern = "chessboard"``, ``squares = [10, 7]``
(squares, as for ChArUco) and its ``square_length``.  Malformed content raises ``UserError`` naming the file and the key.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from pipeline.errors import UserError
from pipeline.io.values import is_number
from pipeline.settings import number
from pipeline.workdir import write_text

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib  # type: ignore[no-redef]

CAPTURE_TOML = "capture.toml"


@dataclass(frozen=True)
class ExposureOverride:
    """EXIF replacements for one image; None keeps the file's own value."""

    time: float | None = None  # seconds
    iso: float | None = None  # ISO arithmetic speed
    fnumber: float | None = None  # N


@dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: cv2.aruco dictionary name, squares (x, y), lengths in metres, pose in the object;
    or a plain chessboard (pattern "chessboard": no dictionary, marker_length 0)."""

    dictionary: str
    squares: tuple[int, int]
    square_length: float
    marker_length: float
    board_to_object: np.ndarray = field(default_factory=lambda: np.eye(4))
    pattern: Literal["charuco", "chessboard"] = "charuco"


@dataclass(frozen=True)
class KnownLight:
    """A photo's known lighting from capture.toml [lighting]: an equirect map (``path``), or one
    directional light (unit ``direction`` towards it, ``intensity`` = irradiance at normal incidence, RGB)."""

    path: Path | None = None
    direction: tuple[float, float, float] | None = None
    intensity: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class ChartSpec:
    """capture.toml [chart]: the photo holding a ColorChecker Classic (``kind`` "colorchecker") or a
    grey card (``kind`` "grey_card", its ``box`` and ``reflectance`` (3,)); ``normal`` None = the
    chart faces its photo's camera, else a unit vector in the object frame."""

    kind: Literal["colorchecker", "grey_card"]
    image: str
    box: tuple[int, int, int, int] | None = None
    reflectance: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class CaptureConfig:
    """Parsed capture.toml (absent file -> all defaults). Paths are absolute."""

    camera: Path | None = None
    response: Path | None = None
    response_curve: str = "srgb"  # without a response path: "srgb" or "linear"
    vignetting: Path | None = None
    wb_multipliers: tuple[float, float, float] | None = None
    wb_gray_patch: tuple[int, int, int, int] | None = None
    exposure: dict[str, ExposureOverride] = field(default_factory=dict)
    brackets: dict[str, tuple[str, ...]] = field(default_factory=dict)
    board: BoardSpec | None = None
    lighting: dict[str, KnownLight] = field(default_factory=dict)
    chart: ChartSpec | None = None
    source: Path | None = None

    def exposure_for(self, name: str) -> ExposureOverride:
        """Override for image ``name``: its own entry field by field over ``default``."""
        own = self.exposure.get(name, ExposureOverride())
        base = self.exposure.get("default", ExposureOverride())
        return ExposureOverride(
            *(a if a is not None else b for a, b in zip((own.time, own.iso, own.fnumber), (base.time, base.iso, base.fnumber)))
        )

    def lighting_for(self, name: str) -> KnownLight | None:
        """[lighting] of image ``name``: its entry, or the entry of the same file stem (a linear
        image's key for the photo it was made from), else ``default``, else None."""
        if name in self.lighting:
            return self.lighting[name]
        same = [light for key, light in self.lighting.items() if Path(key).stem == Path(name).stem]
        return same[0] if same else self.lighting.get("default")

    def lights_for(self, names: list[str]) -> dict[str, KnownLight]:
        """Each image's [lighting] entry (lighting_for); a UserError naming the images without one."""
        lights = {name: self.lighting_for(name) for name in names}
        missing = [name for name, light in lights.items() if light is None]
        if missing and not self.lighting:
            raise UserError("capture.toml has no [lighting]: name each photo's lighting there (or a default)")
        if missing:
            raise UserError(
                f"{self.source}: [lighting] gives no lighting for {', '.join(missing[:3])}: name each "
                "photo's lighting there (or a default)"
            )
        return lights


def read_toml(path: Path) -> dict:
    """Parse a TOML file (tomllib, tomli on Python 3.10); UserError when missing or malformed."""
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise UserError(f"{path}: file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise UserError(f"{path}: not valid TOML ({exc}); fix the syntax") from None


# capture.toml's sections and their keys (None: any key, e.g. image file names)
SECTIONS: dict[str, set[str] | None] = {
    "camera": {"path"},
    "response": {"path", "curve"},
    "vignetting": {"path"},
    "white_balance": {"multipliers", "gray_patch"},
    "exposure": None,
    "brackets": None,
    "lighting": None,
    "board": {"pattern", "dictionary", "squares", "square_length", "marker_length", "board_to_object"},
    "fit": {"known_albedo"},
    "chart": {"colorchecker", "grey_card", "normal"},
}


def did_you_mean(name: str, valid) -> str:
    """' (did you mean X?)' for the closest of ``valid`` to a misspelt ``name``, else ''."""
    import difflib

    close = difflib.get_close_matches(name, list(valid), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def check_sections(path: Path, doc: dict) -> None:
    """UserError naming every unknown section or key of a capture.toml (a typo is otherwise ignored)."""
    problems = []
    for section, value in doc.items():
        if section not in SECTIONS:
            problems.append(f"[{section}]{did_you_mean(section, SECTIONS)}")
        elif not isinstance(value, dict):
            problems.append(f"{section} = ... must be a [{section}] table")
        elif SECTIONS[section] is not None:
            problems += [
                f"[{section}] {key}{did_you_mean(key, SECTIONS[section])}" for key in value if key not in SECTIONS[section]
            ]
    if problems:
        raise UserError(f"{path}: unknown " + "; ".join(problems) + f" — known sections: {', '.join(SECTIONS)}")


def _fraction(value: Any) -> Any:
    """A string written as cameras print exposure times ("1/250") as its number; anything else as it is."""
    try:
        return number(value) if isinstance(value, str) else value
    except ValueError:
        return value


def _positive(path: Path, where: str, value: Any) -> float:
    if not is_number(value) or not np.isfinite(value) or value <= 0:
        raise UserError(f"{path}: {where} must be a positive number, got {value!r}")
    return float(value)


def _path_entry(path: Path, doc: dict, section: str) -> Path | None:
    table = doc.get(section)
    if table is None:
        return None
    if not isinstance(table, dict) or not isinstance(table.get("path"), str):
        raise UserError(f'{path}: [{section}] needs path = "file" (relative to the capture folder)')
    target = (path.parent / table["path"]).resolve()
    if not target.exists():
        raise UserError(f"{path}: [{section}] path {table['path']!r} does not exist ({target})")
    return target


RESPONSE_CURVES = ("srgb", "linear")
BOARD_PATTERNS = ("charuco", "chessboard")


def _response_entry(path: Path, doc: dict) -> tuple[Path | None, str]:
    """[response]: (path of a response.json, None) or (None, curve name); no section -> (None, "srgb")."""
    table = doc.get("response")
    if isinstance(table, dict) and "curve" in table:
        if "path" in table:
            raise UserError(f"{path}: [response] has both path and curve; keep one")
        if table["curve"] not in RESPONSE_CURVES:
            raise UserError(
                f"{path}: [response] curve = {table['curve']!r}; use one of {', '.join(RESPONSE_CURVES)} "
                'or path = "response.json"'
            )
        return None, table["curve"]
    return _path_entry(path, doc, "response"), "srgb"


def parse_board(path: Path, table: dict) -> BoardSpec:
    """A ``[board]`` table -> BoardSpec (UserError naming ``path`` on a bad key)."""
    pattern = table.get("pattern", "charuco")
    if pattern not in BOARD_PATTERNS:
        raise UserError(f"{path}: [board] pattern = {pattern!r}; use one of {', '.join(map(repr, BOARD_PATTERNS))}")
    chessboard = pattern == "chessboard"
    try:
        dictionary = "" if chessboard else str(table["dictionary"])
        squares = tuple(int(v) for v in table["squares"])
        square = _positive(path, "[board] square_length", table["square_length"])
        marker = 0.0 if chessboard else _positive(path, "[board] marker_length", table["marker_length"])
    except (KeyError, TypeError, ValueError) as exc:
        needs = (
            "squares = [x, y] and square_length"
            if chessboard
            else "dictionary, squares = [x, y], square_length and marker_length"
        )
        raise UserError(f"{path}: [board] needs {needs} (metres); problem with {exc}") from None
    if chessboard and min(squares, default=0) < 3:
        raise UserError(
            f"{path}: [board] a chessboard needs squares >= [3, 3] (squares, not inner corners: "
            f"OpenCV's 9 x 6-corner board is [10, 7]), got {table['squares']!r}"
        )
    if len(squares) != 2 or min(squares) < 2:
        raise UserError(f"{path}: [board] squares must be two integers >= 2, got {table['squares']!r}")
    if marker >= square and not chessboard:
        raise UserError(f"{path}: [board] marker_length {marker} must be smaller than square_length {square}")
    try:
        m = np.asarray(table.get("board_to_object", np.eye(4)), dtype=float)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise UserError(
            f"{path}: [board] board_to_object must be a finite 4x4 matrix of numbers (rows of the "
            f"board -> object transform), got {table.get('board_to_object')!r}"
        )
    return BoardSpec(dictionary, (squares[0], squares[1]), square, marker, m, pattern)


def read_board(path: str | os.PathLike) -> BoardSpec:
    """A board file: a ``[board]`` table, or the same keys at the top level."""
    path = Path(path)
    doc = read_toml(path)
    return parse_board(path, doc["board"] if isinstance(doc.get("board"), dict) else doc)


def parse_lighting(path: Path, table: dict) -> dict[str, KnownLight]:
    """[lighting]: image name (or "default") -> KnownLight (UserError naming ``path`` and the key)."""
    out = {}
    for name, entry in table.items():
        where = f"{path}: [lighting] {name!r}"
        if isinstance(entry, str):
            target = (path.parent / entry).resolve()
            if not target.is_file():
                raise UserError(f"{where}: {entry!r} does not exist ({target})")
            out[name] = KnownLight(path=target)
            continue
        if not isinstance(entry, dict) or set(entry) != {"direction", "intensity"}:
            raise UserError(f'{where} must be a map file name ("light.exr") or {{direction = [x, y, z], intensity = [r, g, b]}}')
        d, i = entry["direction"], entry["intensity"]
        i = [i] * 3 if is_number(i) else i
        if (
            not isinstance(d, list)
            or len(d) != 3
            or not all(is_number(v) for v in d)
            or not isinstance(i, list)
            or len(i) != 3
            or not all(is_number(v) and v >= 0 for v in i)
        ):
            raise UserError(f"{where}: direction must be three numbers and intensity one or three numbers >= 0")
        norm = float(np.linalg.norm(np.asarray(d, float)))
        if not np.isfinite(norm) or norm == 0 or not np.all(np.isfinite(i)):
            raise UserError(f"{where}: direction must be a finite non-zero vector (towards the light)")
        out[name] = KnownLight(direction=tuple(float(v) / norm for v in d), intensity=tuple(float(v) for v in i))
    return out


def parse_chart(path: Path, table: dict) -> ChartSpec:
    """[chart] -> ChartSpec (UserError naming ``path`` and the key)."""
    where = f"{path}: [chart]"
    if ("colorchecker" in table) == ("grey_card" in table):
        raise UserError(
            f'{where} needs one of colorchecker = "photo file name" or grey_card = {{image = "...", '
            "box = [x0, y0, x1, y1], reflectance = 0.18}"
        )
    normal = table.get("normal", "camera")
    unit = None
    if normal != "camera":
        vec = np.asarray(normal if isinstance(normal, list) and all(is_number(v) for v in normal) else [], float)
        norm = float(np.linalg.norm(vec)) if vec.shape == (3,) else 0.0
        if not np.isfinite(norm) or norm == 0:
            raise UserError(f'{where} normal must be "camera" or a non-zero [x, y, z] (object frame), got {normal!r}')
        unit = tuple(float(v) / norm for v in vec)
    if "colorchecker" in table:
        if not isinstance(table["colorchecker"], str) or not table["colorchecker"]:
            raise UserError(f'{where} colorchecker must be a photo file name ("IMG_0003.jpg")')
        return ChartSpec("colorchecker", table["colorchecker"], normal=unit)
    card = table["grey_card"]
    if not isinstance(card, dict) or set(card) - {"image", "box", "reflectance"} or not isinstance(card.get("image"), str):
        raise UserError(f'{where} grey_card must be {{image = "photo file name", box = [x0, y0, x1, y1], reflectance = 0.18}}')
    box = card.get("box")
    if (
        not isinstance(box, list)
        or len(box) != 4
        or not all(isinstance(v, int) for v in box)
        or min(box) < 0
        or box[2] <= box[0]
        or box[3] <= box[1]
    ):
        raise UserError(
            f"{where} grey_card box must be [x0, y0, x1, y1] integer pixels with x1 > x0 >= 0, y1 > y0 >= 0, got {box!r}"
        )
    rho = card.get("reflectance", 0.18)
    rho = [rho] * 3 if is_number(rho) else rho
    if not isinstance(rho, list) or len(rho) != 3 or not all(is_number(v) and np.isfinite(v) and 0 < v <= 1 for v in rho):
        raise UserError(f"{where} grey_card reflectance must be one or three numbers in (0, 1], got {card.get('reflectance')!r}")
    return ChartSpec("grey_card", card["image"], tuple(box), tuple(float(v) for v in rho), unit)


def write_capture_toml(path: str | os.PathLike, doc: dict, comment: str = "") -> Path:
    """A capture.toml from its tables (plain Python values) through tomli_w (strings escaped), with
    ``comment`` as a first line: what synth and the poses bench write, read back by read_capture_config."""
    import tomli_w

    return write_text(path, (f"# {comment}\n\n" if comment else "") + tomli_w.dumps(doc))


def read_capture_config(capture: str | os.PathLike) -> CaptureConfig:
    """Parse ``capture/capture.toml``; a missing file gives the defaults."""
    path = Path(capture) / CAPTURE_TOML
    if not path.exists():
        return CaptureConfig()
    doc = read_toml(path)
    check_sections(path, doc)

    wb = doc.get("white_balance", {})
    mult = gray = None
    if "multipliers" in wb:
        vals = wb["multipliers"]
        if not isinstance(vals, list) or len(vals) != 3:
            raise UserError(f"{path}: [white_balance] multipliers must be [r, g, b]")
        mult = tuple(_positive(path, "[white_balance] multipliers", v) for v in vals)
    if "gray_patch" in wb:
        vals = wb["gray_patch"]
        if (
            not isinstance(vals, list)
            or len(vals) != 4
            or not all(isinstance(v, int) for v in vals)
            or vals[2] <= vals[0]
            or vals[3] <= vals[1]
            or min(vals) < 0
        ):
            raise UserError(f"{path}: [white_balance] gray_patch must be [x0, y0, x1, y1] integer pixels with x1 > x0, y1 > y0")
        gray = tuple(vals)
    if mult and gray:
        raise UserError(f"{path}: [white_balance] give multipliers or gray_patch, not both")

    exposure = {}
    for name, entry in doc.get("exposure", {}).items():
        if not isinstance(entry, dict) or set(entry) - {"time", "iso", "fnumber"}:
            raise UserError(f"{path}: [exposure] {name!r} must be a table with time, iso and/or fnumber")
        exposure[name] = ExposureOverride(
            **{k: _positive(path, f"[exposure] {name}.{k}", _fraction(v)) for k, v in entry.items()}
        )

    brackets = {}
    for name, members in doc.get("brackets", {}).items():
        if not isinstance(members, list) or len(members) < 2 or not all(isinstance(m, str) for m in members):
            raise UserError(f"{path}: [brackets] {name!r} must list at least two image file names")
        brackets[name] = tuple(members)

    board = parse_board(path, doc["board"]) if "board" in doc else None
    response, curve = _response_entry(path, doc)
    return CaptureConfig(
        camera=_path_entry(path, doc, "camera"),
        response=response,
        response_curve=curve,
        vignetting=_path_entry(path, doc, "vignetting"),
        wb_multipliers=mult,
        wb_gray_patch=gray,
        exposure=exposure,
        brackets=brackets,
        board=board,
        lighting=parse_lighting(path, doc.get("lighting", {})),
        chart=parse_chart(path, doc["chart"]) if "chart" in doc else None,
        source=path,
    )
