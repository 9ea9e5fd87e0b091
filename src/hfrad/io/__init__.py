"""Readers and writers of hfrad files."""
