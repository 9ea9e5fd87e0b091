"""Low-rank factorization of diag(rho_max) F: HF (the paper's method) and baselines."""

from .api import lowrank_from_blocks, lowrank_from_matrix
from .baselines import randomized_factorization, sketch_factorization, svd_factorization
from .hf import hierarchical_factorization
from .factors import LowRank
from .operator import operator_factorization

__all__ = ["LowRank", "hierarchical_factorization", "svd_factorization", "randomized_factorization",
           "sketch_factorization", "lowrank_from_matrix", "lowrank_from_blocks", "operator_factorization"]
