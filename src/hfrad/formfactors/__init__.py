"""Form factors with visibility: kernels, ray casting, column blocks.

F[i, j] = fraction of the energy leaving patch i that arrives at patch j,
visibility included (docs/method.md, section 2). Public entry points:

- :func:`iter_column_blocks` streams F in column blocks (what the hierarchical
  factorization consumes; optionally cached on disk and resumable);
- :func:`form_factor_matrix` assembles a dense F for small scenes;
- :func:`row_sums` checks closure (rows of a closed scene sum to 1);
- :mod:`hfrad.formfactors.analytic` has the catalogue's closed forms.
"""

from . import analytic
from .blocks import (DEFAULT_BLOCK_SIZE, FormFactorEngine, available_memory, check_dense_memory,
                     form_factor_matrix, iter_column_blocks, row_sums)
from .cache import BlockCache, CacheMismatchError, scene_hash
from .kernel import KERNEL_VERSION, PatchGeometry, point_to_patch, unoccluded_block
from .visibility import DEFAULT_SAMPLES, Visibility

__all__ = [
    "analytic", "DEFAULT_BLOCK_SIZE", "DEFAULT_SAMPLES", "FormFactorEngine", "available_memory",
    "check_dense_memory", "form_factor_matrix", "iter_column_blocks", "row_sums",
    "BlockCache", "CacheMismatchError", "scene_hash", "KERNEL_VERSION", "PatchGeometry",
    "point_to_patch", "unoccluded_block", "Visibility",
]
