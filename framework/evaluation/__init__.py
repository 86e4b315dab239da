"""Evaluation protocols and what a run leaves behind: body-box image regions (Neural Body / Animatable NeRF), metrics
on them, a run's cost (render fps, size) and the per-run results record. May import framework's core modules,
registries and model/ (frame timing); not lightning/ or entry points."""
