"""Energy checks on the row sums of F: a patch cannot send out more light than it has.

Row i of F sums to the fraction of patch i's light that lands on other
patches: at most 1, exactly 1 in a closed scene. The sums are accumulated for
free while F streams past (:class:`hfrad.solve.stats.PassStatistics`). A row
well above 1 means duplicated or overlapping geometry (each copy receives the
full share) or a form-factor failure; well below 1 in a closed scene means
light leaks through a gap.
"""

from __future__ import annotations

import warnings

import numpy as np

from ..errors import AccuracyWarning

#: Row sums within this of 1 are the kernel's and the visibility sampling's own error.
ROW_SUM_TOLERANCE = 0.05
#: Patches named in a warning.
WORST = 5

__all__ = ["ROW_SUM_TOLERANCE", "energy_problems", "warn_energy", "is_closed"]


def is_closed(scene) -> bool:
    """Whether the occluder mesh is closed: every edge is shared by exactly two triangles."""
    faces = np.asarray(scene.occluder_faces, dtype=np.int64)
    if not len(faces):
        return False
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    # each edge as one integer (lower corner, higher corner), sorted: closed when they come in equal
    # pairs and no pair equals the next (an edge of three or more faces). One sort of integers: a
    # row-wise np.unique of the 1M edges of a 331K-triangle mesh took a second
    keys = edges[:, 0] * (int(faces.max()) + 1) + edges[:, 1]
    keys.sort()
    if keys.size % 2:
        return False
    return bool((keys[0::2] == keys[1::2]).all() and (keys[1:-1:2] != keys[2::2]).all())


def _worst(scene, idx: np.ndarray, row_sums: np.ndarray) -> str:
    names = scene.material_names
    return ", ".join(f"patch {i} ({names[scene.material[i]]}) {row_sums[i]:.3f}" for i in idx)


def _likely_cause(scene) -> str:
    """Why rows exceed 1, as far as the scene tells (measured against cosine-weighted ray shooting
    on the public scenes, issue 46: after duplicates and overlaps are resolved at load, and since
    bent clusters get segments on their own triangles (visibility.py), the worst rows' excess sits on
    a few touching neighbours, bent clusters whose visibility the paired segments estimate with a
    large scatter: the weights cos cos / r^2 of a few short segments dominate)."""
    if not scene.is_clustered:
        return ("Duplicate or overlapping faces kept (--keep-duplicates), or faces that cut through each "
                "other? (hfrad info lists the broken faces)")
    return ("Duplicates and coplanar overlaps are merged and cut at load unless --keep-duplicates; on a "
            "clustered mesh the rest comes from patches touching a curved cluster (up to "
            f"{float(np.max(scene.non_flatness)):.2f} from flat, 1 - |mean normal|): the visibility rays "
            "between touching curved clusters scatter (a few short rays weigh most); more patches "
            "(smaller, flatter clusters) bring the rows closer to 1")


def energy_problems(scene, row_sums, *, tolerance: float = ROW_SUM_TOLERANCE) -> list[str]:
    """Messages about rows of F that create energy (> 1 + tolerance) or, in a closed scene, leak it.

    Parameters
    ----------
    scene : Scene
    row_sums : (n,) float, user patch order
        ``sum_j F[i, j]``.
    tolerance : float

    Returns
    -------
    list of str, empty when the row sums are plausible; each names the worst
    patches, their materials and row sums.
    """
    r = np.asarray(row_sums, dtype=np.float64)
    out = []
    over = np.flatnonzero(r > 1.0 + tolerance)
    if over.size:
        worst = over[np.argsort(r[over])[::-1][:WORST]]
        mats = sorted({scene.material_names[m] for m in scene.material[over]})
        out.append(f"{scene.name}: {over.size} patches send out more light than they receive (row sums of F up "
                   f"to {r.max():.3f} > 1 + {tolerance}), materials {', '.join(mats)}; worst: "
                   f"{_worst(scene, worst, r)}. {_likely_cause(scene)}")
    under = np.flatnonzero(r < 1.0 - tolerance)
    if under.size and is_closed(scene):
        worst = under[np.argsort(r[under])[:WORST]]
        out.append(f"{scene.name}: the scene is closed but {under.size} patches lose light (row sums of F "
                   f"down to {r.min():.3f} < 1 - {tolerance}); worst: {_worst(scene, worst, r)}")
    return out


def warn_energy(scene, row_sums, *, tolerance: float = ROW_SUM_TOLERANCE) -> list[str]:
    """Emit :func:`energy_problems` as AccuracyWarnings; returns the messages."""
    problems = energy_problems(scene, row_sums, tolerance=tolerance)
    for message in problems:
        warnings.warn(message, AccuracyWarning, stacklevel=3)
    return problems
