"""Synthetic data with known truth: shapes, factor populations, images (used by tests,
benchmarks and the demo tour)."""
