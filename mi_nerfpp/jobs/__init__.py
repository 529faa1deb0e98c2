"""Whole jobs built from the layers below: a training run and its folder, sweeps, Ray clusters,
exports to DCC tools, benchmarks, the terminal display."""
