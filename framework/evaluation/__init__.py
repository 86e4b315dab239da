"""Evaluation protocols and what a run leaves behind: body-box image regions (Neural Body / Animatable NeRF), metrics
on them, and the per-run results record. May import framework's core modules and registries; not lightning/ or
entry points."""
