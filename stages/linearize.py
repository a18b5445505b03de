"""linearize: camera files -> linear float RGB radiance on one scale for the capture (WORK/linear/).

Every file of ``CAPTURE/images/`` (or every bracket of them) becomes ``WORK/linear/<key>.exr`` (float32
RGB, linear sRGB primaries), ``WORK/linear/masks/<key>.png`` (255 = valid) and an entry of
``WORK/linear/manifest.json`` (schema: pipeline.io.linear_manifest; user docs: docs/linearize.md).

Decoding by kind
    RAW (LibRaw via rawpy): linear (gamma 1, 1), no auto-brightness, 16 bit, highlights clipped,
        black/white level from the file, LibRaw's maximum never adapted to the data
        (adjust_maximum_thr = 0, so one scale for every image), one white balance for all images,
        linear sRGB output.  value = LibRaw output / 65535.  Saturation: raw values at or above
        ``saturation`` x white level, found before demosaicing and dilated by the 5x5 demosaic footprint.
    float EXR/HDR/TIFF and 16-bit TIFF (OpenImageIO): taken as linear; 16-bit values >= ``saturation``
        (of full scale) are masked.
    8-bit JPEG/PNG/TIFF: inverse camera response (sRGB curve, or capture.toml [response]);
        codes >= ``saturation`` x 255 are masked.

Exposure: radiance = value x N^2 / (t x ISO/100) (t seconds, N f-number, ISO arithmetic), from EXIF
or capture.toml [exposure]; a factor missing from every image is taken as equal (with a warning); a
factor missing from some images only is an error.  A vignetting gain map (capture.toml [vignetting])
divides every image.  Brackets (capture.toml [brackets], or --bracket-size) are merged into one HDR
image: a weighted mean of the members' radiance, weight = exposure x validity x a linear roll-off over
the top 10 % below the saturation level.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing
import os
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.chart import measure_chart
from pipeline.errors import UserError
from pipeline.io.camera_decode import (
    OTHER_BYTES_PER_PIXEL,
    RAW_DECODE_BYTES_PER_PIXEL,
    RAW_HELD_BYTES_PER_PIXEL,
    Probe,
    decode_other,
    decode_other_rows,
    decode_raw,
    decode_raw16,
    no_alpha_error,
    probe,
    raw_rows_to_float,
)
from pipeline.io.camera_files import Exposure
from pipeline.io.camera_json import read_camera_json
from pipeline.io.capture_toml import CAPTURE_TOML, CaptureConfig, did_you_mean, read_capture_config
from pipeline.io.chart_json import chart_path, write_chart
from pipeline.io.images import ImageRowReader, ImageRowWriter
from pipeline.io.linear_manifest import linear_dir, manifest_path, write_manifest
from pipeline.io.photos import capture_photos
from pipeline.io.response_json import inverse_table
from pipeline.logs import progress
from pipeline.memory import DEFAULT as DEFAULT_LIMIT
from pipeline.memory import WORKER_BASE, Budget, band_rows
from pipeline.settings import memory_limit_setting, setting, settings_dict
from pipeline.workdir import collected_writes, commit_writes, fingerprints

ROLLOFF = 0.1  # bracket weights fall linearly to 0 over the top 10 % below the saturation level
HEADER_KEY = "sigrend:linearize"  # EXR attribute holding the recipe digest and manifest entry


@dataclass(frozen=True)
class Settings:
    wb: str = setting(
        "capture",
        "white balance applied to every image: 'capture' (capture.toml [white_balance], "
        "else 'camera'), 'camera' (as-shot WB of the first RAW image), 'r,g,b' multipliers, "
        "or 'gray:x0,y0,x1,y1' (gray card patch in the first image, pixels)",
    )
    saturation: float = setting(
        0.98,
        "fraction of the white level (RAW) or full scale (8/16-bit files) from which a pixel counts as saturated and is masked",
    )
    bracket_size: int = setting(
        0, "merge every N consecutive images (sorted by name) into one HDR bracket; 0 = only the [brackets] of capture.toml"
    )
    workers: int = setting(
        0, "worker processes (0 = one per CPU core, 1 = serial); fewer when --memory-limit leaves room for fewer"
    )
    memory_limit: str = memory_limit_setting()

    def validate(self) -> None:
        parse_wb(self.wb)
        if not 0.5 <= self.saturation <= 1.0:
            raise UserError(f"--saturation {self.saturation}: must be in [0.5, 1]")
        if self.bracket_size < 0 or self.bracket_size == 1:
            raise UserError(f"--bracket-size {self.bracket_size}: use 0 (no automatic brackets) or >= 2")
        if self.workers < 0:
            raise UserError(f"--workers {self.workers}: must be >= 0")
        Budget.of(self.memory_limit)


def parse_wb(text: str) -> tuple[str, tuple]:
    """'capture' | 'camera' | 'r,g,b' | 'gray:x0,y0,x1,y1' -> (kind, values)."""
    if text in ("capture", "camera"):
        return text, ()
    try:
        if text.startswith("gray:"):
            box = tuple(int(v) for v in text[5:].split(","))
            if len(box) == 4 and box[2] > box[0] >= 0 and box[3] > box[1] >= 0:
                return "gray", box
        else:
            mult = tuple(float(v) for v in text.split(","))
            if len(mult) == 3 and all(np.isfinite(mult)) and min(mult) > 0:
                return "multipliers", mult
    except ValueError:
        pass
    raise UserError(
        f"--wb {text!r}: use 'capture', 'camera', three positive multipliers 'r,g,b', "
        "or 'gray:x0,y0,x1,y1' with x1 > x0 and y1 > y0"
    )


# ----------------------------------------------------------------------------------------------
# Planning: which files, which outputs


def plan_groups(files: list[Path], config: CaptureConfig, bracket_size: int) -> dict[str, list[Path]]:
    """Output key -> source files (one file, or the members of a bracket)."""
    by_name = {p.name: p for p in files}
    groups: dict[str, list[Path]] = {}
    used: set[str] = set()
    where = config.source or CAPTURE_TOML
    for name, members in config.brackets.items():
        for m in members:
            if m not in by_name:
                raise UserError(f"{where}: bracket {name!r} lists {m!r}, which is not in images/")
            if m in used:
                raise UserError(f"{where}: {m!r} appears in more than one bracket")
            used.add(m)
        groups[name] = [by_name[m] for m in members]
    rest = [p for p in files if p.name not in used]
    if bracket_size >= 2:
        if len(rest) % bracket_size:
            raise UserError(
                f"{len(rest)} images outside capture.toml brackets do not split into brackets of "
                f"{bracket_size}; fix --bracket-size or list the brackets in capture.toml"
            )
        chunks = [rest[i : i + bracket_size] for i in range(0, len(rest), bracket_size)]
    else:
        chunks = [[p] for p in rest]
    for chunk in chunks:
        key = chunk[0].stem
        if key in groups:
            other = groups[key][0].name
            raise UserError(f"{chunk[0]}: output name {key!r} is already used by {other!r}; rename one of them")
        groups[key] = chunk
    return groups


def _capture_files(capture: Path, config: CaptureConfig) -> list[Path]:
    return [p for p in (config.source, config.camera, config.response, config.vignetting) if p is not None]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    config = read_capture_config(capture)
    return capture_photos(capture) + _capture_files(capture, config)


def outputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    config = read_capture_config(capture)
    keys = plan_groups(capture_photos(capture), config, settings.bracket_size)
    folder = linear_dir(work)
    return (
        [folder / f"{k}.exr" for k in keys]
        + [folder / "masks" / f"{k}.png" for k in keys]
        + [manifest_path(work)]
        + ([chart_path(work)] if config.chart is not None else [])
    )


# ----------------------------------------------------------------------------------------------
# Exposure


def exposure_scales(probes: list[Probe], config: CaptureConfig) -> dict[str, dict]:
    """Per file: t, ISO, N after capture.toml overrides, and scale = N^2 / (t ISO/100).

    A factor absent from every file is equal for all (value None, factor 1, one warning); absent from
    some files only -> UserError naming the first such file.  Zero or negative values -> UserError.
    """
    names = {pr.path.name for pr in probes}
    unmatched = sorted(set(config.exposure) - names - {"default"})
    if unmatched:
        raise UserError(
            f"{config.source}: [exposure] names no image of the capture: "
            + ", ".join(f"{n!r}{did_you_mean(n, names)}" for n in unmatched)
            + ' (keys are image file names, or "default" for all)'
        )
    resolved = {}
    for pr in probes:
        over = config.exposure_for(pr.path.name)
        vals = {k: getattr(over, k) if getattr(over, k) is not None else pr.exif[k] for k in ("time", "iso", "fnumber")}
        for k, v in vals.items():
            if v is not None and not (np.isfinite(v) and v > 0):
                raise UserError(
                    f'{pr.path}: EXIF {k} is {v}; give the true value in capture.toml [exposure] "{pr.path.name}" = {{{k} = ...}}'
                )
        resolved[pr.path.name] = vals
    labels = {"time": "exposure time", "iso": "ISO", "fnumber": "f-number"}
    for k, label in labels.items():
        missing = [pr.path for pr in probes if resolved[pr.path.name][k] is None]
        if missing and len(missing) < len(probes):
            raise UserError(
                f"{missing[0]}: no {label} in EXIF while other images have one; give it in capture.toml "
                f'[exposure] "{missing[0].name}" = {{{k} = ...}} (or a default for all)'
            )
        if missing:
            warnings.warn(
                f"no {label} in any image's EXIF or capture.toml: assuming it is the same for every image",
                UserWarning,
                stacklevel=2,
            )
    out = {}
    for name, v in resolved.items():
        shot = Exposure(v["time"] or 1.0, v["iso"] or 100.0, v["fnumber"] or 1.0)
        out[name] = {"exposure_time_s": v["time"], "iso": v["iso"], "f_number": v["fnumber"], "scale": 1.0 / shot.scale}
    return out


# ----------------------------------------------------------------------------------------------
# One job (an output image): decode its files, scale, devignette, merge, write


def _digest(job: dict) -> str:
    """The recipe of a job: everything it depends on (its pixel size, known from the files, is not)."""
    recipe = {k: v for k, v in job.items() if k != "size"}
    return hashlib.sha1(json.dumps(recipe, sort_keys=True).encode()).hexdigest()


def _read_header_entry(exr: Path) -> dict | None:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(exr))
    if inp is None:
        oiio.geterror()
        return None
    try:
        text = inp.spec().get_string_attribute(HEADER_KEY)
    finally:
        inp.close()
    try:
        return json.loads(text) if text else None
    except json.JSONDecodeError:
        return None


def _fresh_entry(job: dict) -> dict | None:
    """The manifest entry recorded in an existing output with the same recipe (settings, sources
    and the content of every file it depends on: the job's ``content``)."""
    exr, mask = Path(job["exr"]), Path(job["mask"])
    if not (exr.exists() and mask.exists()):
        return None
    header = _read_header_entry(exr)
    if not header or header.get("recipe") != _digest(job):
        return None
    return header["entry"]


def linearize_job(job: dict, rows: int | None = None) -> dict:
    """Decode, normalize and (for brackets) merge the sources of one output; write EXR + mask.

    ``rows``: image rows decoded at a time (None: the whole image at once).  With fewer rows than
    the image the sources are decoded twice, band by band: once to count the valid pixels the EXR's
    header records, once to write; the files hold the same values either way (every step is per
    pixel).  Returns the manifest entry.  Runs in a worker process: everything it needs is in ``job``.
    """
    key = job["key"]
    with JobSources(job) as sources:
        height, width = sources.height, sources.width
        rows = min(rows or height, height)
        bands = [(y, min(y + rows, height)) for y in range(0, height, rows)]
        kept = None
        for y0, y1 in bands:  # the first pass: counts (and the one band, when it is the image)
            merged, valid = sources.band(y0, y1, count=True)
            kept = (merged, valid) if len(bands) == 1 else None
        valid_fraction = sources.valid_count / (height * width)
        entry = {
            "exr": f"{key}.exr",
            "mask": f"masks/{key}.png",
            "width": int(width),
            "height": int(height),
            "sources": sources.entries(),
            "white_balance": job["white_balance"],
            "saturated_fraction": round(1.0 - valid_fraction, 6),
            "valid_fraction": round(valid_fraction, 6),
            "vignetting": job["vignetting"],
            "response": job["response"] or job["response_curve"],
        }
        header = json.dumps({"recipe": _digest(job), "entry": entry})
        if kept is None:
            sources.rewind()
        with (
            ImageRowWriter(job["mask"], width, height, 1, dtype="uint8") as mask,
            ImageRowWriter(job["exr"], width, height, 3, dtype="float", attributes={HEADER_KEY: header}) as exr,
        ):
            for y0, y1 in bands:
                merged, valid = kept if kept is not None else sources.band(y0, y1)
                mask.write(valid.astype(np.float32))
                exr.write(merged)
    return entry


def job_radiance(job: dict) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """One output's linear radiance (H, W, 3) float32, its valid mask (H, W) and its sources'
    manifest entries: the sources decoded, scaled and (brackets) merged, the whole image at once."""
    with JobSources(job) as sources:
        merged, valid = sources.band(0, sources.height, count=True)
        return merged, valid, sources.entries()


def job_bytes(job: dict) -> tuple[int, float]:
    """A job's memory: (bytes it holds whatever the band, bytes per row of a band).  A RAW source is
    decoded whole by LibRaw (its 16-bit output kept for the bands); a band's arrays (the decoded rows,
    radiance, masks, bracket sums, the writers' conversions) cost ~BAND_BYTES_PER_PIXEL per pixel."""
    raws = sum(src["kind"] == "raw" for src in job["sources"])
    pixels = job["size"][0] * job["size"][1]
    fixed = raws and pixels * (RAW_HELD_BYTES_PER_PIXEL * (raws - 1) + RAW_DECODE_BYTES_PER_PIXEL)
    per_pixel = BAND_BYTES_PER_PIXEL + (OTHER_BYTES_PER_PIXEL + 24) * (len(job["sources"]) - raws) + 24 * raws
    return int(fixed), float(per_pixel * job["size"][0])


BAND_BYTES_PER_PIXEL = 64  # radiance, valid, weights, bracket sums, merged, the mask's float copy
BAND_CAP = 256 * 10**6  # bytes of a band beyond which a band is not worth a second decode


class JobSources:
    """The sources of a job opened for reading band by band (a RAW file decoded once, its 16-bit
    output kept; other files read by rows through OpenImageIO), the vignetting gain map with them.
    ``band(y0, y1)`` -> the merged radiance and valid mask of those rows, as job_radiance computed
    them for the whole image; with ``count`` it also counts valid pixels and, at the last row,
    raises the capture's one-line errors (a black or saturated photo)."""

    def __init__(self, job: dict):
        self.job = job
        self.inverse = inverse_table(job["response"], job["response_curve"])
        self.single = len(job["sources"]) == 1
        self._raw: dict[int, tuple] = {}
        self._readers: dict[int, ImageRowReader] = {}
        self._gain: ImageRowReader | None = None
        self.counts = [0] * len(job["sources"])
        self.seen = [{"alpha": False, "black": True} for _ in job["sources"]]
        self.valid_count = 0
        self.infos: list[dict] = [{} for _ in job["sources"]]
        self.open()

    def open(self) -> None:
        job = self.job
        for i, src in enumerate(job["sources"]):
            path = Path(src["path"])
            if src["kind"] == "raw":
                if i not in self._raw:
                    rgb16, valid, info, all_black = decode_raw16(path, job["raw_wb"], job["saturation"])
                    self._raw[i] = (rgb16, valid, all_black)
                    self.infos[i] = info
                    self.height, self.width = valid.shape
            else:
                self._readers[i] = ImageRowReader(path)
                self.height, self.width = self._readers[i].height, self._readers[i].width
        if job["vignetting"]:
            self._gain = ImageRowReader(job["vignetting"])
            if (self._gain.width, self._gain.height) != (self.width, self.height):
                name = Path(job["sources"][0]["path"]).name
                raise UserError(
                    f"{job['vignetting']}: vignetting map is {self._gain.width}x{self._gain.height} but "
                    f"{name} is {self.width}x{self.height}; calibrate vignetting with this camera's images"
                )

    def rewind(self) -> None:
        """Back to the first row (OpenImageIO readers reopened; RAW decodes kept)."""
        self.close(raw=False)
        self.open()

    def close(self, raw: bool = True) -> None:
        for reader in self._readers.values():
            reader.close()
        self._readers = {}
        if self._gain is not None:
            self._gain.close()
            self._gain = None
        if raw:
            self._raw = {}

    def __enter__(self) -> "JobSources":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def band(self, y0: int, y1: int, count: bool = False) -> tuple[np.ndarray, np.ndarray]:
        job = self.job
        gain = self._gain.rows(y0, y1)[:, :, :3] if self._gain is not None else None
        num = den = None
        for i, src in enumerate(job["sources"]):
            radiance, valid, level = self._source_rows(i, src, y0, y1, gain, want_level=not self.single)
            if count:
                self.counts[i] += int(np.count_nonzero(valid))
                if y1 == self.height:
                    self._check(i, src)
            if self.single:  # no merge: the scaled image with its mask
                if count:
                    self.valid_count += int(np.count_nonzero(valid))
                return radiance, valid
            weight = _bracket_weight(valid, level, job["saturation"], src["scale"])
            num = radiance * weight[:, :, None] if num is None else num + radiance * weight[:, :, None]
            den = weight if den is None else den + weight
        valid = den > 0
        merged = np.where(valid[:, :, None], num / np.where(valid, den, 1.0)[:, :, None], 0.0).astype(np.float32)
        if count:
            self.valid_count += int(np.count_nonzero(valid))
        return merged, valid

    def _source_rows(self, i: int, src: dict, y0: int, y1: int, gain: np.ndarray | None, want_level: bool):
        """Rows y0:y1 of source ``i`` as linear radiance (its exposure scale applied, vignetting
        ``gain`` divided out, saturated pixels 0), their valid mask and the raw level (brackets)."""
        if src["kind"] == "raw":
            rgb16, valid, all_black = self._raw[i]
            rgb = raw_rows_to_float(rgb16[y0:y1])
            valid = valid[y0:y1]
            level = rgb.max(axis=2) if want_level else None
            self.seen[i] = {"alpha": True, "black": all_black}
        else:
            rgb, valid, level, info, seen = decode_other_rows(
                self._readers[i], y0, y1, src["kind"], self.inverse, self.job["saturation"]
            )
            self.infos[i] = info
            self.seen[i] = {"alpha": self.seen[i]["alpha"] or seen["alpha"], "black": self.seen[i]["black"] and seen["black"]}
            rgb_gains = np.asarray(self.job["rgb_gains"], dtype=np.float32)
            if np.any(rgb_gains != 1):
                rgb = rgb * rgb_gains
        if gain is not None:
            rgb = rgb / gain
        radiance = np.multiply(rgb, np.float32(src["scale"]), dtype=np.float32)
        radiance[~valid] = 0.0
        return radiance, valid, level

    def _check(self, i: int, src: dict) -> None:
        """The whole-image errors of source ``i``, once its last row is counted."""
        path = Path(src["path"])
        if not self.seen[i]["alpha"]:
            raise no_alpha_error(path)
        if self.seen[i]["black"]:
            raise UserError(f"{path}: the image is entirely black; check the lens cap and exposure, or remove it")
        if not self.counts[i]:
            raise UserError(f"{path}: every pixel is saturated; shoot it darker (or bracket it) or remove it")

    def entries(self) -> list[dict]:
        """The sources' manifest entries (after a counting pass over every row)."""
        out = []
        for i, src in enumerate(self.job["sources"]):
            info = self.infos[i]
            out.append(
                {
                    "file": Path(src["path"]).name,
                    "format": src["format"],
                    "exposure_time_s": src["exposure_time_s"],
                    "iso": src["iso"],
                    "f_number": src["f_number"],
                    "scale": src["scale"],
                    "black_level": info.get("black_level"),
                    "white_level": info.get("white_level"),
                    "saturated_fraction": round(1.0 - self.counts[i] / (self.height * self.width), 6),
                }
            )
        return out


def _bracket_weight(valid: np.ndarray, level: np.ndarray | None, saturation: float, scale: float) -> np.ndarray:
    """A bracket's merge weight (H, W), > 0 where valid: its exposure (photon-noise SNR grows with
    it, 1 / ``scale``) x a roll-off below the clip level ``saturation`` of the raw ``level``."""
    rolloff = np.ones(valid.shape, np.float32)
    if level is not None:
        rolloff = np.clip((saturation - level) / (ROLLOFF * saturation), 1e-3, 1.0).astype(np.float32)
    return np.where(valid, rolloff / np.float32(scale), 0.0).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# White balance policy: one set of gains for the whole capture


def resolve_white_balance(
    settings: Settings, config: CaptureConfig, probes: list[Probe], inverse: np.ndarray, saturation: float
) -> tuple[list[float], list[float], dict]:
    """(raw-channel multipliers R,G,B,G2 for RAW files, RGB gains for decoded files, record for the manifest)."""
    kind, values = parse_wb(settings.wb)
    if kind == "capture":
        if config.wb_multipliers:
            kind, values = "multipliers", config.wb_multipliers
        elif config.wb_gray_patch:
            kind, values = "gray", config.wb_gray_patch
        else:
            kind = "camera"
    raws = [p for p in probes if p.kind == "raw"]
    if kind == "multipliers":
        r, g, b = values
        return [r, g, b, g], [r, g, b], {"policy": "multipliers", "multipliers": [r, g, b]}
    if kind == "camera":
        wb = list(raws[0].camera_wb) if raws else [1.0, 1.0, 1.0, 1.0]
        if len(wb) == 4 and wb[3] == 0:
            wb[3] = wb[1]
        record = {
            "policy": "camera",
            "from": raws[0].path.name if raws else None,
            "raw_multipliers": wb,
            "decoded_files": "as encoded",
        }
        return wb, [1.0, 1.0, 1.0], record
    # gray card in the first image
    first = probes[0]
    if any((p.kind == "raw") != (first.kind == "raw") for p in probes):
        raise UserError(f"{first.path}: gray-card white balance needs all images RAW or all decoded; give --wb r,g,b instead")
    x0, y0, x1, y1 = values
    if x1 > first.width or y1 > first.height:
        raise UserError(f"{first.path}: gray patch {values} lies outside the {first.width}x{first.height} image")
    if first.kind == "raw":
        rgb, valid, _, _, _ = decode_raw(first.path, (1.0, 1.0, 1.0, 1.0), saturation, camera_space=True)
    else:
        rgb, valid, _, _, _ = decode_other(first.path, first.kind, inverse, saturation)
    patch = rgb[y0:y1, x0:x1][valid[y0:y1, x0:x1]]
    if len(patch) == 0 or np.any(patch.mean(axis=0) <= 0):
        raise UserError(f"{first.path}: gray patch {values} is saturated or black; choose another patch")
    mean = patch.mean(axis=0)
    gains = [float(mean[1] / mean[0]), 1.0, float(mean[1] / mean[2])]
    record = {"policy": "gray", "patch": list(values), "from": first.path.name, "multipliers": gains}
    return gains + [1.0], gains, record


# ----------------------------------------------------------------------------------------------


def _check_sizes(probes: list[Probe], config: CaptureConfig) -> None:
    if config.camera is not None:
        cam = read_camera_json(config.camera)
        expected, source = (cam.width, cam.height), f"camera.json ({config.camera.name})"
    else:
        sizes = [(p.width, p.height) for p in probes]
        expected = max(set(sizes), key=sizes.count)
        source = "most images"
    for p in probes:
        if (p.width, p.height) != expected:
            raise UserError(
                f"{p.path}: image is {p.width}x{p.height} but {source} {expected[0]}x{expected[1]}; "
                "all images of a capture must come from one camera at one size (remove or re-export it)"
            )


def build_jobs(capture: Path, work: Path, settings: Settings) -> list[dict]:
    """Probe every file and describe each output as a picklable job (validates the whole capture first)."""
    config = read_capture_config(capture)
    files = capture_photos(capture)
    groups = plan_groups(files, config, settings.bracket_size)
    probes = [probe(p) for p in files]
    _check_sizes(probes, config)
    by_name = {p.path.name: p for p in probes}
    exposure = exposure_scales(probes, config)
    inverse = inverse_table(config.response, config.response_curve)
    raw_wb, rgb_gains, wb_record = resolve_white_balance(settings, config, probes, inverse, settings.saturation)
    extra = [str(p) for p in _capture_files(capture, config)]
    content = fingerprints(files + [Path(p) for p in extra], work)  # in each job's recipe: a replaced file redoes it
    folder = linear_dir(work)
    jobs = []
    for key, members in groups.items():
        sources = []
        for m in members:
            pr = by_name[m.name]
            fmt = "raw" if pr.kind == "raw" else m.suffix.lower().lstrip(".") + ("" if pr.kind == "float" else f"-{pr.kind}")
            sources.append({"path": str(m), "kind": pr.kind, "format": fmt, **exposure[m.name]})
        size = (by_name[members[0].name].width, by_name[members[0].name].height)
        jobs.append(
            {
                "key": key,
                "sources": sources,
                "exr": str(folder / f"{key}.exr"),
                "size": size,
                "mask": str(folder / "masks" / f"{key}.png"),
                "saturation": settings.saturation,
                "raw_wb": raw_wb,
                "rgb_gains": rgb_gains,
                "white_balance": wb_record,
                "response": str(config.response) if config.response else None,
                "response_curve": config.response_curve,
                "vignetting": str(config.vignetting) if config.vignetting else None,
                "settings": {
                    k: v for k, v in settings_dict(settings).items() if k not in ("workers", "memory_limit")
                },  # how, not what
                "orientation": "as stored",  # in the recipe: RAW outputs made when LibRaw turned them are redone
                "content": {p: content[str(Path(p).resolve())] for p in [str(m) for m in members] + extra},
            }
        )
    return jobs


def _linearize_job_collected(job: dict, rows: int | None = None) -> tuple[dict, list]:
    """linearize_job in a worker process: its files stay under temporary names, handed back to
    the parent so that they are committed with the rest of the stage."""
    with collected_writes() as written:
        entry = linearize_job(job, rows)
    return entry, written


def exit_with(stage_pid: int, every_s: float = 0.5) -> None:
    """Pool worker initializer: a daemon thread ends the worker (os._exit) once the stage's process
    ``stage_pid`` is gone.  A ``kill -9`` of sigrend otherwise leaves the workers blocked on the
    pool's queue for good, and the forkserver with them (every forkserver child holds its
    keep-alive pipe, so prctl's PR_SET_PDEATHSIG on the forkserver parent would not fire)."""
    import threading
    import time

    def watch() -> None:
        while True:
            time.sleep(every_s)
            try:
                os.kill(stage_pid, 0)
            except ProcessLookupError:
                os._exit(1)
            except PermissionError:  # the pid now belongs to another user's process: ours is gone
                os._exit(1)

    threading.Thread(target=watch, daemon=True, name="exit-with-stage").start()


def run_jobs(jobs: list[dict], workers: int, force: bool = False, budget: Budget | None = None) -> dict[str, dict]:
    """Run ``linearize_job`` for every job not already fresh (every job with ``force``); serial or
    in a process pool of as many workers as ``budget`` leaves room for, with a progress bar."""
    entries: dict[str, dict] = {}
    todo = []
    for job in jobs:
        fresh = None if force else _fresh_entry(job)
        if fresh is not None:
            entries[job["key"]] = fresh
        else:
            todo.append(job)
    workers = workers or os.cpu_count() or 1
    if multiprocessing.current_process().daemon:
        workers = 1  # a daemonic process (a Dask worker of `sigrend batch`) may not start children
    workers, rows = plan_memory(todo, min(workers, max(len(todo), 1)), budget or Budget.of(DEFAULT_LIMIT))
    bar = progress(total=len(todo), desc="linearize", unit="img")
    try:
        if workers == 1 or len(todo) <= 1:
            for job in todo:
                entries[job["key"]] = linearize_job(job, rows)
                bar.update()
        else:
            # forkserver, not fork: OpenImageIO's thread pool in this process would deadlock forked children
            context = multiprocessing.get_context("forkserver")
            with cf.ProcessPoolExecutor(
                max_workers=workers, mp_context=context, initializer=exit_with, initargs=(os.getpid(),)
            ) as pool:
                futures = {pool.submit(_linearize_job_collected, job, rows): job["key"] for job in todo}
                try:
                    for fut in cf.as_completed(futures):
                        entries[futures[fut]], written = fut.result()
                        commit_writes(written)  # into the stage's transaction (pipeline.workdir)
                        bar.update()
                except BaseException:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise
    finally:
        bar.close()
    return entries


def plan_memory(todo: list[dict], workers: int, budget: Budget) -> tuple[int, int | None]:
    """(workers, image rows decoded at a time) for ``todo`` within ``budget``: as many of ``workers``
    as the largest job leaves room for, each with bands of at most BAND_CAP bytes (None: whole
    images).  UserError (one line: what to reduce) when even one job at a time cannot fit."""
    if not todo:
        return 1, None
    job = max(todo, key=lambda j: job_bytes(j)[0] + job_bytes(j)[1] * j["size"][1])
    fixed, per_row = job_bytes(job)
    width, height = job["size"]
    least = min(height, 16)
    free = budget.free()
    need = fixed + least * per_row
    if need > free:
        raws = [Path(s["path"]).name for s in job["sources"] if s["kind"] == "raw"]
        what = (
            f"{Path(job['sources'][0]['path']).name}: linearizing {'a bracket of ' if len(job['sources']) > 1 else ''}"
            f"{len(job['sources'])} photo(s) of {width * height / 1e6:.0f} MP"
        )
        reduce = (
            "RAW photos are decoded whole by LibRaw: use smaller photos or fewer brackets per image (or "
            "JPEG/TIFF files, read by rows)"
            if raws
            else "use smaller photos"
        )
        raise budget.too_small(need, what, reduce)
    band = min(BAND_CAP, height * per_row)
    workers = budget.workers(workers, fixed + int(band), processes=workers > 1)
    share = free // workers - fixed - (WORKER_BASE if workers > 1 else 0)
    rows = band_rows(width, per_row / width, min(BAND_CAP, max(share, 0)), height, least)
    return workers, (None if rows >= height else rows)


def response_note(jobs: list[dict]) -> str | None:
    """One line saying which curve 8-bit files were linearized with when capture.toml did not give a
    calibrated response (the curve is then an assumption the user should see)."""
    eight_bit = [s for j in jobs if j["response"] is None for s in j["sources"] if s["kind"] == "uint8"]
    if not eight_bit:
        return None
    curve = jobs[0]["response_curve"]
    why = (
        'no [response] in capture.toml; a linear machine-vision camera needs [response] curve = "linear", '
        'a calibrated one path = "response.json"'
        if curve == "srgb"
        else "[response] curve in capture.toml"
    )
    return f"linearize: {len(eight_bit)} 8-bit file(s) linearized with the {curve} curve ({why})"


def run(*, capture: Path, work: Path, settings: Settings, force: bool = False) -> list[Path]:
    """Linearize every image of the capture (``force``: even those whose EXR records the same
    recipe); returns the written EXRs, masks and manifest.json."""
    jobs = build_jobs(Path(capture), Path(work), settings)
    config = read_capture_config(capture)
    chart = None if config.chart is None else measure_capture_chart(config, jobs, work)  # before the long part
    entries = run_jobs(jobs, settings.workers, force, Budget.of(settings.memory_limit))
    manifest = write_manifest(work, entries)
    if (note := response_note(jobs)) is not None:
        print(note, file=sys.stderr)
    written = [Path(j["exr"]) for j in jobs] + [Path(j["mask"]) for j in jobs]
    folder = linear_dir(work)
    previous = [p for p in [*folder.glob("*.exr"), *(folder / "masks").glob("*.png")] if not p.name.startswith(".")]
    for stale in set(previous) - set(written):
        stale.unlink()  # a photo removed from the capture leaves no linear image behind
    if chart is None:
        chart_path(work).unlink(missing_ok=True)  # a [chart] removed from capture.toml leaves none behind
        return written + [manifest]
    return written + [manifest, chart]


def measure_capture_chart(config: CaptureConfig, jobs: list[dict], work: Path) -> Path:
    """capture.toml [chart] measured in its photo's linear radiance (pipeline.chart.measure_chart)
    -> WORK/linear/chart.json; one line naming [chart] when its photo is not in the capture, or the
    chart is not found or cannot be measured."""
    spec = config.chart
    where = f"{config.source} [chart] {spec.kind} {spec.image!r}"
    job = next((j for j in jobs if any(Path(src["path"]).name == spec.image for src in j["sources"])), None)
    if job is None:
        names = [Path(src["path"]).name for j in jobs for src in j["sources"]]
        raise UserError(f"{where}: no such photo in images/{did_you_mean(spec.image, names)}")
    rgb, valid, _ = job_radiance(job)
    record = measure_chart(spec, rgb, valid, where)
    summary = ", ".join(f"{v:.4g}" for v in record["irradiance"])
    print(f"linearize: {spec.kind} in {spec.image}: irradiance on its plane ({summary}) in the photos' units", file=sys.stderr)
    return write_chart(work, {**record, "image": spec.image, "key": job["key"]})
