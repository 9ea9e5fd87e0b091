"""Memory checks: refuse with a clear message rather than swap the machine to death."""

from __future__ import annotations

from .errors import MemoryLimitError


def available_bytes() -> int:
    """Memory available to new allocations (Linux MemAvailable; a large number elsewhere)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover - non-Linux
        pass
    return 1 << 62


def human(nbytes: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if nbytes < 1024 or unit == "TB":
            return f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} TB"  # pragma: no cover


def require(nbytes: float, what: str, hint: str = "", fraction: float = 0.8) -> None:
    """Raise MemoryLimitError if ``nbytes`` exceeds ``fraction`` of the available memory."""
    limit = fraction * available_bytes()
    if nbytes > limit:
        raise MemoryLimitError(f"{what} needs about {human(nbytes)} but only {human(limit)} is available"
                               + (f"; {hint}" if hint else ""))


def precompute_bytes(n: int, block_size: int, rank_guess: int | None = None, itemsize: int = 4) -> int:
    """Rough peak memory of ``factorize``: a few float64 blocks plus the factors.

    The factors are Q, V and three Y_c (5 n k values); merges hold about twice
    the rank transiently. The rank is not known before the run: the default
    guess is min(n, 3000), generous for eps = 0.02 on scenes up to ~50K patches.
    """
    k = min(n, 3000) if rank_guess is None else rank_guess
    return 3 * 8 * n * block_size + (5 + 4) * n * k * itemsize
