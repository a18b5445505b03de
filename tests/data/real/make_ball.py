"""Convert DiLiGenT's "ball" (as shipped by github t-taniai/neuralps, data/DiLiGenT/pmsData/ballPNG) into a
one-view sigrend capture with a known directional light per photo.  See README.md beside this file.

    python tests/data/real/make_ball.py --mirror /work/.mirror/t-taniai+neuralps/repo --out tests/data/real/ball_diligent

Needs numpy, scipy (loadmat), opencv and trimesh (sigrend's own dependencies).
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
from pathlib import Path

import numpy as np

SRC = "data/DiLiGenT/pmsData/ballPNG"
WIDTH, HEIGHT = 612, 512  # DiLiGenT's images (2448 x 2048 sensor binned/downsampled by 4)
FOCAL_PX = 3772.0  # assumed (see README): not shipped with this copy, not recoverable from it
CROP = 160  # square crop around the ball (its mask is 142 px across)
RADIUS_M = 0.03  # nominal sphere radius: one view does not fix the scale
LIGHT_TILT_DEG = 25.0  # the four side lights are those nearest 25 degrees off the frontal one
SUBDIVISIONS = 5  # icosphere: 20480 faces


def git_show(mirror: Path, path: str) -> bytes:
    return subprocess.run(["git", f"--git-dir={mirror}", "show", f"HEAD:{path}"], check=True, capture_output=True).stdout


def decode(data: bytes, flags: int):
    import cv2

    return cv2.imdecode(np.frombuffer(data, np.uint8), flags)


def silhouette_cone(mask: np.ndarray, fx: float, cx: float, cy: float) -> tuple[np.ndarray, float]:
    """Axis (unit, OpenCV camera coordinates) and half-angle of the cone of rays tangent to a sphere, fitted
    to the mask's boundary: the points halfway between a mask pixel and a 4-neighbour outside it (COLMAP
    pixel coordinates, pixel centres at +0.5).  A sphere's silhouette cone has c . d = cos(alpha) for every
    boundary ray d: least squares of D c' = 1 gives c = c'/|c'|, cos(alpha) = 1/|c'|."""
    pts = []
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        shifted = np.zeros_like(mask)
        r0, r1 = max(dr, 0), mask.shape[0] + min(dr, 0)
        c0, c1 = max(dc, 0), mask.shape[1] + min(dc, 0)
        shifted[r0 - dr : r1 - dr, c0 - dc : c1 - dc] = mask[r0:r1, c0:c1]  # shifted[r, c] = mask[r + dr, c + dc]
        rr, cc = np.nonzero(mask & ~shifted)
        pts.append(np.stack([cc + 0.5 + 0.5 * dc, rr + 0.5 + 0.5 * dr], axis=1))
    uv = np.concatenate(pts)
    d = np.stack([(uv[:, 0] - cx) / fx, (uv[:, 1] - cy) / fx, np.ones(len(uv))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    c, *_ = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)
    return c / np.linalg.norm(c), float(np.arccos(1.0 / np.linalg.norm(c))), len(uv)


# DiLiGenT's frame (normals, light directions): x right, y up, z towards the camera.  Object frame
# (DESIGN.md, +Z up): X = x, Z = y (up in the photo), Y = Z x X = -z (away from the camera).
D_TO_OBJECT = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
# object -> OpenCV camera (+X right, +Y down, +Z forward): x_cam = (x, -y, -z)_D = (X, -Z, Y)
OBJECT_TO_CAMERA = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def choose_lights(directions: np.ndarray) -> list[int]:
    """0-based indices: the most frontal light, then the lights nearest LIGHT_TILT_DEG off it towards
    +x, -x, +y and -y (DiLiGenT frame)."""
    front = int(np.argmax(directions[:, 2]))
    t = np.radians(LIGHT_TILT_DEG)
    picks = [front]
    for axis in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]):
        want = np.cos(t) * np.array([0.0, 0.0, 1.0]) + np.sin(t) * np.asarray(axis, float)
        order = np.argsort(-directions @ want)
        picks.append(int(next(i for i in order if i not in picks)))
    return picks


def main() -> None:
    import cv2
    import scipy.io
    import trimesh

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mirror", type=Path, required=True, help="bare git dir of t-taniai/neuralps")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    out = args.out
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "gt").mkdir(exist_ok=True)
    commit = subprocess.run(
        ["git", f"--git-dir={args.mirror}", "rev-parse", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.strip()

    mask = decode(git_show(args.mirror, f"{SRC}/mask.png"), cv2.IMREAD_GRAYSCALE) > 0
    normals = scipy.io.loadmat(io.BytesIO(git_show(args.mirror, f"{SRC}/Normal_gt.mat")))["Normal_gt"].astype(float)
    directions = np.loadtxt(io.BytesIO(git_show(args.mirror, f"{SRC}/light_directions.txt")))
    intensities = np.loadtxt(io.BytesIO(git_show(args.mirror, f"{SRC}/light_intensities.txt")))  # R G B
    names = git_show(args.mirror, f"{SRC}/filenames.txt").decode().split()
    assert mask.shape == (HEIGHT, WIDTH) and len(directions) == len(intensities) == len(names) == 96

    # the crop: CROP x CROP around the mask's bounding-box centre
    rows, cols = np.nonzero(mask)
    r0 = int(round((rows.min() + rows.max() + 1) / 2 - CROP / 2))
    c0 = int(round((cols.min() + cols.max() + 1) / 2 - CROP / 2))
    window = (slice(r0, r0 + CROP), slice(c0, c0 + CROP))

    # camera: principal point at the full image's centre (COLMAP: W/2, H/2), moved by the crop
    fx = FOCAL_PX
    cx, cy = WIDTH / 2.0 - c0, HEIGHT / 2.0 - r0
    axis, alpha, n_edge = silhouette_cone(mask[window], fx, cx, cy)
    distance = RADIUS_M / np.sin(alpha)
    centre_cam = distance * axis
    poses = {
        "frame": "object",
        "units": "meters",
        "cameras": {"cam0": {"model": "PINHOLE", "width": CROP, "height": CROP, "params": [fx, fx, cx, cy]}},
        "images": {},
    }

    lights = choose_lights(directions)
    toml = [
        "# DiLiGenT ball: one camera, one calibrated directional light per photo (make_ball.py, README.md)",
        "# direction: unit vector towards the light in the object frame; intensity: DiLiGenT's light_intensities",
        "# (R, G, B; relative units, as the dataset gives them)",
        "",
        "[lighting]",
    ]
    chosen = []
    for i in lights:
        src = names[i]
        img = decode(git_show(args.mirror, f"{SRC}/{src}"), cv2.IMREAD_UNCHANGED)  # BGR, uint16
        assert img.dtype == np.uint16 and img.shape == (HEIGHT, WIDTH, 3)
        key = f"light{i + 1:03d}.png"
        cv2.imwrite(str(out / "images" / key), img[window])  # BGR stays BGR
        poses["images"][key] = {"camera": "cam0", "R": OBJECT_TO_CAMERA.tolist(), "t": centre_cam.tolist()}
        d_obj = D_TO_OBJECT @ directions[i]
        d_obj /= np.linalg.norm(d_obj)
        toml.append(
            f'"{key}" = {{direction = [{d_obj[0]:.6f}, {d_obj[1]:.6f}, {d_obj[2]:.6f}], '
            f"intensity = [{intensities[i, 0]:.4f}, {intensities[i, 1]:.4f}, {intensities[i, 2]:.4f}]}}"
        )
        chosen.append(
            {
                "image": key,
                "source": src,
                "index0": i,
                "direction_diligent": directions[i].tolist(),
                "direction_object": d_obj.tolist(),
                "intensity_rgb": intensities[i].tolist(),
                "saturated_pixels": int((img[window] >= 65535).any(axis=2).sum()),
            }
        )
    (out / "capture.toml").write_text("\n".join(toml) + "\n")
    (out / "poses.json").write_text(json.dumps(poses, indent=1) + "\n")

    sphere = trimesh.creation.icosphere(subdivisions=SUBDIVISIONS, radius=RADIUS_M)
    sphere.export(out / "mesh.ply")
    cv2.imwrite(str(out / "gt" / "mask.png"), (mask[window] * 255).astype(np.uint8))
    np.savez_compressed(out / "gt" / "normal_gt.npz", normal=normals[window].astype(np.float32))

    # sanity: the orthographic sphere the ground truth is (fit n_x, n_y to pixel offsets)
    rr, cc = np.nonzero(mask)
    n = normals[rr, cc]
    a = np.stack([np.ones(len(rr)), cc + 0.5], axis=1)
    sx = np.linalg.lstsq(a, n[:, 0], rcond=None)[0]
    b = np.stack([np.ones(len(rr)), rr + 0.5], axis=1)
    sy = np.linalg.lstsq(b, n[:, 1], rcond=None)[0]
    ortho = {
        "centre_px_colmap": [-sx[0] / sx[1], -sy[0] / sy[1]],
        "radius_px": [1 / sx[1], -1 / sy[1]],
        "rms_nx": float(np.sqrt(np.mean((a @ sx - n[:, 0]) ** 2))),
        "rms_ny": float(np.sqrt(np.mean((b @ sy - n[:, 1]) ** 2))),
    }
    check = {
        "source": {"repo": "t-taniai/neuralps", "commit": commit, "path": SRC},
        "crop": {"row0": r0, "col0": c0, "size": CROP},
        "camera": {"focal_px": fx, "cx": cx, "cy": cy, "focal_assumed": True},
        "sphere": {
            "axis_cam": axis.tolist(),
            "half_angle_deg": float(np.degrees(alpha)),
            "edge_points": n_edge,
            "radius_m": RADIUS_M,
            "distance_m": float(distance),
            "radius_px_equivalent": float(fx * np.tan(alpha)),
            "centre_px_colmap_full": [float(fx * axis[0] / axis[2] + cx + c0), float(fx * axis[1] / axis[2] + cy + r0)],
        },
        "ground_truth_normals_as_orthographic_sphere": ortho,
        "mask_pixels": int(mask.sum()),
        "lights": chosen,
    }
    (out / "conversion.json").write_text(json.dumps(check, indent=1) + "\n")
    print(json.dumps(check, indent=1))


if __name__ == "__main__":
    main()
