"""Equirectangular environment-map geometry (DESIGN.md convention).

Pixel row i, column j of an H x 2H map is the direction with polar angle theta = pi (i + 0.5) / H
from +Z and azimuth phi = 2 pi (j + 0.5) / W from +X towards +Y; row 0 is the zenith.
A pixel's exact solid angle is (2 pi / W) (cos theta_top - cos theta_bottom).
"""

from __future__ import annotations

import numpy as np


def equirect_angles(height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre polar angles (H,) and azimuths (2H,) in radians."""
    width = 2 * height
    theta = np.pi * (np.arange(height) + 0.5) / height
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    return theta, phi


def equirect_directions(height: int) -> np.ndarray:
    """Unit direction of every pixel centre: (H, 2H, 3)."""
    theta, phi = equirect_angles(height)
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    return np.stack(np.broadcast_arrays(st * np.cos(phi)[None, :], st * np.sin(phi)[None, :], ct), axis=-1)


def equirect_solid_angles(height: int) -> np.ndarray:
    """Exact solid angle of the pixels of each row: (H,), in steradians; they sum (x 2H) to 4 pi."""
    edges = np.pi * np.arange(height + 1) / height
    return (2.0 * np.pi / (2 * height)) * (np.cos(edges[:-1]) - np.cos(edges[1:]))


def direction_to_pixel(dirs: np.ndarray, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column (integer, nearest pixel) of each unit direction (N, 3) in an H x 2H map."""
    d = np.asarray(dirs, dtype=float).reshape(-1, 3)
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi)
    width = 2 * height
    row = np.clip((theta / np.pi * height).astype(np.int64), 0, height - 1)
    col = np.clip((phi / (2.0 * np.pi) * width).astype(np.int64), 0, width - 1)
    return row, col


def lookup(env: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Nearest-pixel radiance of an (H, 2H, C) map in directions (N, 3) -> (N, C)."""
    row, col = direction_to_pixel(dirs, env.shape[0])
    return env[row, col]


def downsample(env: np.ndarray, factor: int) -> np.ndarray:
    """Box-filter an (H, 2H, C) map by an integer factor, weighting by solid angle (energy-preserving)."""
    h, w, c = env.shape
    if factor == 1:
        return env.copy()
    if h % factor:
        raise ValueError(f"height {h} is not divisible by {factor}")
    omega = equirect_solid_angles(h)[:, None, None]
    flux = (env * omega).reshape(h // factor, factor, w // factor, factor, c).sum(axis=(1, 3))
    new_omega = equirect_solid_angles(h // factor)[:, None, None]
    return flux / new_omega


def blender_columns(env: np.ndarray, rotation_texels: int = 0) -> np.ndarray:
    """An (H, W, C) map's columns reordered between DESIGN.md's convention and Blender's default
    Environment Texture mapping (also three.js's equirectangular one, in its +Y-up frame after
    glTF's rotation): Blender reads world direction d at u = 0.5 - atan2(d_y, d_x) / 2pi from the
    left edge, after a world rotation of ``rotation_texels`` whole texels about +Z, so column j of one
    is column (W/2 - 1 - j - k) mod W of the other; rows (v = acos(d_z) / pi from the top) agree.
    The reordering is its own inverse, so it converts either way."""
    width = env.shape[1]
    return env[:, (width // 2 - 1 - np.arange(width) - int(rotation_texels)) % width]


# A map in Blender's column order (blender_columns) as the latlong texture of a USD DomeLight.
# UsdLux.DomeLight reads its texture as OpenEXR's latitude-longitude map in the light's own frame,
# pole +Y: column x at longitude lon = pi - 2 pi (x + 0.5) / W (+pi at the left edge), row y at
# latitude pi/2 - pi (y + 0.5) / H, direction (cos lat sin lon, sin lat, cos lat cos lon); lon 0 is
# +Z, lon pi/2 is +X.  Blender's column x holds our azimuth phi = pi - 2 pi (x + 0.5) / W, so lon =
# phi and lat = pi/2 - theta: the light's (x, y, z) is our (sin th sin phi, cos th, sin th cos phi),
# i.e. d_object = (d_light_z, d_light_x, d_light_y).  That is a rotation (det +1, 120 degrees about
# (1, 1, 1)): the light's +Y (its pole) to the object's +Z, +Z to +X, +X to +Y; as USD's xformOp
# rotateXYZ (X first, then Y, then Z: Rz(90) Rx(90)), the angles below.  A stage whose upAxis is Z
# changes nothing: UsdLux.DomeLight's pole is its own +Y whatever the stage's up axis.
USD_DOME_TO_OBJECT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # d_object = M @ d_light
USD_DOME_ROTATE_XYZ_DEG = (90.0, 0.0, 90.0)

# The same map as the radiance of a Mitsuba 3 ``envmap`` emitter (src/emitters/envmap.cpp; checked on
# mitsuba 3.9.1 by evaluating the emitter).  Mitsuba reads its latlong image in the emitter's own frame,
# pole +Y: direction_to_uv u = atan2(d_x, -d_z) / 2 pi, v = acos(d_y) / pi, i.e. (u, v) is the direction
# (sin 2 pi u sin pi v, cos pi v, -cos 2 pi u sin pi v); column x sits at u = (x + 0.5) / W (its
# half-texel shift) and row y at v = y / (H - 1) (rows from pole to pole inclusive, not pixel centres).
# Blender's column x holds our azimuth phi = pi - 2 pi (x + 0.5) / W, so 2 pi u = pi - phi and the
# emitter's (x, y, z) is our (sin th sin phi, cos th, sin th cos phi): d_object = (d_em_z, d_em_x, d_em_y),
# OpenEXR's latlong exactly as USD's DomeLight reads it, so the same rotation as USD_DOME_TO_OBJECT is
# the emitter's ``to_world`` (a map in our own column order would need a mirror: det -1).  Rows: Mitsuba
# puts row y at theta = pi y / (H - 1), we at pi (y + 0.5) / H; they agree at the equator and differ by
# up to half a texel towards the poles (0.18 degrees for export's default 512 rows).
MITSUBA_ENVMAP_TO_OBJECT = USD_DOME_TO_OBJECT  # d_object = M @ d_emitter


def add_sources(env: np.ndarray, directions: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """A copy of an (H, 2H, 3) map with directional sources added: each source's intensity
    (J, 3) (irradiance it gives at normal incidence, sum L dω) spread bilinearly over the four
    pixel centres around its direction (J, 3), as radiance intensity x weight / pixel solid angle."""
    out = np.array(env, dtype=float)
    d = np.atleast_2d(np.asarray(directions, float))
    power = np.atleast_2d(np.asarray(intensity, float))
    if d.size == 0:
        return out
    h = out.shape[0]
    w = 2 * h
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2.0 * np.pi)
    y = np.clip(theta / np.pi * h - 0.5, 0.0, h - 1.0)
    x = phi / (2.0 * np.pi) * w - 0.5
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    omega = equirect_solid_angles(h)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            row, col = np.minimum(y0 + dy, h - 1), np.mod(x0 + dx, w)
            np.add.at(out, (row, col), power * (wy * wx / omega[row])[:, None])
    return out


def bilinear_lookup(env: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of an (H, 2H, C) equirect map at unit directions (N, 3) (wraps in azimuth)."""
    h, w = env.shape[:2]
    d = np.asarray(dirs, float)
    theta = np.arccos(np.clip(d[:, 2], -1, 1))
    phi = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    y = np.clip(theta / np.pi * h - 0.5, 0, h - 1)  # pixel centres at (i + 0.5)
    x = phi / (2 * np.pi) * w - 0.5
    y0 = np.minimum(np.floor(y).astype(int), h - 2) if h > 1 else np.zeros(len(y), int)
    fy = (y - y0)[:, None]
    x0 = np.floor(x).astype(int)
    fx = (x - x0)[:, None]
    x0 %= w
    x1 = (x0 + 1) % w
    y1 = np.minimum(y0 + 1, h - 1)
    return (1 - fy) * ((1 - fx) * env[y0, x0] + fx * env[y0, x1]) + fy * ((1 - fx) * env[y1, x0] + fx * env[y1, x1])
