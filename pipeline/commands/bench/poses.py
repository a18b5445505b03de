"""`sigrend bench poses`: seconds of the poses stage for 24 photos at 1 and 6 megapixels, split into
feature extraction, matching, mapping and registration (+ board bundle adjustment), with the pose
accuracy reached.

The photos are ray-traced here (exact ground truth, any size in seconds): a ChArUco board on a
textured floor and a textured box, pinhole cameras on a ring — the scene of tests/stages/test_poses.py,
which imports it from this module.  Full run: 24 photos of 1225x817 and 3000x2000; --quick: 8 of
400x300.  Rendering is not timed; every timed run starts from a fresh work folder.
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import map_coordinates
from scipy.spatial.transform import Rotation

from pipeline.board import make_board
from pipeline.commands.bench import BenchRow
from pipeline.core.camera import Camera, Rigid3, look_at, pixel_centers, pixel_rays
from pipeline.io.capture_toml import BoardSpec, write_capture_toml
from pipeline.io.poses import ImagePose, Poses, read_poses, write_poses
from pipeline.logs import progress as progress_bar
from pipeline.settings import make_settings
from stages import poses as poses_stage

BOARD = dict(dictionary="DICT_5X5_100", squares=(7, 5), square_length=0.03, marker_length=0.022)
# board lying on the floor, its printed side up (+Z object), centred on the origin:
# board x -> object +X, board y -> object -Y, board z (into the print) -> object -Z
BOARD_TO_OBJECT = np.array([[1.0, 0, 0, -0.105], [0, -1, 0, 0.075], [0, 0, -1, 0], [0, 0, 0, 1]])


def noise_texture(rng, size: int) -> np.ndarray:
    """Multi-scale random texture (8-bit gray) with SIFT-friendly blobs at every scale."""
    tex = np.zeros((size, size), np.float32)
    for cells in (4, 8, 16, 32, 64, 128):
        tex += cv2.resize(rng.random((cells, cells)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    return np.round(40 + 200 * tex).astype(np.uint8)


def scene_quads(
    rng, textured: bool = True, texture_scale: int = 1
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Scene as textured rectangles: (origin, edge a, edge b, 8-bit texture); point = o + u·a + v·b."""
    board = make_board(BoardSpec(BOARD["dictionary"], tuple(BOARD["squares"]), BOARD["square_length"], BOARD["marker_length"]))
    sx, sy = BOARD["squares"]
    board_img = board.generateImage((sx * 100, sy * 100), marginSize=0)
    R, t = BOARD_TO_OBJECT[:3, :3], BOARD_TO_OBJECT[:3, 3]
    quads = [(t + [0, 0, 1e-4], R @ [sx * BOARD["square_length"], 0, 0], R @ [0, sy * BOARD["square_length"], 0], board_img)]
    if not textured:  # only the board: SfM is starved of features
        return quads
    quads.append(
        (np.array([-0.3, -0.3, 0.0]), np.array([0.6, 0, 0]), np.array([0, 0.6, 0]), noise_texture(rng, 1024 * texture_scale))
    )
    # a textured box (0.08 m) off the board: four sides and the top
    c, h = np.array([0.07, 0.12, 0.0]), 0.08
    corners = [c + [-h / 2, -h / 2, 0], c + [h / 2, -h / 2, 0], c + [h / 2, h / 2, 0], c + [-h / 2, h / 2, 0]]
    for i in range(4):
        p, q = corners[i], corners[(i + 1) % 4]
        quads.append((p, q - p, np.array([0, 0, h]), noise_texture(rng, 256 * texture_scale)))
    quads.append(
        (corners[0] + [0, 0, h], corners[1] - corners[0], corners[3] - corners[0], noise_texture(rng, 256 * texture_scale))
    )
    return quads


def render(camera: Camera, R: np.ndarray, t: np.ndarray, quads, supersample: int = 2) -> np.ndarray:
    """Ray-cast the textured rectangles (nearest hit), 8-bit gray, box-filtered ``supersample``²."""
    s = supersample
    big = Camera("PINHOLE", camera.width * s, camera.height * s, tuple(np.array(camera.params) * s))
    origins, dirs = pixel_rays(big, R, t, pixel_centers(big.width, big.height))
    best = np.full(len(dirs), np.inf)
    out = np.full(len(dirs), 128.0, np.float32)
    for o, a, b, tex in quads:
        n = np.cross(a, b)
        denom = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = ((o - origins[0]) @ n) / denom
        p = origins + dist[:, None] * dirs - o
        u, v = p @ a / (a @ a), p @ b / (b @ b)
        hit = (dist > 0) & (dist < best) & (u >= 0) & (u <= 1) & (v >= 0) & (v <= 1)
        if hit.any():
            th, tw = tex.shape
            # texel centres at integer + 0.5 in (u·tw, v·th): bilinear lookup
            coords = np.stack([v[hit] * th - 0.5, u[hit] * tw - 0.5])
            out[hit] = map_coordinates(tex.astype(np.float32), coords, order=1, mode="nearest")
            best[hit] = dist[hit]
    img = out.reshape(big.height, big.width)
    return cv2.resize(img, (camera.width, camera.height), interpolation=cv2.INTER_AREA)


def make_textured_capture(
    folder: Path,
    *,
    n_views: int = 14,
    size=(400, 300),
    focal: float = 440.0,
    seed: int = 7,
    board: bool = True,
    textured: bool = True,
    views=None,
    supersample: int = 2,
    texture_scale: int = 1,
    progress: bool = False,
) -> Poses:
    """Write images/NNNN.jpg (q95, +1 grey level noise), capture.toml ([board]) and gt/poses.json.

    Cameras on a ring at 0.55 m (elevations 38°/50° alternating) looking at the scene centre;
    ``textured=False`` leaves only the board.  Returns the ground-truth poses.
    """
    rng = np.random.default_rng(seed)
    quads = scene_quads(rng, textured, texture_scale)
    w, h = size
    camera = Camera("PINHOLE", w, h, (focal, focal, w / 2, h / 2))
    gt = Poses(cameras={"cam0": camera})
    (folder / "images").mkdir(parents=True)
    if views is None:
        az = np.linspace(0, 2 * np.pi, n_views, endpoint=False) + 0.3
        el = np.deg2rad(np.where(np.arange(n_views) % 2, 50.0, 38.0))
        views = [
            (np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)]) * 0.55, np.array([0.02, 0.02, 0.03]))
            for a, e in zip(az, el)
        ]
    for i, (center, target) in enumerate(progress_bar(views, desc="render", enabled=progress)):
        R, t = look_at(center, target)
        img = render(camera, R, t, quads, supersample)
        img = np.clip(img + rng.normal(0, 1.0, img.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(folder / "images" / f"{i:04d}.jpg"), img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        gt.images[f"{i:04d}.jpg"] = ImagePose("cam0", Rigid3(R, t))
    if board:
        write_capture_toml(
            folder / "capture.toml",
            {
                "board": {
                    "dictionary": BOARD["dictionary"],
                    "squares": list(BOARD["squares"]),
                    "square_length": BOARD["square_length"],
                    "marker_length": BOARD["marker_length"],
                    "board_to_object": np.asarray(BOARD_TO_OBJECT, float).tolist(),
                }
            },
        )
    (folder / "gt").mkdir()
    write_poses(folder / "gt" / "poses.json", gt)
    return gt


def pose_errors(gt: Poses, est: Poses) -> tuple[np.ndarray, np.ndarray]:
    """Per-image rotation error (degrees) and camera-centre error relative to the camera's distance."""
    rot, cen = [], []
    for key, p in est.images.items():
        g = gt.images[key]
        rot.append(
            np.rad2deg(np.linalg.norm(Rotation.from_matrix(p.cam_from_world.rotation @ g.cam_from_world.rotation.T).as_rotvec()))
        )
        c_gt = g.cam_from_world.center()
        cen.append(np.linalg.norm(p.cam_from_world.center() - c_gt) / np.linalg.norm(c_gt))
    return np.array(rot), np.array(cen)


STEPS = ("extraction", "matching", "mapping", "registration")


def poses_suite(quick: bool, repeat: int) -> list[BenchRow]:
    """Per size: best-of-``repeat`` seconds of each step and of the stage, and the accuracy reached."""
    cases = [(8, 0.12)] if quick else [(24, 1.0), (24, 6.0)]
    rows = []
    with tempfile.TemporaryDirectory(prefix="sigrend-bench-poses-") as tmp:
        for n, megapixels in cases:
            w = int(round(np.sqrt(megapixels * 1e6 * 1.5)))
            h = int(round(w / 1.5))
            capture = Path(tmp) / f"capture_{megapixels:g}mp"
            gt = make_textured_capture(
                capture,
                n_views=n,
                size=(w, h),
                focal=1.1 * w,
                supersample=1,
                texture_scale=max(1, int(np.ceil(w / 1000))),
                progress=True,
            )
            best: dict[str, float] = {}
            for run in range(max(1, repeat)):
                work = Path(tmp) / f"work_{megapixels:g}mp_{run}"
                poses_stage.run(capture=capture, work=work, settings=make_settings(poses_stage.Settings))
                seconds = json.loads((work / "poses_summary.json").read_text())["seconds"]
                seconds["total"] = sum(seconds.values())
                for key, value in seconds.items():
                    best[key] = min(best.get(key, np.inf), value)
            rot, cen = pose_errors(gt, read_poses(work / "poses.json"))
            size = f"{n} x {w}x{h}"
            for step in (*STEPS, "copies_and_board_detection", "total"):
                rows.append(
                    BenchRow(
                        f"poses {step}",
                        0,
                        size,
                        best.get(step, float("nan")),
                        "s",
                        "registration = triangulation + similarity + board BA" if step == "registration" else "",
                    )
                )
            rows.append(BenchRow("poses max rotation error", 0, size, float(rot.max()), "deg", "vs ground truth"))
            rows.append(BenchRow("poses max centre error", 0, size, float(100 * cen.max()), "% of distance", ""))
    return rows
