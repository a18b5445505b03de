"""Convert one capture of the Robovision multi-view stereo benchmark data into a sigrend capture folder.

Source: github drewm1980/multi_view_stereo_benchmark_data (12 calibrated cameras in a ring, images
already undistorted, HALCON 12 calibration, PMVS reference point clouds), read from a bare git
mirror with ``git show``.  See README.md beside this file for what every step does and why.

    python tests/data/real/make_ring.py --mirror /work/.mirror/drewm1980+multi_view_stereo_benchmark_data/repo \
        --capture 2016_10_25__12_12_50 --out tests/data/real/ring_sweet

Needs pymeshlab (screened Poisson + quadric decimation; used only here, not by the tests:
``pip install --target /tmp/pml pymeshlab`` and ``PYTHONPATH=/tmp/pml``), OpenImageIO, trimesh
(sigrend's own dependencies) and numpy.
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
from pathlib import Path

import numpy as np

HELD_BACK = "2016_10_24__17_43_17"  # the walnut kept for evaluation: never converted
CAMERAS = 12
FACTOR = 4  # 1280x1024 -> 320x256
SATURATED_CODE = 250  # 8-bit codes >= this count as clipped (sigrend's default 0.98 x 255)
MAX_FACES = 20000
POISSON_DEPTH = 8
REFERENCE_POINTS = 4000  # subsample of the PMVS cloud kept beside the mesh (with its colours)


def git_show(mirror: Path, path: str) -> bytes:
    return subprocess.run(["git", f"--git-dir={mirror}", "show", f"HEAD:{path}"], check=True, capture_output=True).stdout


def halcon_intrinsics(text: str) -> dict[str, float]:
    """HALCON 12 'ParGroup: Camera: Parameter' file -> {name: value} (Focus, Poly1..5 or Kappa, Sx, Sy, Cx, Cy, ...)."""
    values = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith(("#", '"', "ParGroup", "DOUBLE", "INT")) or ":" not in line:
            continue
        parts = line.split(":")
        if len(parts) >= 3 and ";" in parts[2]:
            values[parts[0]] = float(parts[2].split(";")[0])
    return values


def camera_to_world(text: str) -> tuple[np.ndarray, np.ndarray]:
    """extrinsics_cameraNN.txt: 12 numbers, a 3x4 [R | T] row-major, camera -> world (x_world = R x_cam + T),
    as the benchmark's load_camera_info.load_halcon_extrinsics_homogeneous documents."""
    h = np.array(text.split(), float).reshape(3, 4)
    return h[:, :3], h[:, 3]


def load_cloud(data: bytes):
    """The PMVS reference.ply (ASCII: x y z nx ny nz red green blue alpha per vertex, no faces) ->
    points (N, 3), normals (N, 3), grey colour (N,) (the mean of red, green, blue)."""
    text = data.decode("ascii")
    header, body = text.split("end_header\n", 1)
    props = [line.split()[-1] for line in header.splitlines() if line.startswith("property")]
    table = np.loadtxt(io.StringIO(body), ndmin=2)[:, : len(props) - (1 if "vertex_indices" in props else 0)]
    col = {name: table[:, k] for k, name in enumerate(props) if name != "vertex_indices"}
    points = np.stack([col["x"], col["y"], col["z"]], axis=1)
    normals = np.stack([col["nx"], col["ny"], col["nz"]], axis=1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals, (col["red"] + col["green"] + col["blue"]) / 3.0


def object_frame(centres: np.ndarray, cam_down: np.ndarray, points_world: np.ndarray, first_centre: np.ndarray):
    """Rotation Q (rows = object X, Y, Z in world coordinates) and origin o: x_obj = Q (x_world - o).

    +Z: the normal of the ring of camera centres, signed along the cameras' mean +Y axis (image down): the
    rig's cameras are mounted upside down (benchmark README), so image-down is up in the room — the
    photos show the platform the object stands on at the top of the frame.  Origin: the centre of the
    reference cloud's bounding box in that frame.  +X: towards camera 01, in the horizontal plane.
    """
    c0 = centres.mean(axis=0)
    normal = np.linalg.svd(centres - c0)[2][2]
    z = normal if normal @ cam_down.mean(axis=0) > 0 else -normal
    x = first_centre - c0
    x -= (x @ z) * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    q = np.stack([x, y, z])
    local = points_world @ q.T
    o_local = 0.5 * (local.min(axis=0) + local.max(axis=0))
    return q, q.T @ o_local


def poisson_mesh(points: np.ndarray, normals: np.ndarray):
    """Screened Poisson surface of the oriented PMVS points (object frame), flattened to the cloud's
    height range and decimated to <= MAX_FACES faces; watertight, outward normals.

    The cloud has no points where the object stands on the platform and few on its top (the cameras are
    4 degrees above it): there Poisson closes the surface with a bulge ~1 cm beyond the data.  Vertices
    above the highest / below the lowest reference point are moved onto those planes (a flat base and
    top; the topology, hence watertightness, is unchanged).  The Poisson domain is 1.5x the cloud's box
    (MeshLab's default 1.1 cuts the bulges open at the box's faces).
    """
    import pymeshlab
    import trimesh

    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=points, v_normals_matrix=normals))
    ms.generate_surface_reconstruction_screened_poisson(depth=POISSON_DEPTH, preclean=True, scale=1.5)
    m = ms.current_mesh()
    verts, faces = m.vertex_matrix().copy(), m.face_matrix().copy()
    verts[:, 2] = np.clip(verts[:, 2], points[:, 2].min(), points[:, 2].max())
    ms.clear()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=faces))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_decimation_quadric_edge_collapse(
        targetfacenum=MAX_FACES, preservenormal=True, planarquadric=True, preservetopology=True
    )
    m = ms.current_mesh()
    mesh = trimesh.Trimesh(m.vertex_matrix(), m.face_matrix(), process=True)
    parts = mesh.split(only_watertight=False)  # keep the largest piece (Poisson islands, if any)
    mesh = max(parts, key=lambda p: len(p.faces))
    trimesh.repair.fix_normals(mesh)
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def downscale(gray8: np.ndarray, alpha8: np.ndarray):
    """4x4 box average of the 8-bit codes as a 16-bit value (codes/255 * 65535), and an alpha that is
    opaque only where all 16 source pixels were valid (alpha 255) and unclipped (code < SATURATED_CODE)."""
    h, w = gray8.shape
    blocks = gray8.reshape(h // FACTOR, FACTOR, w // FACTOR, FACTOR).astype(float)
    mean = blocks.mean(axis=(1, 3))
    ok = ((alpha8 == 255) & (gray8 < SATURATED_CODE)).reshape(h // FACTOR, FACTOR, w // FACTOR, FACTOR).all(axis=(1, 3))
    value = np.round(mean / 255.0 * 65535.0).astype(np.uint16)
    return value, np.where(ok, 65535, 0).astype(np.uint16)


def write_png16(path: Path, gray: np.ndarray, alpha: np.ndarray) -> None:
    """Grey + alpha, 16 bit, through OpenImageIO (sigrend reads a grey channel as R = G = B)."""
    import OpenImageIO as oiio

    img = np.stack([gray, alpha], axis=2)
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 2, "uint16")
    spec.channelnames = ("Y", "A")
    spec.alpha_channel = 1
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(str(path), spec), oiio.geterror()
    assert out.write_image(np.ascontiguousarray(img)), out.geterror()
    out.close()


def reprojection_check(points_obj, normals_obj, colours, views, images):
    """Per view: NCC between the PMVS colours of the reference points that face the camera and the
    photo (bilinear) at their projections, with the calibrated pose and with the projection shifted
    by 1 px (downscaled) — a pose that lands on the object scores high, a shifted one lower."""
    import cv2

    out = {}
    for key, (cam, R, t) in views.items():
        fx, fy, cx, cy = cam["params"]
        pc = points_obj @ R.T + t
        u, v = fx * pc[:, 0] / pc[:, 2] + cx, fy * pc[:, 1] / pc[:, 2] + cy
        centre = -R.T @ t
        facing = np.einsum("ij,ij->i", normals_obj, centre - points_obj) > 0
        img = images[key]
        inside = (u > 1) & (v > 1) & (u < img.shape[1] - 1) & (v < img.shape[0] - 1)
        sel = facing & inside

        def ncc(du, dv=0.0):
            # COLMAP (u, v) -> OpenCV remap coordinates: subtract 0.5 (pixel centres at integers)
            s = cv2.remap(
                img.astype(np.float32),
                (u[sel] - 0.5 + du).astype(np.float32)[None],
                (v[sel] - 0.5 + dv).astype(np.float32)[None],
                cv2.INTER_LINEAR,
            )[0]
            a, b = s - s.mean(), colours[sel] - colours[sel].mean()
            return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

        # where the NCC peaks, on a 1/8 px grid within +-1 px (downscaled pixels)
        grid = np.arange(-8, 9) / 8.0
        scores = np.array([[ncc(du, dv) for du in grid] for dv in grid])
        iv, iu = np.unravel_index(np.argmax(scores), scores.shape)
        out[key] = {
            "points": int(sel.sum()),
            "in_image": float(inside.mean()),
            "ncc": round(ncc(0.0), 4),
            "ncc_shift_1px": round(ncc(1.0), 4),
            "ncc_shift_3px": round(ncc(3.0), 4),
            "ncc_peak_offset_px": [float(grid[iu]), float(grid[iv])],
            "ncc_peak": round(float(scores.max()), 4),
        }
    return out


def main() -> None:
    global FACTOR, MAX_FACES
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mirror", type=Path, required=True, help="bare git dir of multi_view_stereo_benchmark_data")
    ap.add_argument("--capture", required=True, help="capture id, e.g. 2016_10_25__12_12_50")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--factor", type=int, default=FACTOR, help=f"downscale factor of the 1280x1024 photos (default {FACTOR})")
    ap.add_argument("--max-faces", type=int, default=MAX_FACES, help=f"faces of the decimated mesh (default {MAX_FACES})")
    args = ap.parse_args()
    FACTOR, MAX_FACES = args.factor, args.max_faces
    if args.capture == HELD_BACK:
        raise SystemExit(f"{HELD_BACK} is held back for evaluation: never convert it")

    src = f"undistorted_images/{args.capture}"
    commit = subprocess.run(
        ["git", f"--git-dir={args.mirror}", "rev-parse", "HEAD"], check=True, capture_output=True, text=True
    ).stdout.strip()
    out = args.out
    (out / "images").mkdir(parents=True, exist_ok=True)

    # --- cameras: HALCON -> world-to-camera (HALCON world frame, metres)
    import OpenImageIO as oiio

    raw = {}
    for i in range(1, CAMERAS + 1):
        intr = halcon_intrinsics(git_show(args.mirror, f"{src}/intrinsics_camera{i:02d}.txt").decode())
        distortion = [intr.get(k, 0.0) for k in ("Poly1", "Poly2", "Poly3", "Poly4", "Poly5", "Kappa")]
        assert not any(distortion), f"camera {i}: distortion {distortion}; the images should be undistorted"
        assert (intr["ImageWidth"], intr["ImageHeight"]) == (1280, 1024)
        r_cw, t_cw = camera_to_world(git_show(args.mirror, f"{src}/extrinsics_camera{i:02d}.txt").decode())
        # the printed matrix has 6 decimals: re-orthonormalize (polar decomposition), error ~1e-6
        uu, _, vt = np.linalg.svd(r_cw)
        r_cw = uu @ vt
        raw[i] = (intr, r_cw.T, -r_cw.T @ t_cw)
    centres = np.array([-r.T @ t for _, r, t in raw.values()])
    cam_down = np.array([r[1] for _, r, _ in raw.values()])  # camera +Y in world = row 1 of R

    points, normals, colours = load_cloud(git_show(args.mirror, f"reference_reconstructions/{args.capture}/reference.ply"))
    q, origin = object_frame(centres, cam_down, points, centres[0])
    points_obj = (points - origin) @ q.T
    normals_obj = normals @ q.T

    cameras, images, views, photos = {}, {}, {}, {}
    for i, (intr, r, t) in raw.items():
        # HALCON: Cx, Cy in pixels with pixel centres at integer coordinates (the top-left pixel's centre is
        # (0, 0)); COLMAP puts it at (0.5, 0.5).  Focal length in pixels = Focus / Sx (Sx: pixel width, m).
        # Downscaling by FACTOR scales COLMAP coordinates exactly: u_small = u_full / FACTOR.
        fx, fy = intr["Focus"] / intr["Sx"] / FACTOR, intr["Focus"] / intr["Sy"] / FACTOR
        cx, cy = (intr["Cx"] + 0.5) / FACTOR, (intr["Cy"] + 0.5) / FACTOR
        name, key = f"cam{i:02d}", f"cam{i:02d}.png"
        cam = {"model": "PINHOLE", "width": 1280 // FACTOR, "height": 1024 // FACTOR, "params": [fx, fy, cx, cy]}
        # object -> camera: x_cam = R (Q^T x_obj + origin) + t
        R_obj = r @ q.T
        t_obj = r @ origin + t
        cameras[name] = cam
        images[key] = {"camera": name, "R": R_obj.tolist(), "t": t_obj.tolist()}
        views[key] = (cam, R_obj, t_obj)

        data = git_show(args.mirror, f"{src}/image_camera{i:02d}.png")
        tmp = out / f".src_{i:02d}.png"
        tmp.write_bytes(data)
        inp = oiio.ImageInput.open(str(tmp))
        spec = inp.spec()
        pix = inp.read_image(0, 0, 0, spec.nchannels, "uint8")
        inp.close()
        tmp.unlink()
        pix = np.asarray(pix).reshape(spec.height, spec.width, spec.nchannels)
        assert spec.nchannels == 2, "the source PNGs are grey + alpha"
        gray16, alpha16 = downscale(pix[:, :, 0], pix[:, :, 1])
        write_png16(out / "images" / key, gray16, alpha16)
        photos[key] = gray16.astype(float) / 65535.0

    (out / "poses.json").write_text(
        json.dumps({"frame": "object", "units": "meters", "cameras": cameras, "images": images}, indent=1) + "\n"
    )

    mesh = poisson_mesh(points_obj, normals_obj)
    mesh.export(out / "mesh.ply")

    rng = np.random.default_rng(0)
    keep = np.sort(rng.choice(len(points_obj), size=min(REFERENCE_POINTS, len(points_obj)), replace=False))
    _write_points_with_normals(out / "reference_points.ply", points_obj[keep], normals_obj[keep], colours[keep])

    # --- sanity numbers
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    rays = RayMeshIntersector(mesh)
    # the reference points against the mesh: signed distance along the PMVS normal (ray cast both ways)
    eps = 0.004
    origins = points_obj + eps * normals_obj
    loc, idx, _ = rays.intersects_location(origins, -normals_obj, multiple_hits=False)
    dist = np.full(len(points_obj), np.nan)
    dist[idx] = eps - np.linalg.norm(loc - origins[idx], axis=1)
    check = {
        "source": {"repo": "drewm1980/multi_view_stereo_benchmark_data", "commit": commit, "capture": args.capture},
        "object_frame": {"Q_rows_world": q.tolist(), "origin_world_m": origin.tolist(), "scale": 1.0},
        "ring_radius_m": float(np.linalg.norm(centres - centres.mean(0), axis=1).mean()),
        "ring_flatness_m": float(np.linalg.svd(centres - centres.mean(0))[1][2] / np.sqrt(CAMERAS)),
        "cloud_points": int(len(points_obj)),
        "cloud_extent_m": (points_obj.max(0) - points_obj.min(0)).tolist(),
        "mesh": {
            "vertices": len(mesh.vertices),
            "faces": len(mesh.faces),
            "watertight": bool(mesh.is_watertight),
            "winding_consistent": bool(mesh.is_winding_consistent),
            "volume_m3": float(mesh.volume),
            "extent_m": mesh.extents.tolist(),
        },
        "cloud_to_mesh_m": {
            "hit_fraction": float(np.isfinite(dist).mean()),
            "median_abs": float(np.nanmedian(np.abs(dist))),
            "p95_abs": float(np.nanpercentile(np.abs(dist), 95)),
        },
        "reprojection": reprojection_check(points_obj, normals_obj, colours, views, photos),
    }
    (out / "conversion.json").write_text(json.dumps(check, indent=1) + "\n")
    print(json.dumps({k: v for k, v in check.items() if k != "reprojection"}, indent=1))
    for key, r in check["reprojection"].items():
        print(key, r)


def _write_points_with_normals(path: Path, points: np.ndarray, normals: np.ndarray, grey: np.ndarray) -> None:
    """Binary little-endian PLY: x y z nx ny nz (float32) and the PMVS grey colour (uchar red = green = blue)."""
    n = len(points)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment PMVS reference points (subsample), object frame, metres; colour = PMVS point colour\n"
        f"element vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n"
    )
    rec = np.zeros(n, dtype=[("p", "<f4", 3), ("n", "<f4", 3), ("c", "u1", 3)])
    rec["p"], rec["n"] = points, normals
    rec["c"] = np.repeat(np.clip(np.round(grey), 0, 255)[:, None], 3, axis=1)
    path.write_bytes(header.encode() + rec.tobytes())


if __name__ == "__main__":
    main()
