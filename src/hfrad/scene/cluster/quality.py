"""Measures of clustered patches: diameter, compactness, and a summary for ``hfrad info``."""

from __future__ import annotations

import numpy as np

from ..scene import Scene

def patch_diameters(scene: Scene) -> np.ndarray:
    """(n,) metres: twice the largest distance of a patch's corners from its centroid.

    At least the patch's diameter and at most twice it (a disk: exactly it).
    """
    start, index = scene.patch_triangles
    if not len(index):
        return np.zeros(scene.n_patches)
    owner = np.repeat(np.arange(scene.n_patches), np.diff(start))
    reach = np.linalg.norm(scene.triangles[index] - scene.centroids[owner][:, None], axis=2).max(axis=1)
    return 2.0 * np.maximum.reduceat(reach, start[:-1])


def compactness(scene: Scene) -> np.ndarray:
    """(n,) D^2 / A per patch, D from :func:`patch_diameters`: 4 / pi for a disk, about 2.3 to 5 for
    squares and equilateral triangles, ~ length / width for a long strip."""
    if not scene.n_patches:
        return np.zeros(0)
    return patch_diameters(scene) ** 2 / np.maximum(scene.areas, 1e-300)


def cluster_summary(scene: Scene) -> dict:
    """What clustering did: patches, triangles per patch, worst non-flatness, compactness."""
    per = np.bincount(scene.patch_of_triangle, minlength=scene.n_patches) if scene.n_patches else np.zeros(0, int)
    nf = scene.non_flatness
    q = compactness(scene)
    return {
        "clustered": scene.is_clustered,
        "triangles": scene.n_triangles,
        "triangles_per_patch": {"mean": float(per.mean()) if per.size else 0.0,
                                "max": int(per.max(initial=0)), "median": float(np.median(per)) if per.size else 0.0},
        "worst_non_flatness": float(nf.max(initial=0.0)),
        "area_cv": float(scene.areas.std() / scene.areas.mean()) if per.size else 0.0,
        "compactness": {"median": float(np.median(q)) if q.size else 0.0,
                        "p99": float(np.percentile(q, 99)) if q.size else 0.0, "max": float(q.max(initial=0.0))},
    }
