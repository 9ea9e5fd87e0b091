"""Form factors with visibility: kernels, ray casting, column blocks."""
