"""hfrad: hierarchical-factorization radiosity (Aguerre & Fernández 2016)."""
__version__ = "0.1.0"
