"""The precompute: what ``hfrad.factorize`` validates, runs in this process and assembles.

Between :mod:`hfrad.solve` (the solver object and its file) and :mod:`hfrad.distributed`
(the same precompute as Dask tasks):

* :mod:`~hfrad.precompute.options`: the expert knobs (:class:`PrecomputeOptions`), the
  near-field policy, and :func:`plan_precompute`, which validates everything once
  (``eps`` first) into a :class:`PrecomputePlan` both backends run;
* :mod:`~hfrad.precompute.backends`: :class:`LocalBackend`, :class:`DaskBackend` and
  :class:`Checkpoint`, the small objects of the front door;
* :mod:`~hfrad.precompute.assemble`: what a column block adds (statistics, G, the near
  field's split) and the one assembly step of every entry point;
* :mod:`~hfrad.precompute.local`: the in-process loop (streamed blocks into HF, checkpoints);
* :mod:`~hfrad.precompute.matrix`: ``factorize_matrix`` and ``factorize_blocks``.

The public entry points are :func:`hfrad.factorize` (:mod:`hfrad.pipeline`, which picks
the backend) and :func:`hfrad.factorize_matrix`.
"""

from .backends import Checkpoint, DaskBackend, LocalBackend
from .assemble import PrecomputePlan
from .options import PrecomputeOptions, plan_precompute

__all__ = ["Checkpoint", "DaskBackend", "LocalBackend", "PrecomputeOptions", "PrecomputePlan", "plan_precompute"]
