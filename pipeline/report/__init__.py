"""WORK/report.html: one self-contained page (PNGs embedded as base64) about a capture's run.

Sections, each shown when the stage that feeds it has run: summary and stage timings
(WORK/run.json), photos and masks (WORK/linear/), cameras (a 3D plot of the camera centres and
viewing directions around the mesh's bounding box), sample coverage (WORK/samples_coverage.png),
the fitted lighting (equirect map + spheres rendered under it) beside the fit's own plots
(per-band spectrum and recoverability), the BRDF, relit vs photo with error maps on the held-out
views (WORK/relight/check/), and the settings every stage ran with.  This module reads the work
folder's files and assembles the page; the figures are pipeline.report.figures', the tables
pipeline.report.tables'.  It imports no stage.
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path

import numpy as np

from pipeline.io.brdf import read_brdf
from pipeline.io.images import read_image
from pipeline.io.lighting import read_lighting_sh
from pipeline.io.mesh import mesh_path, read_mesh, read_vertex_albedo
from pipeline.io.poses import capture_poses_path, read_poses
from pipeline.io.run_summary import (
    StageResult,
    method_description,
    noise_phrase,
    relight_check,
    samples_holdout,
    stage_table,
    summary_lines,
)
from pipeline.report.figures import (
    array_png,
    camera_plot,
    figure_png,
    masked_overlay,
    pyplot,
    residual_plot,
    spectrum_plot,
    sphere_renders,
    texture_views,
    tonemap,
)
from pipeline.report.tables import brdf_table, fit_tables, flat_rows, format_value, html_table
from pipeline.workdir import write_text

MAX_PHOTOS = 12

THUMB_PX = 160


def _img_tag(png: bytes, alt: str, width: int | None = None) -> str:
    size = f' width="{width}"' if width else ""
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"{size}>'


def _file_tag(path: Path, alt: str, width: int | None = None) -> str:
    return _img_tag(Path(path).read_bytes(), alt, width) if Path(path).exists() else ""


def _thumb(img: np.ndarray) -> np.ndarray:
    """Nearest-neighbour downscale so the longer side is at most THUMB_PX."""
    step = max(1, int(np.ceil(max(img.shape[:2]) / THUMB_PX)))
    return img[::step, ::step]


def _section(title: str, body: str) -> str:
    return f"<section><h2>{html.escape(title)}</h2>\n{body}\n</section>\n"


def _missing(what: str) -> str:
    return f'<p class="missing">{html.escape(what)}</p>'


def _json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None


# --------------------------------------------------------------------------------------- sections


def _summary(capture: Path, work: Path) -> str:

    parts = [
        f"<p>capture <code>{html.escape(str(Path(capture).resolve()))}</code>, "
        f"work folder <code>{html.escape(str(Path(work).resolve()))}</code></p>"
    ]
    lines = summary_lines(work)
    if lines:
        parts.append("<ul>" + "".join(f"<li>{html.escape(s)}</li>" for s in lines) + "</ul>")
    run = _json(Path(work) / "run.json")
    if run:
        results = [StageResult(s["name"], s["outputs"], s["seconds"], s["skipped"]) for s in run["stages"]]
        parts.append("<h3>Stage timings</h3><pre>" + html.escape(stage_table(results)) + "</pre>")
    return _section("Summary", "\n".join(parts))


def _warnings(work: Path) -> str:
    """The run's warnings (WORK/run.json "warnings", recorded by the runner), each once."""
    run = _json(Path(work) / "run.json")
    if not run or "warnings" not in run:
        return ""
    found = run["warnings"]
    body = (
        '<ul class="warnings">' + "".join(f"<li>{html.escape(str(w))}</li>" for w in found) + "</ul>"
        if found
        else "<p>The run raised no warnings.</p>"
    )
    return _section(f"Warnings ({len(found)})", body)


def _photos(capture: Path, work: Path) -> str:

    linear = Path(work) / "linear"
    exrs = sorted(p for p in linear.glob("*.exr") if not p.name.startswith("."))[:MAX_PHOTOS] if linear.is_dir() else []
    if not exrs:
        return _section("Photos and masks", _missing("no linear images yet (linearize has not run)"))
    cells = []
    for exr in exrs:
        img = _thumb(read_image(exr))
        shown = tonemap(img)
        mask_file = linear / "masks" / f"{exr.stem}.png"
        caption = exr.stem
        if mask_file.exists():
            valid = _thumb(read_image(mask_file))[..., 0] > 0.5
            shown = masked_overlay(shown, valid)
            caption += f" — {100 * (1 - valid.mean()):.3g}% masked"
        tag = _img_tag(array_png(shown), exr.name)
        cells.append(f'<figure class="photo">{tag}<figcaption>{html.escape(caption)}</figcaption></figure>')
    note = (
        "<p>Linear photos (tone-mapped for display); pixels their validity mask leaves out (saturated, "
        'outside the image\'s valid area) are tinted <span class="swatch"></span> red and not used.</p>'
    )
    return _section("Photos and masks", note + '<div class="grid">' + "".join(cells) + "</div>")


def _cameras(capture: Path, work: Path) -> str:

    path = capture_poses_path(capture, work)
    if not path.exists():
        return _section("Cameras", _missing("no poses yet (the poses stage has not run)"))
    poses = read_poses(path)
    bounds = None
    try:
        bounds = read_mesh(mesh_path(capture)).bounds
    except Exception:  # the report shows what it can; a bad mesh is reported by the stages
        bounds = None
    summary = _json(Path(work) / "poses_summary.json") or {}
    text = f"<p>{len(poses.images)} views from <code>{html.escape(str(path))}</code>.</p>"
    if "registration_residual_fraction_of_size" in summary:  # registered to the mesh (stages/poses/mesh.py)
        text += (
            f"<p>Registered to the mesh: RMS {summary['registration_residual_mm']:.3g} mm "
            f"({100 * summary['registration_residual_fraction_of_size']:.2g}% of its size), "
            f"{100 * summary['registration_points_used_fraction']:.0f}% of {summary['registration_points']} "
            "SfM points on it.</p>"
        )
    if summary:
        text += (
            "<details><summary>poses_summary.json</summary>" + html_table(flat_rows(summary), ["entry", "value"]) + "</details>"
        )
    return _section("Cameras", text + _img_tag(camera_plot(poses, bounds, samples_holdout(work)), "cameras"))


def _coverage(work: Path) -> str:
    png = Path(work) / "samples_coverage.png"
    summary = _json(Path(work) / "samples_summary.json")
    body = _file_tag(png, "sample coverage") or _missing("no samples yet (the samples stage has not run)")
    if summary:
        rows = [["samples kept", summary.get("count")], ["pixels considered", summary.get("pixels")]]
        rows += [[f"dropped: {k.replace('_', ' ')}", v] for k, v in (summary.get("drops") or {}).items()]
        for name in ("normals", "reflections"):
            cov = (summary.get("coverage") or {}).get(name)
            if cov:
                rows.append(
                    [f"{name}: sphere covered", f"{100 * cov['fraction']:.3g}% ({cov['cells_hit']}/{cov['cells']} cells)"]
                )
        if summary.get("holdout"):
            rows.append(["held out of the fit", summary["holdout"]])
        body += html_table(rows, ["", "value"])
    return _section("Sample coverage", body)


def _lighting(work: Path) -> str:

    fit = Path(work) / "fit"
    sh_file = fit / "lighting_sh.json"
    if not sh_file.exists():
        return _section("Fitted lighting", _missing("no fitted lighting yet (the fit stage has not run)"))
    parts = []
    if (fit / "lighting.exr").exists():
        env = read_image(fit / "lighting.exr")
        parts.append(
            "<h3>Equirect map (DESIGN.md convention, row 0 = zenith)</h3>"
            + _img_tag(array_png(tonemap(env)), "fitted lighting", 512)
        )
    coeffs = read_lighting_sh(sh_file)
    brdf = read_brdf(fit / "brdf.json") if (fit / "brdf.json").exists() else None
    parts.append("<h3>Spheres under the fitted lighting</h3>" + _img_tag(sphere_renders(coeffs, brdf), "spheres"))
    report = _json(fit / "report.json") or {}
    if report.get("bands"):
        parts.append(
            "<h3>What the data determine, band by band</h3>"
            + _img_tag(spectrum_plot(report["bands"]), "spectrum")
            + html_table(
                [[b.get("l"), b.get("label"), b.get("snr"), b.get("snr_data"), b.get("energy")] for b in report["bands"]],
                ["band l", "label", "snr (vs residual)", "snr (vs photo noise)", "energy"],
            )
        )
    if report.get("residuals_per_view"):
        parts.append("<h3>Fit residual per view</h3>" + _img_tag(residual_plot(report["residuals_per_view"]), "residuals"))
    return _section("Fitted lighting", "\n".join(parts))


def _brdf(capture: Path, work: Path) -> str:
    fit = Path(work) / "fit"
    brdf = _json(fit / "brdf.json")
    if brdf is None:
        return _section("BRDF", _missing("no fitted BRDF yet (the fit stage has not run)"))
    truth = _json(Path(capture) / "gt" / "brdf.json")
    report = _json(fit / "report.json")
    body = brdf_table(brdf, truth)
    scale = (report or {}).get("scale_convention")
    if truth is not None and isinstance(scale, dict) and scale.get("source"):
        body += (
            f"<p>The base colour's level (and the lighting's) is fixed by: {html.escape(str(scale['source']))}; "
            "where that is a convention, a common factor in the base colour's error is that convention's.</p>"
        )
    if (fit / "albedo.ply").exists():
        import trimesh

        tex = trimesh.load(fit / "albedo.ply", force="mesh", process=False)
        colour = read_vertex_albedo(fit / "albedo.ply", len(tex.vertices))
        if colour is not None:
            word = "albedo" if brdf.get("model") == "lambert" else "base colour"
            body += f"<h3>Textured {word} (fit/albedo.ply; the table holds its mean)</h3>" + _img_tag(
                texture_views(np.asarray(tex.vertices), np.asarray(tex.faces), colour), "texture"
            )
    texels = (report or {}).get("texels") or {}
    if (fit / "textures" / "base_color.png").exists():
        body += _texels(fit / "textures", texels)
    elif texels.get("why") or texels.get("note"):  # the per-texel step was skipped, or kept no map: say why
        said = "; ".join(html.escape(texels[k]) for k in ("why", "note") if texels.get(k))
        body += f"<p><b>Base colour per texel:</b> {'none kept' if texels.get('ran') else 'not fitted'} ({said}).</p>"
    selection = (report or {}).get("model_selection") or {}
    if selection.get("by") == "training residual":
        body = f"<p><b>Not validated:</b> {html.escape(selection['why'])} (kept: {html.escape(selection['kept'])}).</p>" + body
    if report:
        body += fit_tables(report)
    return _section("BRDF", body)


def _texels(folder: Path, entry: dict) -> str:
    """fit/textures/: the base colour map and its relative uncertainty, and the levels the held-out
    views chose (report.json "texels")."""

    base = read_image(folder / "base_color.png")[:, :, :3]
    std = read_image(folder / "base_color_std.exr")[:, :, :3].astype(float)
    linear = read_image(folder / "base_color.exr")[:, :, :3].astype(float)
    seen = np.isfinite(std).all(axis=2)
    relative = np.full(seen.shape, np.nan)
    relative[seen] = std[seen].mean(axis=1) / np.maximum(linear[seen].mean(axis=1), 1e-3)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.2))
    axes[0].imshow(base, interpolation="nearest")
    axes[0].set_title("base colour (sRGB)")
    shown = axes[1].imshow(np.log10(relative), cmap="viridis", vmin=-3, vmax=0, interpolation="nearest")
    axes[1].set_facecolor("0.6")
    axes[1].set_title("std / value (log10); grey: no sample")
    fig.colorbar(shown, ax=axes[1], fraction=0.046, pad=0.04, label="log10 relative std")
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    rows = [
        ["levels kept", entry.get("choice", "?")],
        ["why the step ran", entry.get("why", "?")],
        ["texel size (mm)", format_value(entry.get("atlas", {}).get("texel_mm"))],
        ["texels with samples / in charts", f"{entry.get('texels_with_samples', '?')} / {entry.get('texels_in_charts', '?')}"],
        ["samples", format_value(entry.get("samples"))],
    ]
    cands = [
        [c["name"], format_value(c["validation_rmse"]), format_value(c["train_rmse"])]
        for c in entry.get("vertex_level", {}).get("candidates", []) + entry.get("texel_level", {}).get("candidates", [])
    ]
    return (
        "<h3>Base colour per texel (fit/textures/; grey texels saw no sample: their colour is the "
        "per-vertex level's)</h3>"
        + _img_tag(figure_png(fig), "base colour map and uncertainty")
        + html_table(rows)
        + (html_table(cands, ["level", "held-out RMSE", "training RMSE"]) if cands else "")
    )


def _relight(work: Path) -> str:

    folder = Path(work) / "relight" / "check"
    check = relight_check(work)
    if check is None:
        return _section("Relit vs photo", _missing("no relight comparison yet (the relight stage has not run)"))
    which = "held-out views (not used by the fit)" if check["heldout"] else "training views (no view was held out)"
    head = (
        f"<p>{len(check['views'])} {which}: relative RMS error <b>{100 * check['relative_error']:.2f}%</b>"
        + html.escape(noise_phrase(check))
        + (f" after one global scale {check['scale']:.3g}" if check.get("scale_fitted") else "")
        + f". Relit images made by the <b>{html.escape(method_description(check))}</b>"
        + f"; error maps show |relit − photo| / mean photo from 0 (black) to "
        f"{100 * check.get('error_map_range', 0.2):.0f}% (white).</p>"
    )
    cells = []
    for key, entry in check["views"].items():
        stem = Path(key).stem
        imgs = "".join(
            _file_tag(folder / f"{stem}{suffix}.png", f"{stem}{suffix}", THUMB_PX) for suffix in ("_photo", "", "_error")
        )
        cells.append(
            f'<figure class="photo">{imgs}<figcaption>{html.escape(key)}: photo | relit | error — '
            f"{100 * entry['relative_error']:.2f}%{html.escape(noise_phrase(entry))}</figcaption></figure>"
        )
    extra = []
    for sub in sorted(p for p in (Path(work) / "relight").iterdir() if p.is_dir() and p.name != "check"):
        pngs = sorted(p for p in sub.glob("*.png") if not p.name.startswith("."))[:MAX_PHOTOS]
        if pngs:
            extra.append(f"<h3>Relit under {html.escape(sub.name)}</h3>" + "".join(_file_tag(p, p.stem, THUMB_PX) for p in pngs))
    return _section("Relit vs photo", head + "".join(cells) + "".join(extra))


def _size(n: int) -> str:
    """A file size in B, kB, MB or GB (decimal)."""
    if n < 1000:
        return f"{n} B"
    for unit in ("kB", "MB", "GB"):
        n /= 1000.0
        if n < 1000 or unit == "GB":
            return f"{n:.1f} {unit}"


def _export(work: Path) -> str:
    """The exported asset (WORK/export, `sigrend export`'s default place): its files with their sizes
    and its previews under two bundled maps; nothing when it has not been exported there."""
    folder = Path(work) / "export"
    manifests = sorted(folder.glob("*.export.json"), key=lambda p: p.stat().st_mtime)  # asset.glb.export.json, ...
    manifest = _json(manifests[-1]) if manifests else None
    if not manifest:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(f['file'])}</td><td>{_size(int(f['bytes']))}</td></tr>" for f in manifest.get("files", [])
    )
    previews = "".join(
        f"<figure>{_file_tag(folder / name, name, THUMB_PX)}<figcaption>under the bundled "
        f"{html.escape(spec)} map (sigrend's renderer)</figcaption></figure>"
        for spec, name in manifest.get("previews", {}).items()
    )
    body = (
        f"<p>{html.escape(manifest.get('frame', ''))}; the lighting map: "
        f"{html.escape(manifest.get('lighting_mapping', ''))} (docs/export.md).</p>"
        f"<table>{rows}</table>{previews}"
    )
    return _section(f"Exported asset ({html.escape(str(folder))})", body)


def _settings(work: Path) -> str:
    files = sorted(Path(work).glob("*.settings.json"))
    if not files:
        return ""
    body = "".join(
        f"<details><summary>{html.escape(p.name)}</summary>{html_table(flat_rows(_json(p) or {}), ['entry', 'value'])}</details>"
        for p in files
    )
    return _section("Settings", body)


STYLE = """body{font-family:sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
h2{border-bottom:1px solid #ccc;margin-top:1.5em}figure{display:inline-block;margin:4px;text-align:center;max-width:100%}
figcaption{font-size:12px}.missing{color:#999;font-style:italic}table{border-collapse:collapse;margin:4px 0}
td,th{border:1px solid #ddd;padding:2px 8px;text-align:left;vertical-align:top;overflow-wrap:anywhere}
th{background:#f3f3f3;font-weight:600}td{font-family:monospace}
pre{background:#f6f6f6;padding:6px;overflow-x:auto}img{max-width:100%;height:auto}
.photo img{border:1px solid #888;margin:1px}.swatch{display:inline-block;width:0.9em;height:0.9em;
background:rgb(255,26,26);vertical-align:middle;border:1px solid #888}
ul.warnings li{color:#8a4b00}summary{cursor:pointer;margin:4px 0}"""


def build_report(capture: Path, work: Path) -> str:
    """The report as one HTML string (no external references)."""
    capture, work = Path(capture), Path(work)
    sections = [
        _summary(capture, work),
        _warnings(work),
        _photos(capture, work),
        _cameras(capture, work),
        _coverage(work),
        _lighting(work),
        _brdf(capture, work),
        _relight(work),
        _export(work),
        _settings(work),
    ]
    return (
        '<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>sigrend report: '
        f"{html.escape(Path(capture).name)}</title><style>{STYLE}</style></head><body>\n"
        f"<h1>sigrend report: {html.escape(Path(capture).resolve().name)}</h1>\n" + "".join(sections) + "</body></html>\n"
    )


def write_report_html(capture: Path, work: Path) -> Path:
    """Write WORK/report.html atomically and return its path."""
    return write_text(Path(work) / "report.html", build_report(capture, work))
