"""report.html's figures and images, each as PNG bytes (matplotlib's Agg backend, no window): the
cameras around the mesh's bounding box, spheres under the fitted SH lighting, a mesh's per-vertex
colour from five sides, the lighting's per-band spectrum and the fit's residual per view.

Inputs are linear radiance or colour arrays (tone-mapped here for display: pipeline.io.images'
preview exposure and sRGB encoding), poses in the DESIGN.md convention (object frame, metres,
+Z up) and fit/report.json's entries; the outputs are PNG bytes for pipeline.report's page.
"""

from __future__ import annotations

import io

import numpy as np

from pipeline.core.brdf import Brdf
from pipeline.core.material import material_from_brdf
from pipeline.core.prefilter import Lighting
from pipeline.core.sh import sh_evaluate
from pipeline.core.shading import sphere_radiance
from pipeline.core.transfer import irradiance_from_sh
from pipeline.io.images import preview_exposure, srgb_encode


def pyplot():
    """matplotlib.pyplot on the Agg backend (PNG output, no window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_png(fig) -> bytes:
    """PNG bytes of a matplotlib figure (100 dpi, tight), the figure closed."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    pyplot().close(fig)
    return buf.getvalue()


def array_png(rgb: np.ndarray) -> bytes:
    """8-bit PNG bytes of an sRGB-encoded [0, 1] (H, W, 3) array (matplotlib's writer, no figure)."""
    plt = pyplot()
    buf = io.BytesIO()
    plt.imsave(buf, np.clip(rgb, 0, 1), format="png")
    return buf.getvalue()


def tonemap(linear: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """sRGB-encoded display image of linear RGB (H, W, 3+), exposed for its ``mask``ed pixels (all by default)."""

    rgb = np.asarray(linear, float)[..., :3]
    m = mask if mask is not None else np.ones(rgb.shape[:2], bool)
    return srgb_encode(rgb * preview_exposure(rgb, m))


MASK_TINT = np.array([1.0, 0.1, 0.1])


def masked_overlay(rgb: np.ndarray, valid: np.ndarray, strength: float = 0.6) -> np.ndarray:
    """The display image ``rgb`` (H, W, 3) with the pixels not ``valid`` (H, W) blended towards MASK_TINT."""
    out = np.array(rgb, float)
    out[~valid] = (1 - strength) * out[~valid] + strength * MASK_TINT
    return out


def camera_plot(poses, bounds: np.ndarray | None, heldout: list[str]) -> bytes:
    """PNG: camera centres (held-out ones in orange) with viewing directions, and the mesh's bounding box."""

    plt = pyplot()
    fig = plt.figure(figsize=(5.5, 5))
    ax = fig.add_subplot(projection="3d")
    centres = np.array([p.cam_from_world.center() for p in poses.images.values()])
    axes = np.array([p.cam_from_world.rotation[2] for p in poses.images.values()])  # +Z_cam in world = viewing direction
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
    return figure_png(fig)


def principled_sphere(coeffs: np.ndarray, brdf: Brdf, normal: np.ndarray, view: np.ndarray) -> np.ndarray:
    """Radiance (P, 3) of a principled sphere under SH lighting (a sphere casts no shadows), shaded
    as the renderer shades (pipeline.core.shading.sphere_radiance)."""
    return sphere_radiance(material_from_brdf(brdf), coeffs, normal, view, brdf.base_color)


def sphere_renders(coeffs: np.ndarray, brdf: Brdf | None, size: int = 128) -> bytes:
    """PNG: orthographic spheres seen from +Y under SH lighting ``coeffs`` (one panel each):
    a mirror sphere (the lighting itself), a white Lambertian sphere, and the fitted BRDF."""

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
        lighting = Lighting(brdf, coeffs=coeffs)  # the same forward model as relight
        panels["fitted BRDF"] = lighting.radiance(normal, np.array(view), np.asarray(brdf.albedo, float))
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(3 * len(panels), 3.1))
    for ax, (title, values) in zip(np.atleast_1d(axes), panels.items()):
        img = np.zeros((size, size, 3))
        img[inside] = values
        top = np.percentile(img[inside].max(axis=1), 99)
        ax.imshow(srgb_encode(img * (0.9 / top if top > 0 else 1.0)))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    return figure_png(fig)


def texture_views(vertices: np.ndarray, faces: np.ndarray, colour: np.ndarray, size: float = 3.0) -> bytes:
    """PNG: a mesh's per-vertex linear colour (V, 3), unlit, seen orthographically from the four
    sides and from above (+Z up): each face in its vertices' mean colour, sRGB-encoded, nearer faces
    drawn over farther ones."""
    from matplotlib.collections import PolyCollection

    sides = {"from +X": (1, 2, 0), "from +Y": (0, 2, 1), "from −X": (1, 2, 0), "from −Y": (0, 2, 1), "from above": (0, 1, 2)}
    # (image x, image y, towards the viewer) signs: from +X the image's right is +Y, from +Y it is -X
    signs = {"from +X": (1, 1, 1), "from +Y": (-1, 1, 1), "from −X": (-1, 1, -1), "from −Y": (1, 1, -1), "from above": (1, 1, 1)}
    tri = np.asarray(vertices, float)[np.asarray(faces)]  # (F, 3 corners, 3)
    face_rgb = np.clip(srgb_encode(np.asarray(colour, float)[np.asarray(faces)].mean(axis=1)), 0, 1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    plt = pyplot()
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
    return figure_png(fig)


LABEL_COLOURS = {"recoverable": "tab:green", "ill-conditioned": "tab:orange", "ill-posed": "tab:red"}


def spectrum_plot(bands: list[dict]) -> bytes:
    """PNG: the fitted lighting's energy per SH band (log scale), coloured by what the data determine;
    integer band ticks, the legend beside the axes."""
    from matplotlib.patches import Patch
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
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
    return figure_png(fig)


def residual_plot(views: list[dict]) -> bytes:
    """PNG: the fit's relative RMS residual per fitted view, one bar per image (named), coloured by
    the cross-validation fold it was held out in when the fit chose its models, with a legend."""
    plt = pyplot()
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
    return figure_png(fig)
