"""Batch runs of scenario variants and the export of their tables."""
