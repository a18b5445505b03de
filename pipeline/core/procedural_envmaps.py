"""Procedural environment maps in DESIGN.md's equirect convention (pure NumPy).

Every map is linear RGB radiance, (H, 2H, 3), row 0 the zenith, and covers the whole sphere:
the lower hemisphere is a ground (or floor) of non-zero radiance.  Small sources (sun disk,
near-point source) are rasterized on the pixel centres and then rescaled so that their power
(sum of L dω) is exactly what was asked, at any map height; a source smaller than a pixel
still lights at least its nearest pixel.

Spec grammar (``parse_env_spec``):  ``NAME[:key=value,key=value,...]``

  constant   value=1                                uniform radiance (white furnace)
  smooth     scale=1                                band-limited (spherical polynomial of degree 2,
                                                    SH bands l <= 2 only), positive everywhere;
                                                    its exact formula is ``smooth_coefficients``
  sun+sky    elev=45,az=30,sun=30,sky=1,size=0.53   sun disk (irradiance ``sun`` at normal
                                                    incidence, angular diameter ``size`` degrees)
                                                    over a bluish gradient sky and a brown ground
  overcast   zenith=1,ground=0.3                    CIE overcast sky L(θ) = Lz (1 + 2 cos θ) / 3
  area       n=2,size=20,radiance=8,elev=45,seed=0  n rectangular area lights (size degrees square)
                                                    spread around the object, dim grey room
  point      elev=50,az=120,power=20,size=1         a near-point source: a small, very bright disk
                                                    of angular diameter ``size`` degrees and
                                                    irradiance ``power``, over a dim room
  room       lamp=10                                coloured walls (red, green, blue, white), a white
                                                    ceiling with a rectangular lamp, a grey floor
All accept ``height=H`` (default 64, giving a 128 x 64 map).  Angles are degrees; ``elev`` is
the elevation above the horizon (90 = zenith), ``az`` the azimuth from +X towards +Y.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.envmap import equirect_directions, equirect_solid_angles

DEFAULT_HEIGHT = 64

# name -> default parameters (every key a user may set)
ENV_PARAMS: dict[str, dict[str, float]] = {
    "constant": {"value": 1.0},
    "smooth": {"scale": 1.0},
    "sun+sky": {"elev": 45.0, "az": 30.0, "sun": 30.0, "sky": 1.0, "size": 0.53},
    "overcast": {"zenith": 1.0, "ground": 0.3},
    "area": {"n": 2, "size": 20.0, "radiance": 8.0, "elev": 45.0, "seed": 0},
    "point": {"elev": 50.0, "az": 120.0, "power": 20.0, "size": 1.0},
    "room": {"lamp": 10.0},
}


def direction_from_angles(elev_deg: float, az_deg: float) -> np.ndarray:
    """Unit vector at elevation ``elev_deg`` above the XY plane and azimuth ``az_deg`` from +X to +Y."""
    e, a = np.radians(elev_deg), np.radians(az_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _solid_angle_map(height: int) -> np.ndarray:
    return np.broadcast_to(equirect_solid_angles(height)[:, None], (height, 2 * height))


def _add_disk(env: np.ndarray, dirs: np.ndarray, centre: np.ndarray, diameter_deg: float, irradiance: np.ndarray) -> None:
    """Add a uniform disk of angular diameter ``diameter_deg`` whose power sum(L dω) = ``irradiance`` (RGB)."""
    cos_r = np.cos(np.radians(diameter_deg) / 2.0)
    inside = dirs @ centre >= cos_r
    if not inside.any():  # smaller than a pixel: light the nearest pixel centre
        inside = np.zeros(dirs.shape[:2], bool)
        inside[np.unravel_index(np.argmax(dirs @ centre), inside.shape)] = True
    omega = float(_solid_angle_map(env.shape[0])[inside].sum())
    env[inside] += np.asarray(irradiance, float)[None, :] / omega


def _tangent_frame(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(helper, c)
    u /= np.linalg.norm(u)
    return u, np.cross(c, u)


def _add_rectangle(
    env: np.ndarray, dirs: np.ndarray, centre: np.ndarray, width_deg: float, height_deg: float, radiance: np.ndarray
) -> None:
    """Add a rectangular light: |atan(d.u / d.c)| < w/2 and |atan(d.v / d.c)| < h/2 around ``centre``."""
    u, v = _tangent_frame(centre)
    dc = dirs @ centre
    with np.errstate(divide="ignore", invalid="ignore"):
        au = np.abs(np.arctan2(dirs @ u, dc))
        av = np.abs(np.arctan2(dirs @ v, dc))
    inside = (dc > 0) & (au < np.radians(width_deg) / 2) & (av < np.radians(height_deg) / 2)
    if not inside.any():
        inside[np.unravel_index(np.argmax(dc), inside.shape)] = True
    env[inside] = np.asarray(radiance, float)[None, :]


def smooth_coefficients(scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``smooth`` map L(d) = c + a . d + d^T Q d per channel: c (3,), a (3, 3) rows x,y,z, Q (3, 3, 3).

    Degree 2 in d, so only SH bands l <= 2 are non-zero; positive everywhere (minimum about 0.37 * scale).
    Arrays are indexed [channel], [channel, axis], [channel, axis, axis].
    """
    c = np.array([1.0, 0.9, 0.8])
    a = np.array([[0.3, 0.1, 0.4], [-0.2, 0.25, 0.35], [0.1, -0.3, 0.3]])
    q = np.zeros((3, 3, 3))
    for ch, (xy, yz, xz, zz) in enumerate([(0.15, 0.0, 0.1, 0.1), (0.0, 0.1, -0.1, -0.05), (-0.1, 0.05, 0.0, 0.15)]):
        q[ch] = [[0.0, xy, xz], [xy, 0.0, yz], [xz, yz, zz]]
    return scale * c, scale * a, scale * q


def _smooth(dirs: np.ndarray, scale: float) -> np.ndarray:
    c, a, q = smooth_coefficients(scale)
    lin = np.einsum("hwi,ci->hwc", dirs, a)
    quad = np.einsum("hwi,cij,hwj->hwc", dirs, q, dirs)
    return c[None, None, :] + lin + quad


def _sky_and_ground(dirs: np.ndarray, sky: float, sun_dir: np.ndarray | None = None) -> np.ndarray:
    """Bluish gradient sky (brighter at the horizon and around the sun) over a brown ground."""
    z = dirs[..., 2]
    zenith_blue = np.array([0.35, 0.55, 1.0]) * sky
    horizon = np.array([0.8, 0.85, 0.95]) * sky
    tt = np.clip(z, 0.0, 1.0)[..., None] ** 0.5
    env = horizon * (1 - tt) + zenith_blue * tt
    if sun_dir is not None:
        glow = np.exp((dirs @ sun_dir - 1.0) / 0.1)[..., None]  # circumsolar brightening
        env = env + glow * np.array([1.0, 0.9, 0.7]) * 2.0 * sky
    ground = np.array([0.30, 0.25, 0.18]) * sky * (0.6 + 0.4 * np.clip(-z, 0, 1))[..., None]
    return np.where((z > 0)[..., None], env, ground)


def _dim_room(dirs: np.ndarray, level: float = 0.05) -> np.ndarray:
    z = dirs[..., 2]
    return level * np.where((z > 0)[..., None], np.array([1.0, 1.0, 1.0]), np.array([0.6, 0.55, 0.5]))


def make_envmap(name: str, height: int = DEFAULT_HEIGHT, **params: float) -> np.ndarray:
    """Procedural map ``name`` (see the module docstring) as float32 (height, 2*height, 3)."""
    if name not in ENV_PARAMS:
        raise ValueError(f"unknown environment {name!r}")
    p = {**ENV_PARAMS[name], **params}
    unknown = set(params) - set(ENV_PARAMS[name])
    if unknown:
        raise ValueError(f"environment {name!r} has no parameter(s) {sorted(unknown)}")
    dirs = equirect_directions(height)
    if name == "constant":
        env = np.full(dirs.shape, float(p["value"]))
    elif name == "smooth":
        env = _smooth(dirs, float(p["scale"]))
    elif name == "sun+sky":
        sun_dir = direction_from_angles(p["elev"], p["az"])
        env = _sky_and_ground(dirs, float(p["sky"]), sun_dir)
        _add_disk(env, dirs, sun_dir, float(p["size"]), float(p["sun"]) * np.array([1.0, 0.95, 0.85]))
    elif name == "overcast":
        z = dirs[..., 2]
        sky = float(p["zenith"]) * (1 + 2 * np.clip(z, 0, 1)) / 3
        env = np.where(
            (z > 0)[..., None],
            sky[..., None] * np.array([0.95, 0.97, 1.0]),
            float(p["ground"]) * float(p["zenith"]) * np.array([0.9, 0.85, 0.8]),
        )
    elif name == "area":
        env = _dim_room(dirs)
        n = int(p["n"])
        rng = np.random.default_rng(int(p["seed"]))
        tints = [np.array([1.0, 0.95, 0.9]), np.array([0.85, 0.9, 1.0]), np.array([1.0, 0.85, 0.7]), np.array([0.9, 1.0, 0.9])]
        for k in range(n):
            elev = float(p["elev"]) + rng.uniform(-15, 15)
            az = 360.0 * k / max(n, 1) + rng.uniform(0, 40)
            w = float(p["size"]) * rng.uniform(0.7, 1.3)
            _add_rectangle(
                env, dirs, direction_from_angles(elev, az), w, float(p["size"]), float(p["radiance"]) * tints[k % len(tints)]
            )
    elif name == "point":
        env = _dim_room(dirs)
        _add_disk(
            env, dirs, direction_from_angles(p["elev"], p["az"]), float(p["size"]), float(p["power"]) * np.array([1.0, 1.0, 1.0])
        )
    elif name == "room":
        z = dirs[..., 2]
        phi = np.mod(np.arctan2(dirs[..., 1], dirs[..., 0]), 2 * np.pi)
        walls = np.array([[0.6, 0.15, 0.1], [0.15, 0.5, 0.15], [0.15, 0.2, 0.6], [0.6, 0.6, 0.6]])
        env = walls[(phi // (np.pi / 2)).astype(int) % 4]
        env = np.where((z > 0.7)[..., None], np.array([0.8, 0.8, 0.8]), env)  # ceiling
        env = np.where((z < -0.3)[..., None], np.array([0.3, 0.28, 0.25]), env)  # floor
        env = env.astype(float)
        _add_rectangle(env, dirs, np.array([0.0, 0.0, 1.0]), 30.0, 15.0, float(p["lamp"]) * np.array([1.0, 0.95, 0.85]))
    return np.ascontiguousarray(env, dtype=np.float32)


def parse_env_spec(spec: str) -> tuple[str, int, dict[str, float]]:
    """``NAME[:k=v,...]`` -> (name, height, params); ValueError with a readable message when malformed."""
    name, _, rest = spec.strip().partition(":")
    name = name.strip()
    if name not in ENV_PARAMS:
        raise ValueError(f"unknown environment {name!r}; use an equirect EXR or one of {', '.join(ENV_PARAMS)}")
    params: dict[str, float] = {}
    height = DEFAULT_HEIGHT
    for token in filter(None, (t.strip() for t in rest.split(","))):
        key, eq, value = token.partition("=")
        key = key.strip()
        if not eq:
            raise ValueError(f"environment spec {spec!r}: expected key=value, got {token!r}")
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"environment spec {spec!r}: {key} must be a number, got {value!r}") from None
        if key == "height":
            height = int(number)
            if height < 2:
                raise ValueError(f"environment spec {spec!r}: height must be >= 2")
        elif key not in ENV_PARAMS[name]:
            raise ValueError(f"environment {name!r} has no parameter {key!r}; known: {', '.join(['height', *ENV_PARAMS[name]])}")
        else:
            params[key] = number
    return name, height, params


def spec_help() -> str:
    """The procedural maps in one phrase, for every option that takes one (relight --env, synth --env,
    env make): the names from ENV_PARAMS, the one list."""
    return (
        f"a procedural map NAME[:key=value,...], NAME one of {', '.join(ENV_PARAMS)} (e.g. 'sun+sky:elev=40,az=30'; "
        f"height=H rows, default {DEFAULT_HEIGHT}; every key in docs/synth.md)"
    )


def envmap_from_spec(spec: str) -> np.ndarray:
    """Procedural map from a spec string (module docstring)."""
    name, height, params = parse_env_spec(spec)
    return make_envmap(name, height, **params)
