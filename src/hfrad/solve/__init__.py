"""Radiosity solvers: the Woodbury solve of a factorization, and baselines (LU, iterations)."""

from .woodbury import HFactorization

__all__ = ["HFactorization"]
