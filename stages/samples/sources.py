"""samples' sources: which posed images are sampled, and their radiometric scales when linearize
has not run (the capture's own linear images and their EXIF exposures)."""

from __future__ import annotations

from pathlib import Path

from pipeline.errors import UserError
from pipeline.io.camera_decode import probe
from pipeline.io.camera_files import Exposure
from pipeline.io.linear_manifest import LINEAR_SUFFIXES
from pipeline.io.poses import Poses


def exif_radiance_scales(capture: Path, keys: list[str]) -> dict[str, float]:
    """Per capture image: N² / (t · ISO/100) from its EXIF, the linearize stage's convention.

    Factors absent from every image count as equal (1 s, ISO 100, f/1): plain radiance EXRs get
    scale 1.  A factor present in some images only -> UserError (run linearize with capture.toml).
    """
    exifs = {key: probe(Path(capture) / "images" / key).exif for key in keys}
    for factor in ("time", "iso", "fnumber"):
        missing = [k for k in keys if exifs[k].get(factor) is None]
        if missing and len(missing) < len(keys):
            raise UserError(
                f"{Path(capture) / 'images' / missing[0]}: no EXIF {factor} while other images have "
                "one, so their radiometric scales differ; run `sigrend linearize` (capture.toml "
                "[exposure] can give the value)"
            )
    scales = {}
    for key, exif in exifs.items():
        shot = Exposure(exif.get("time") or 1.0, exif.get("iso") or 100.0, exif.get("fnumber") or 1.0)
        scales[key] = 1.0 / shot.scale  # radiance per unit value, N^2 / (t ISO/100)
    return scales


def sampled_keys(poses: Poses, pose_file: Path, holdout) -> list[str]:
    """The posed images to sample (sorted), less ``holdout``; UserError on an unknown held-out key or none left."""
    unknown = sorted(set(holdout) - set(poses.images))
    if unknown:
        raise UserError(f"--holdout names image(s) not in {pose_file}: {', '.join(unknown)}")
    keys = sorted(set(poses.images) - set(holdout))
    if not keys:
        raise UserError(f"{pose_file}: no images left to sample{' after --holdout' if holdout else ''}; nothing to sample")
    return keys


def capture_exposure_scales(capture: Path, keys: list[str], pose_file: Path) -> dict[str, float]:
    """Without linearize's outputs: the capture's own linear images (each must exist and be linear),
    scaled by their EXIF exposures (exif_radiance_scales)."""
    for key in keys:
        if not (capture / "images" / key).exists():
            raise UserError(
                f"{capture / 'images' / key}: image listed in {pose_file} is missing from the "
                "capture; restore it or remove it from poses.json"
            )
        if Path(key).suffix.lower() not in LINEAR_SUFFIXES:
            raise UserError(f"{capture / 'images' / key}: not a linear image; run `sigrend linearize` first")
    return exif_radiance_scales(capture, keys)
