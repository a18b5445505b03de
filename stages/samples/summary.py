"""samples' summary: the tally of drops, coverage and visibility over all views (samples_summary.json),
why no camera sees the mesh's outside, and samples_coverage.png."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.brdf import reflect
from pipeline.core.camera import project
from pipeline.core.coverage import EqualAreaGrid, coverage_stats
from pipeline.io.poses import Poses
from pipeline.io.samples import SamplesWriter
from pipeline.workdir import atomic_path
from stages.samples.settings import DROP_REASONS, Settings


@dataclass
class Tally:
    """What the samples stage counts over all views: drop reasons, the coverage histograms of normals
    and mirror directions, the visibility statistics, whether any camera sees the mesh's outside,
    and each image's entry for samples_summary.json."""

    min_visibility: float
    grid: EqualAreaGrid = field(default_factory=EqualAreaGrid)
    drops: dict = field(default_factory=lambda: dict.fromkeys(DROP_REASONS, 0))
    images: dict = field(default_factory=dict)
    visibility_low: int = 0
    visibility_sum: float = 0.0
    sees_outside: bool = False

    def __post_init__(self) -> None:
        self.normal_hist = np.zeros(self.grid.shape)
        self.reflect_hist = np.zeros(self.grid.shape)

    def record(self, writer: SamplesWriter, arrays: dict) -> int:
        """Append a chunk of samples and count it; returns its row count."""
        writer.append(arrays)
        self.normal_hist += self.grid.histogram(arrays["normal"])
        self.reflect_hist += self.grid.histogram(reflect(arrays["view_dir"], arrays["normal"]))
        self.visibility_low += int((arrays["visibility"] < self.min_visibility).sum())
        self.visibility_sum += float(arrays["visibility"].sum())
        return len(arrays["image_id"])

    def add_view(self, key: str, drops: dict, kept: int, exposure_scale: float) -> None:
        """A view's drops and kept count (sample_view) into the totals and its samples_summary.json entry."""
        considered = kept + sum(drops.values())
        # pixels that reached the hidden test and passed it: the camera sees the mesh's outside
        self.sees_outside |= considered - drops["background"] - drops["silhouette_edge"] - drops["hidden"] > 0
        for reason, count in drops.items():
            self.drops[reason] += count
        self.images[key] = {"pixels": considered, "kept": kept, "drops": drops, "exposure_scale": exposure_scale}

    def summary(self, count: int, settings: Settings) -> dict:
        return {
            "count": count,
            "pixels": sum(v["pixels"] for v in self.images.values()),
            "drops": self.drops,
            "coverage": {
                "grid": {"type": "equal-area z-phi", "n_bands": self.grid.n_bands, "n_azimuth": self.grid.n_azimuth},
                "normals": coverage_stats(self.normal_hist),
                "reflections": coverage_stats(self.reflect_hist),
            },
            "visibility": {
                "convention": "cosine-weighted unblocked fraction of the hemisphere about the normal",
                "rays_per_vertex": settings.visibility_rays,
                "mean": self.visibility_sum / count,
                "min_visibility": settings.min_visibility,
                "below_min_visibility": self.visibility_low,
            },
        }


def units_hint(mesh, poses: Poses, totals: dict) -> str:
    """Why no camera sees the mesh's outside: units (size vs camera distance), frame (not in view)
    or back faces only (cameras inside the mesh, or faces wound inwards)."""
    size = float(np.linalg.norm(mesh.extents))
    centre = np.asarray(mesh.bounds, float).mean(axis=0)
    centres = np.array([p.cam_from_world.center() for p in poses.images.values()])
    # the scale of the camera rig from the cameras alone (their spread about their centroid): measured
    # from the mesh's centre instead, a mesh 1000x too large puts the cameras inside it at ~its radius
    distance = float(np.median(np.linalg.norm(centres - centres.mean(axis=0), axis=1)))
    if not distance > 0:  # one camera (or all at one point): its distance to the mesh
        distance = float(np.median(np.linalg.norm(centres - centre, axis=1)))
    ratio = size / max(distance, 1e-300)
    sizes = f"(bounding box {size:.3g} across, cameras {distance:.3g} from their centre)"
    if ratio > 20:  # an object is normally about as large as (or smaller than) its distance to the camera
        unit = "millimetres" if ratio >= 100 else "centimetres"
        return f"the mesh is {ratio:.0f}x larger than the camera distances {sizes}: is it in {unit}? convert it to metres"
    if ratio < 1e-3:
        return (
            f"the mesh is {1 / ratio:.0f}x smaller than the camera distances {sizes}: "
            "is it in kilometres, or are the poses scaled?"
        )
    in_view = 0
    for key, pose in poses.images.items():
        cam = poses.camera_of(key)
        uv, z = project(cam, pose.cam_from_world.rotation, pose.cam_from_world.translation, centre[None])
        in_view += bool(z[0] > 0 and 0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height)
    if in_view == 0 or totals["hidden"] == 0:
        return (
            f"the mesh centre is in view of {in_view} of {len(poses.images)} cameras: the mesh and poses.json "
            "are probably in different frames (poses must be in the mesh's object frame, DESIGN.md)"
        )
    return (
        "every hit is on a back face: the cameras are inside the mesh or its faces are wound inwards "
        "(normals pointing in); check the poses or fix the winding (e.g. trimesh.repair.fix_normals)"
    )


def plot_coverage(path: Path, grid: EqualAreaGrid, normal_hist: np.ndarray, reflect_hist: np.ndarray, coverage: dict) -> Path:
    """PNG: equirect (θ down, φ across) histograms of sample normals and reflection directions."""
    import matplotlib  # imported when the plot is drawn: matplotlib's start-up is ~0.5 s

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    theta = np.degrees(grid.band_edges_theta())
    phi = np.degrees(grid.azimuth_edges())
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.4), constrained_layout=True)
    for ax, hist, name in ((axes[0], normal_hist, "normals"), (axes[1], reflect_hist, "reflections")):
        shown = np.where(hist > 0, hist, np.nan)
        mesh = ax.pcolormesh(phi, theta, np.log10(shown), cmap="viridis", shading="flat")
        ax.set_ylim(180, 0)
        ax.set_xlim(0, 360)
        ax.set_xlabel("azimuth φ (deg, from +X towards +Y)")
        ax.set_ylabel("polar angle θ (deg, from +Z)")
        ax.set_title(
            f"{name}: {100 * coverage[name]['fraction']:.1f}% of the sphere "
            f"({coverage[name]['cells_hit']}/{coverage[name]['cells']} equal-area cells)"
        )
        fig.colorbar(mesh, ax=ax, label="log10 samples per cell")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    plt.close(fig)
    return Path(path)
