"""Scenarios: TOML files -> typed, validated dataclasses (ring and sections)."""
