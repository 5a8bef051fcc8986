"""Unconstrained PCA of a registered PSF grid, and principal angles between subspaces.

SVD of the aligned PSFs (positions × pixels), uncentred (the first component is close to the
mean PSF) and centred, on the pixels measured at every position used.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import linalg

from psfkit.errors import InvalidInputError


@dataclass
class PcaResult:
    """PCA of a grid: cumulative explained energy fractions (uncentred / centred) for r = 1..P, the
    first uncentred ``components`` ``(r, C, h, w)`` (zero outside ``region``), PSFs used."""

    explained: np.ndarray
    explained_centred: np.ndarray
    singular_values: np.ndarray
    components: np.ndarray = field(repr=False)
    region: np.ndarray = field(repr=False)
    positions: int = 0

    def residual(self, centred: bool = False) -> np.ndarray:
        """Relative residual ``sqrt(1 − explained)`` vs rank."""
        explained = self.explained_centred if centred else self.explained
        return np.sqrt(np.clip(1.0 - explained, 0.0, None))

    def to_dict(self) -> dict:
        return {"positions": self.positions,
                "region_fraction": float(self.region.mean()),
                "explained": self.explained.tolist(),
                "explained_centred": self.explained_centred.tolist(),
                "singular_values": self.singular_values.tolist()}


def stack_pca(images: np.ndarray, valid: np.ndarray, use: np.ndarray | None = None,
              n_components: int = 6) -> PcaResult:
    """PCA of ``images`` ``(P, C, h, w)`` on the pixels valid in every used PSF.

    Parameters
    ----------
    images, valid : numpy.ndarray
        Aligned PSFs and their ``(P, h, w)`` valid masks.
    use : numpy.ndarray, optional
        ``(P,)`` bool, the PSFs to include.
    n_components : int
        Components kept as images.
    """
    use = np.ones(len(images), bool) if use is None else use
    region = np.all(valid[use], axis=0)
    if region.sum() < 16 or use.sum() < 2:
        raise InvalidInputError("too few PSFs or too little common area for a PCA")
    data = images[use][:, :, region].reshape(int(use.sum()), -1).astype(np.float64)
    _, s, vt = np.linalg.svd(data, full_matrices=False)
    energy = s**2
    explained = np.cumsum(energy) / energy.sum()
    centred = data - data.mean(axis=0)
    sc = np.linalg.svd(centred, compute_uv=False)
    explained_centred = np.cumsum(sc**2) / max(np.sum(sc**2), 1e-300)
    r = min(n_components, len(s))
    components = np.zeros((r, images.shape[1], *region.shape), dtype=np.float32)
    components[:, :, region] = vt[:r].reshape(r, images.shape[1], -1)
    return PcaResult(explained=explained, explained_centred=explained_centred,
                     singular_values=s, components=components, region=region,
                     positions=int(use.sum()))


def principal_angles_deg(basis_a: np.ndarray, basis_b: np.ndarray) -> np.ndarray:
    """Principal angles (degrees, ascending) between the spans of two ``(k, ...)`` image sets."""
    a = basis_a.reshape(len(basis_a), -1).T.astype(np.float64)
    b = basis_b.reshape(len(basis_b), -1).T.astype(np.float64)
    return np.sort(np.degrees(linalg.subspace_angles(a, b)))
