"""linearize's planning: which files make which output (brackets), their exposures, the capture's one
white balance, and each output described as a picklable job (validating the whole capture first)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from pipeline.errors import UserError
from pipeline.io.camera_decode import Probe, decode_other, decode_raw, probe
from pipeline.io.camera_files import Exposure
from pipeline.io.camera_json import read_camera_json
from pipeline.io.capture_toml import CAPTURE_TOML, CaptureConfig, did_you_mean, read_capture_config
from pipeline.io.linear_manifest import linear_dir
from pipeline.io.photos import capture_photos
from pipeline.io.response_json import inverse_table
from pipeline.settings import settings_dict
from pipeline.workdir import fingerprints
from stages.linearize.settings import Settings, parse_wb

# ----------------------------------------------------------------------------------------------
# Planning: which files make which output


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


def capture_files(capture: Path, config: CaptureConfig) -> list[Path]:
    return [p for p in (config.source, config.camera, config.response, config.vignetting) if p is not None]


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
# The jobs


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
    extra = [str(p) for p in capture_files(capture, config)]
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
