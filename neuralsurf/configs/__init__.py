"""Hydra configs of neuralsurf, shipped in the package (the repository configs/ links here)."""
