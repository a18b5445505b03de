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

The package: settings (Settings, --wb parsing), plan (the files of each output, exposures, white
balance, the jobs), jobs (one output image: decoding, merging, writing, its recipe and memory),
pool (the jobs run serially or in worker processes within the memory budget); this module is the
stage (inputs, outputs, run) and the capture's colour chart.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pipeline.chart import measure_chart
from pipeline.errors import UserError
from pipeline.io.capture_toml import CaptureConfig, did_you_mean, read_capture_config
from pipeline.io.chart_json import chart_path, write_chart
from pipeline.io.linear_manifest import linear_dir, manifest_path, write_manifest
from pipeline.io.photos import capture_photos
from pipeline.memory import Budget
from stages.linearize.jobs import (
    BAND_BYTES_PER_PIXEL,
    BAND_CAP,
    HEADER_KEY,
    ROLLOFF,
    JobSources,
    job_bytes,
    job_radiance,
    linearize_job,
)
from stages.linearize.plan import build_jobs, capture_files, exposure_scales, plan_groups, resolve_white_balance
from stages.linearize.pool import exit_with, plan_memory, run_jobs
from stages.linearize.settings import Settings, parse_wb

__all__ = [
    "BAND_BYTES_PER_PIXEL",
    "BAND_CAP",
    "HEADER_KEY",
    "ROLLOFF",
    "JobSources",
    "Settings",
    "build_jobs",
    "exit_with",
    "exposure_scales",
    "inputs",
    "job_bytes",
    "job_radiance",
    "linearize_job",
    "measure_capture_chart",
    "outputs",
    "parse_wb",
    "plan_groups",
    "plan_memory",
    "resolve_white_balance",
    "response_note",
    "run",
    "run_jobs",
]


def inputs(*, capture: Path, work: Path, settings: Settings) -> list[Path]:
    config = read_capture_config(capture)
    return capture_photos(capture) + capture_files(capture, config)


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
