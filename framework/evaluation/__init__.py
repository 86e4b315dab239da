"""Evaluation protocols and what a run leaves behind: body-box image regions (Neural Body / Animatable NeRF), metrics
on them, a run's cost (render fps, size, frame timing) and the per-run results record. May import framework's core
modules and registries; not model/, lightning/ or entry points (the checks are pyproject's import-linter contracts)."""
