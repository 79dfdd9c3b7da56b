"""The SUMO boundary: the only package that starts SUMO or reads its input files."""
