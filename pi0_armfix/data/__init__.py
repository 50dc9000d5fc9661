"""Data sources, statistics, transforms and the input pipeline."""
