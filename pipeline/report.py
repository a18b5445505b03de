"""WORK/report.html: one self-contained page (PNGs embedded as base64) about a capture's run.

Sections, each shown when the stage that feeds it has run: summary and stage timings
(WORK/run.json), photos and masks (WORK/linear/), cameras (a 3D plot of the camera centres and
viewing directions around the mesh's bounding box), sample coverage (WORK/samples_coverage.png),
the fitted lighting (equirect map + spheres rendered under it) beside the fit's own plots
(per-band spectrum and recoverability), the BRDF, relit vs photo with error maps on the held-out
views (WORK/relight/check/), and the settings every stage ran with.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.material import material_from_brdf
from pipeline.core.shading import sphere_radiance
from pipeline.workdir import write_text

MAX_PHOTOS = 12
THUMB_PX = 160


def _figure():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _fig_png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    _figure().close(fig)
    return buf.getvalue()


def _img_tag(png: bytes, alt: str, width: int | None = None) -> str:
    size = f' width="{width}"' if width else ""
    data = base64.b64encode(png).decode("ascii")
    return f'<img src="data:image/png;base64,{data}" alt="{html.escape(alt)}"{size}>'


def _file_tag(path: Path, alt: str, width: int | None = None) -> str:
    return _img_tag(Path(path).read_bytes(), alt, width) if Path(path).exists() else ""


def _array_png(rgb: np.ndarray) -> bytes:
    """8-bit PNG bytes of an sRGB-encoded [0, 1] (H, W, 3) array (matplotlib's writer, no figure)."""
    plt = _figure()
    buf = io.BytesIO()
    plt.imsave(buf, np.clip(rgb, 0, 1), format="png")
    return buf.getvalue()


def _tonemap(linear: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    from pipeline.io.images import preview_exposure, srgb_encode

    rgb = np.asarray(linear, float)[..., :3]
    m = mask if mask is not None else np.ones(rgb.shape[:2], bool)
    return srgb_encode(rgb * preview_exposure(rgb, m))


def _thumb(img: np.ndarray) -> np.ndarray:
    """Nearest-neighbour downscale so the longer side is at most THUMB_PX."""
    step = max(1, int(np.ceil(max(img.shape[:2]) / THUMB_PX)))
    return img[::step, ::step]


def _section(title: str, body: str) -> str:
    return f"<section><h2>{html.escape(title)}</h2>\n{body}\n</section>\n"


def _missing(what: str) -> str:
    return f'<p class="missing">{html.escape(what)}</p>'


def _fmt(value) -> str:
    """A value as the page shows it: numbers to 3 significant digits, lists joined, None as '—'."""
    if isinstance(value, bool) or value is None:
        return "—" if value is None else ("yes" if value else "no")
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.3g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(_fmt(v) for v in value)
    if isinstance(value, dict):
        return "; ".join(f"{k}: {_fmt(v)}" for k, v in value.items())
    return str(value)


def _table(rows: list, header: list[str] | None = None) -> str:
    """An HTML table of ``rows`` (each a list of cells, formatted by _fmt and escaped)."""
    head = "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>" if header else ""
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(c))}</td>" for c in row) + "</tr>" for row in rows)
    return f"<table>{head}{body}</table>"


def _flat(doc: dict, prefix: str = "") -> list[list]:
    """Rows [key path, value] of a nested dict (lists of scalars stay one value)."""
    rows = []
    for k, v in doc.items():
        if isinstance(v, dict):
            rows += _flat(v, f"{prefix}{k}.")
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            rows.append([f"{prefix}{k}", f"{len(v)} entries"])
        else:
            rows.append([f"{prefix}{k}", v])
    return rows


def _json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None


# --------------------------------------------------------------------------------------- sections


def _summary(capture: Path, work: Path) -> str:
    from pipeline.io.run_summary import StageResult, stage_table, summary_lines

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
    from pipeline.io.images import read_image

    linear = Path(work) / "linear"
    exrs = sorted(p for p in linear.glob("*.exr") if not p.name.startswith("."))[:MAX_PHOTOS] if linear.is_dir() else []
    if not exrs:
        return _section("Photos and masks", _missing("no linear images yet (linearize has not run)"))
    cells = []
    for exr in exrs:
        img = _thumb(read_image(exr))
        shown = _tonemap(img)
        mask_file = linear / "masks" / f"{exr.stem}.png"
        caption = exr.stem
        if mask_file.exists():
            valid = _thumb(read_image(mask_file))[..., 0] > 0.5
            shown = masked_overlay(shown, valid)
            caption += f" — {100 * (1 - valid.mean()):.3g}% masked"
        tag = _img_tag(_array_png(shown), exr.name)
        cells.append(f'<figure class="photo">{tag}<figcaption>{html.escape(caption)}</figcaption></figure>')
    note = (
        "<p>Linear photos (tone-mapped for display); pixels their validity mask leaves out (saturated, "
        'outside the image\'s valid area) are tinted <span class="swatch"></span> red and not used.</p>'
    )
    return _section("Photos and masks", note + '<div class="grid">' + "".join(cells) + "</div>")


MASK_TINT = np.array([1.0, 0.1, 0.1])


def masked_overlay(rgb: np.ndarray, valid: np.ndarray, strength: float = 0.6) -> np.ndarray:
    """The display image ``rgb`` (H, W, 3) with the pixels not ``valid`` (H, W) blended towards MASK_TINT."""
    out = np.array(rgb, float)
    out[~valid] = (1 - strength) * out[~valid] + strength * MASK_TINT
    return out


def camera_plot(poses, bounds: np.ndarray | None, heldout: list[str]) -> bytes:
    """PNG: camera centres (held-out ones in orange) with viewing directions, and the mesh's bounding box."""
    from pipeline.core.camera import camera_center

    plt = _figure()
    fig = plt.figure(figsize=(5.5, 5))
    ax = fig.add_subplot(projection="3d")
    centres = np.array([camera_center(p.R, p.t) for p in poses.images.values()])
    axes = np.array([p.R[2] for p in poses.images.values()])  # +Z_cam in world = viewing direction
    span = float(np.ptp(centres, axis=0).max()) if len(centres) > 1 else 1.0
    held = np.array([k in heldout for k in poses.images])
    for sel, colour, label in ((~held, "tab:blue", "fit views"), (held, "tab:orange", "held-out views")):
        if sel.any():
            ax.scatter(*centres[sel].T, color=colour, label=label, s=18)
            ax.quiver(*centres[sel].T, *(axes[sel] * 0.15 * span).T, color=colour, linewidth=0.8)
    if bounds is not None:
        lo, hi = bounds
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        for i in range(8):
            for j in range(i + 1, 8):
                if np.sum(corners[i] != corners[j]) == 1:
                    ax.plot(*corners[[i, j]].T, color="k", linewidth=0.8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.set_aspect("equal")
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title("cameras (object frame, +Z up) and mesh bounding box", fontsize=9)
    return _fig_png(fig)


def _cameras(capture: Path, work: Path) -> str:
    from pipeline.io.poses import capture_poses_path, read_poses
    from pipeline.io.run_summary import samples_holdout

    path = capture_poses_path(capture, work)
    if not path.exists():
        return _section("Cameras", _missing("no poses yet (the poses stage has not run)"))
    poses = read_poses(path)
    bounds = None
    try:
        from pipeline.io.mesh import mesh_path, read_mesh

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
        text += "<details><summary>poses_summary.json</summary>" + _table(_flat(summary), ["entry", "value"]) + "</details>"
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
        body += _table(rows, ["", "value"])
    return _section("Sample coverage", body)


def principled_sphere(coeffs: np.ndarray, brdf: Brdf, normal: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Radiance (P, 3) of a principled sphere under SH lighting (a sphere casts no shadows), shaded
    as the renderer shades (pipeline.core.shading.sphere_radiance)."""
    return sphere_radiance(material_from_brdf(brdf), coeffs, normal, view, brdf.base_color)


def sphere_renders(coeffs: np.ndarray, brdf: Brdf | None, size: int = 128) -> bytes:
    """PNG: orthographic spheres seen from +Y under SH lighting ``coeffs`` (one panel each):
    a mirror sphere (the lighting itself), a white Lambertian sphere, and the fitted BRDF."""
    from pipeline.core.sh import sh_evaluate
    from pipeline.core.transfer import irradiance_from_sh
    from pipeline.io.images import srgb_encode

    # orthographic view along -Y (camera on +Y looking at the origin): image x -> world x, image up -> +Z
    u = (np.arange(size) + 0.5) / size * 2 - 1
    x, z = np.meshgrid(u, -u)
    inside = x * x + z * z < 1
    y = np.sqrt(np.clip(1 - x * x - z * z, 0, 1))
    normal = np.stack([x, y, z], axis=-1)[inside]
    view = np.broadcast_to([0.0, 1.0, 0.0], normal.shape)
    r = 2 * np.sum(normal * view, axis=1, keepdims=True) * normal - view
    panels = {
        "mirror sphere (lighting)": sh_evaluate(coeffs, r),
        "white Lambertian sphere": irradiance_from_sh(coeffs, normal) / np.pi,
    }
    if brdf is not None and brdf.model == "principled":
        panels["fitted material"] = principled_sphere(coeffs, brdf, normal, np.array(view))
    elif brdf is not None:
        from pipeline.core.prefilter import Lighting

        lighting = Lighting(brdf, coeffs=coeffs)  # the same forward model as relight
        panels["fitted BRDF"] = lighting.radiance(normal, np.array(view), np.asarray(brdf.albedo, float))
    plt = _figure()
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.1))
    for ax, (title, values) in zip(np.atleast_1d(axes), panels.items()):
        img = np.zeros((size, size, 3))
        img[inside] = values
        top = np.percentile(img[inside].max(axis=1), 99)
        ax.imshow(srgb_encode(img * (0.9 / top if top > 0 else 1.0)))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    return _fig_png(fig)


def texture_views(vertices: np.ndarray, faces: np.ndarray, colour: np.ndarray, size: float = 3.0) -> bytes:
    """PNG: a mesh's per-vertex linear colour (V, 3), unlit, seen orthographically from the four
    sides and from above (+Z up): each face in its vertices' mean colour, sRGB-encoded, nearer faces
    drawn over farther ones."""
    from matplotlib.collections import PolyCollection

    from pipeline.io.images import srgb_encode

    sides = {"from +X": (1, 2, 0), "from +Y": (0, 2, 1), "from −X": (1, 2, 0), "from −Y": (0, 2, 1), "from above": (0, 1, 2)}
    # (image x, image y, towards the viewer) signs: from +X the image's right is +Y, from +Y it is -X
    signs = {"from +X": (1, 1, 1), "from +Y": (-1, 1, 1), "from −X": (-1, 1, -1), "from −Y": (1, 1, -1), "from above": (1, 1, 1)}
    tri = np.asarray(vertices, float)[np.asarray(faces)]  # (F, 3 corners, 3)
    face_rgb = np.clip(srgb_encode(np.asarray(colour, float)[np.asarray(faces)].mean(axis=1)), 0, 1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    plt = _figure()
    fig, axes = plt.subplots(1, len(sides), figsize=(size * len(sides), size))
    for ax, (title, (a, b, depth)) in zip(axes, sides.items()):
        sa, sb, sd = signs[title]
        facing = normal[:, depth] * sd > 0
        order = np.argsort(sd * tri[facing][:, :, depth].mean(axis=1))  # far first
        xy = np.stack([sa * tri[facing][order][:, :, a], sb * tri[facing][order][:, :, b]], axis=-1)
        ax.add_collection(PolyCollection(xy, facecolors=face_rgb[facing][order], edgecolors="none"))
        ax.autoscale_view()
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    return _fig_png(fig)


def _lighting(work: Path) -> str:
    from pipeline.io.brdf import read_brdf
    from pipeline.io.images import read_image
    from pipeline.io.lighting import read_lighting_sh

    fit = Path(work) / "fit"
    sh_file = fit / "lighting_sh.json"
    if not sh_file.exists():
        return _section("Fitted lighting", _missing("no fitted lighting yet (the fit stage has not run)"))
    parts = []
    if (fit / "lighting.exr").exists():
        env = read_image(fit / "lighting.exr")
        parts.append(
            "<h3>Equirect map (DESIGN.md convention, row 0 = zenith)</h3>"
            + _img_tag(_array_png(_tonemap(env)), "fitted lighting", 512)
        )
    coeffs = read_lighting_sh(sh_file)
    brdf = read_brdf(fit / "brdf.json") if (fit / "brdf.json").exists() else None
    parts.append("<h3>Spheres under the fitted lighting</h3>" + _img_tag(sphere_renders(coeffs, brdf), "spheres"))
    report = _json(fit / "report.json") or {}
    if report.get("bands"):
        parts.append(
            "<h3>What the data determine, band by band</h3>"
            + _img_tag(spectrum_plot(report["bands"]), "spectrum")
            + _table(
                [[b.get("l"), b.get("label"), b.get("snr"), b.get("snr_data"), b.get("energy")] for b in report["bands"]],
                ["band l", "label", "snr (vs residual)", "snr (vs photo noise)", "energy"],
            )
        )
    if report.get("residuals_per_view"):
        parts.append("<h3>Fit residual per view</h3>" + _img_tag(residual_plot(report["residuals_per_view"]), "residuals"))
    return _section("Fitted lighting", "\n".join(parts))


LABEL_COLOURS = {"recoverable": "tab:green", "ill-conditioned": "tab:orange", "ill-posed": "tab:red"}


def spectrum_plot(bands: list[dict]) -> bytes:
    """PNG: the fitted lighting's energy per SH band (log scale), coloured by what the data determine;
    integer band ticks, the legend beside the axes."""
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    plt = _figure()
    fig, ax = plt.subplots(figsize=(7, 3.6))
    energy = [float(b.get("energy") or 0.0) for b in bands]
    positive = [e for e in energy if e > 0]
    floor = min(positive) / 100 if positive else 1e-6
    # ill-posed bands are zero: drawn as a short stub at the bottom of the log axis
    ax.bar(
        [b["l"] for b in bands],
        [max(e, floor * 3) for e in energy],
        bottom=floor,
        color=[LABEL_COLOURS.get(b.get("label"), "tab:gray") for b in bands],
    )
    ax.set_yscale("log")
    ax.set_ylim(bottom=floor)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("SH band l")
    ax.set_ylabel("energy Σ_m L_lm² (RGB sum)")
    ax.legend(
        handles=[Patch(color=c, label=k + (" (zeroed)" if k == "ill-posed" else "")) for k, c in LABEL_COLOURS.items()],
        loc="upper left",
        bbox_to_anchor=(1.01, 1.0),
        fontsize=8,
        frameon=False,
    )
    ax.set_title("fitted lighting spectrum", fontsize=10)
    return _fig_png(fig)


def residual_plot(views: list[dict]) -> bytes:
    """PNG: the fit's relative RMS residual per fitted view, one bar per image (named), coloured by
    the cross-validation fold it was held out in when the fit chose its models, with a legend."""
    plt = _figure()
    names = [str(v.get("image", i)) for i, v in enumerate(views)]
    fig, ax = plt.subplots(figsize=(max(5.0, 0.45 * len(views) + 2.0), 3.6))
    folds = sorted({v.get("fold") for v in views}, key=lambda f: (f is None, f))
    cmap = plt.get_cmap("tab10")
    for k, fold in enumerate(folds):
        idx = [i for i, v in enumerate(views) if v.get("fold") == fold]
        ax.bar(
            idx,
            [100 * (views[i].get("relative_rmse") or 0.0) for i in idx],
            color=cmap(k % 10),
            label="no fold" if fold is None else f"fold {fold}",
        )
    ax.set_xticks(range(len(views)))
    ax.set_xticklabels(names, rotation=45 if len(views) > 4 else 0, ha="right" if len(views) > 4 else "center", fontsize=8)
    ax.set_xlabel("fitted view (image)")
    ax.set_ylabel("relative RMS residual (%)")
    ax.legend(title="held out in", loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
    ax.set_title("fit residual per view (views held out of the whole fit are not here)", fontsize=10)
    return _fig_png(fig)


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

        from pipeline.io.mesh import read_vertex_albedo

        tex = trimesh.load(fit / "albedo.ply", force="mesh", process=False)
        colour = read_vertex_albedo(fit / "albedo.ply", len(tex.vertices))
        if colour is not None:
            word = "albedo" if brdf.get("model") == "lambert" else "base colour"
            body += f"<h3>Textured {word} (fit/albedo.ply; the table holds its mean)</h3>" + _img_tag(
                texture_views(np.asarray(tex.vertices), np.asarray(tex.faces), colour), "texture"
            )
    if (fit / "textures" / "base_color.png").exists():
        body += _texels(fit / "textures", (report or {}).get("texels") or {})
    selection = (report or {}).get("model_selection") or {}
    if selection.get("by") == "training residual":
        body = f"<p><b>Not validated:</b> {html.escape(selection['why'])} (kept: {html.escape(selection['kept'])}).</p>" + body
    if report:
        body += fit_tables(report)
    return _section("BRDF", body)


def _texels(folder: Path, entry: dict) -> str:
    """fit/textures/: the base colour map and its relative uncertainty, and the levels the held-out
    views chose (report.json "texels")."""
    from pipeline.io.images import read_image

    base = read_image(folder / "base_color.png")[:, :, :3]
    std = read_image(folder / "base_color_std.exr")[:, :, :3].astype(float)
    linear = read_image(folder / "base_color.exr")[:, :, :3].astype(float)
    seen = np.isfinite(std).all(axis=2)
    relative = np.full(seen.shape, np.nan)
    relative[seen] = std[seen].mean(axis=1) / np.maximum(linear[seen].mean(axis=1), 1e-3)
    plt = _figure()
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
        ["texel size (mm)", _fmt(entry.get("atlas", {}).get("texel_mm"))],
        ["texels with samples / in charts", f"{entry.get('texels_with_samples', '?')} / {entry.get('texels_in_charts', '?')}"],
        ["samples", _fmt(entry.get("samples"))],
    ]
    cands = [
        [c["name"], _fmt(c["validation_rmse"]), _fmt(c["train_rmse"])]
        for c in entry.get("vertex_level", {}).get("candidates", []) + entry.get("texel_level", {}).get("candidates", [])
    ]
    return (
        "<h3>Base colour per texel (fit/textures/; grey texels saw no sample: their colour is the "
        "per-vertex level's)</h3>"
        + _img_tag(_fig_png(fig), "base colour map and uncertainty")
        + _table(rows)
        + (_table(cands, ["level", "held-out RMSE", "training RMSE"]) if cands else "")
    )


def brdf_table(brdf: dict, truth: dict | None) -> str:
    """The fitted material's parameters (3 significant digits); with the capture's truth (gt/brdf.json,
    synthetic captures) a truth column and each parameter's error (fit − truth, and relative)."""
    materials = brdf.get("materials")
    shown = {k: v for k, v in brdf.items() if k != "materials"}
    if truth is None or truth.get("model") != brdf.get("model"):
        note = (
            ""
            if truth is None
            else (
                f"<p>The capture's truth (gt/brdf.json) is a {html.escape(str(truth.get('model')))} "
                "material: not compared parameter by parameter.</p>"
            )
        )
        out = note + _table([[k, v] for k, v in shown.items()], ["parameter", "fitted"])
    else:
        rows = []
        for k, v in shown.items():
            t = truth.get(k)
            err = rel = None
            if t is not None and isinstance(v, (int, float, list)) and not isinstance(v, bool):
                fv, tv = np.atleast_1d(np.asarray(v, float)), np.atleast_1d(np.asarray(t, float))
                if fv.shape == tv.shape:
                    err = (fv - tv).tolist()
                    rel = [f"{100 * (a - b) / abs(b):+.3g}%" if b != 0 else "—" for a, b in zip(fv, tv)]
                    err, rel = (err[0], rel[0]) if fv.size == 1 else (err, ", ".join(rel))
            rows.append([k, v, t, err, rel])
        out = "<p>Against the capture's truth (gt/brdf.json).</p>" + _table(
            rows, ["parameter", "fitted", "truth", "error (fit − truth)", "relative error"]
        )
    if materials:
        keys = sorted({k for m in materials for k in m if k != "model"})
        out += "<h3>Materials (fit/material.ply's material_id)</h3>" + _table(
            [[i, m.get("model")] + [m.get(k) for k in keys] for i, m in enumerate(materials)], ["id", "model", *keys]
        )
    return out


def fit_tables(report: dict) -> str:
    """fit/report.json as tables: the choices, the candidates compared, and the rest of its entries."""
    parts = []
    chosen = [[k, report[k]] for k in ("mode", "forward_model", "order", "brdf_model") if k in report]
    selection = report.get("model_selection")
    if isinstance(selection, dict):
        chosen += [[f"model selection: {k}", v] for k, v in selection.items() if not isinstance(v, (dict, list))]
    parts.append("<h3>What the fit chose</h3>" + _table(chosen, ["", "value"]))
    cands = report.get("candidates") or []
    if cands and isinstance(cands, list) and isinstance(cands[0], dict):
        cols = [c for c in ("name", "params", "train_rmse", "validation_rmse", "seconds") if any(c in r for r in cands)]
        parts.append(
            "<h3>Candidates compared (lowest validation RMSE wins, within the parsimony rule)</h3>"
            + _table([[r.get(c) for c in cols] for r in cands], [c.replace("_", " ") for c in cols])
        )
    shown = {
        "mode",
        "forward_model",
        "order",
        "brdf_model",
        "model_selection",
        "candidates",
        "bands",
        "labels",
        "residuals_per_view",
        "brdf",
        "schema",
    }
    rest = {k: v for k, v in report.items() if k not in shown}
    if rest:
        parts.append(
            "<details><summary>Everything else in fit/report.json</summary>"
            + _table(_flat(rest), ["entry", "value"])
            + "</details>"
        )
    return "".join(parts)


def _relight(work: Path) -> str:
    from pipeline.io.run_summary import method_description, noise_phrase, relight_check

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
        f"<details><summary>{html.escape(p.name)}</summary>{_table(_flat(_json(p) or {}), ['entry', 'value'])}</details>"
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


def write_report(capture: Path, work: Path) -> Path:
    """Write WORK/report.html atomically and return its path."""
    return write_text(Path(work) / "report.html", build_report(capture, work))
