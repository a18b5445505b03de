"""One object under several lightings (capture.toml [lighting]: a map per photo) as one scene for the
material fit: SceneGroups routes each sample to the renderer (pipeline.core.render.Renderer, one per
lighting, all of one mesh) of its photo's lighting.

Inputs: the renderers and each sample's group index (N,); the calls take the samples' face ids
(N,), barycentrics (N, 3) and unit view directions (N, 3) as a Renderer's do, and return their
arrays (N, 3) in the same row order (linear radiance or irradiance in the maps' units).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.core.brdf import Brdf


@dataclass(frozen=True)
class SceneGroups:
    """One object under several lightings (capture.toml [lighting]: a map per photo): sample i is
    lit by ``scenes[group[i]]`` (Renderers of one mesh).  The part of the Renderer interface the
    material fit uses (with_brdf, direct_parts, shade_parts, _indirect_at), each scene shading
    its own samples; ``direct`` is a list of the scenes' direct_parts."""

    scenes: list
    group: np.ndarray

    def _rows(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.group == g) for g in range(len(self.scenes))]

    def with_brdf(self, brdf: Brdf) -> "SceneGroups":
        return SceneGroups([s.with_brdf(brdf) for s in self.scenes], self.group)

    def direct_parts(self, faces: np.ndarray, bary: np.ndarray, view_dirs: np.ndarray) -> list:
        return [s.direct_parts(faces[i], bary[i], view_dirs[i]) for s, i in zip(self.scenes, self._rows())]

    def shade_parts(self, faces, bary, view_dirs, direct: list | None = None, footprint=None):
        diffuse, specular = np.zeros((len(faces), 3)), np.zeros((len(faces), 3))
        for g, (s, i) in enumerate(zip(self.scenes, self._rows())):
            part = None if footprint is None else (footprint[0][i], footprint[1][i])
            diffuse[i], specular[i] = s.shade_parts(faces[i], bary[i], view_dirs[i], None if direct is None else direct[g], part)
        return diffuse, specular

    def _indirect_at(self, tri: np.ndarray, bary: np.ndarray) -> np.ndarray:
        out = np.zeros((len(tri), 3))
        for s, i in zip(self.scenes, self._rows()):
            out[i] = s._indirect_at(tri[i], bary[i])
        return out
