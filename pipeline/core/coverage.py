"""How much of the sphere of directions a set of samples covers (pure NumPy).

The sphere is cut into an *equal-area* grid: ``n_bands`` bands of equal height in z = cos θ
(Archimedes: a band's area is 2π·Δz, independent of where it sits) times ``n_azimuth`` equal
sectors in φ, so every cell has solid angle 4π / (n_bands · n_azimuth) exactly.  Coverage is the
fraction of cells holding at least ``min_count`` samples; with equal areas it is also the fraction of
solid angle (to within a cell).  θ is the polar angle from +Z, φ the azimuth from +X towards +Y,
as for environment maps (DESIGN.md).
"""

from __future__ import annotations

import numpy as np


class EqualAreaGrid:
    """Equal-area cells on the unit sphere: ``n_bands`` bands in z = cos θ × ``n_azimuth`` sectors in φ."""

    def __init__(self, n_bands: int = 16, n_azimuth: int = 32):
        if n_bands < 1 or n_azimuth < 1:
            raise ValueError("n_bands and n_azimuth must be positive")
        self.n_bands = int(n_bands)
        self.n_azimuth = int(n_azimuth)

    @property
    def shape(self) -> tuple[int, int]:
        """(n_bands, n_azimuth); band 0 is the top (z near +1), like row 0 of an equirect map."""
        return self.n_bands, self.n_azimuth

    @property
    def cells(self) -> int:
        return self.n_bands * self.n_azimuth

    @property
    def cell_solid_angle(self) -> float:
        """Solid angle of one cell in steradians: 4π / cells."""
        return 4.0 * np.pi / self.cells

    def band_edges_z(self) -> np.ndarray:
        """(n_bands + 1,) z = cos θ at the band edges, from +1 (top) down to −1."""
        return np.linspace(1.0, -1.0, self.n_bands + 1)

    def band_edges_theta(self) -> np.ndarray:
        """(n_bands + 1,) polar angle θ (radians) at the band edges, 0 … π."""
        return np.arccos(self.band_edges_z())

    def azimuth_edges(self) -> np.ndarray:
        """(n_azimuth + 1,) azimuth φ (radians) at the sector edges, 0 … 2π."""
        return np.linspace(0.0, 2.0 * np.pi, self.n_azimuth + 1)

    def cell_of(self, directions: np.ndarray) -> np.ndarray:
        """(N,) flat cell index (band * n_azimuth + sector) of each direction (N, 3); need not be unit."""
        d = np.asarray(directions, dtype=float)
        norm = np.linalg.norm(d, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.clip(d[..., 2] / norm, -1.0, 1.0)
        band = np.minimum(((1.0 - z) * 0.5 * self.n_bands).astype(np.int64), self.n_bands - 1)
        phi = np.mod(np.arctan2(d[..., 1], d[..., 0]), 2.0 * np.pi)
        sector = np.minimum((phi / (2.0 * np.pi) * self.n_azimuth).astype(np.int64), self.n_azimuth - 1)
        return band * self.n_azimuth + sector

    def histogram(self, directions: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """(n_bands, n_azimuth) sample counts (or summed ``weights``) per cell."""
        counts = np.bincount(self.cell_of(directions).ravel(), weights=weights, minlength=self.cells)
        return counts.reshape(self.shape).astype(float)


def coverage_stats(histogram: np.ndarray, min_count: float = 1.0) -> dict:
    """Coverage numbers of an equal-area ``histogram`` (from :meth:`EqualAreaGrid.histogram`).

    Returns ``{"cells", "cells_hit", "fraction", "solid_angle_sr", "min_count"}``: cells with at least
    ``min_count`` samples, their fraction of all cells and the solid angle they span.
    """
    hist = np.asarray(histogram, dtype=float)
    hit = int(np.count_nonzero(hist >= min_count))
    cells = int(hist.size)
    return {
        "cells": cells,
        "cells_hit": hit,
        "fraction": hit / cells,
        "solid_angle_sr": 4.0 * np.pi * hit / cells,
        "min_count": float(min_count),
    }
