"""linearize's jobs: one output image each (its files decoded, scaled, devignetted, merged, written
band by band), their recipes and memory."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.camera_decode import (
    OTHER_BYTES_PER_PIXEL,
    RAW_DECODE_BYTES_PER_PIXEL,
    RAW_HELD_BYTES_PER_PIXEL,
    decode_other_rows,
    decode_raw16,
    no_alpha_error,
    raw_rows_to_float,
)
from pipeline.io.images import ImageRowReader, ImageRowWriter
from pipeline.io.response_json import inverse_table

ROLLOFF = 0.1  # bracket weights fall linearly to 0 over the top 10 % below the saturation level
HEADER_KEY = "sigrend:linearize"  # EXR attribute holding the recipe digest and manifest entry


# ----------------------------------------------------------------------------------------------
# One job (an output image): decode its files, scale, devignette, merge, write


def _digest(job: dict) -> str:
    """The recipe of a job: everything it depends on (its pixel size, known from the files, is not)."""
    recipe = {k: v for k, v in job.items() if k != "size"}
    return hashlib.sha1(json.dumps(recipe, sort_keys=True).encode()).hexdigest()


def _read_header_entry(exr: Path) -> dict | None:
    import OpenImageIO as oiio  # lazily, as pipeline.io.images does: keeps `sigrend --help` fast

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


def fresh_entry(job: dict) -> dict | None:
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
