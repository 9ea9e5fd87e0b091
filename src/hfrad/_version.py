"""The package version, importable by every layer (``hfrad/__init__`` re-exports it)."""

__version__ = "0.1.0"
