"""Evaluating the model on an engine: per-point functions and their validation, dense grids, reductions,
the objective."""
