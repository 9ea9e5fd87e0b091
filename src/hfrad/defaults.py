"""Defaults shared by several layers, defined once."""

#: Column block width (patches) in which F is generated, streamed and factorized.
DEFAULT_BLOCK_SIZE = 256
