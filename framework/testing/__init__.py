"""Reusable test machinery for third parties too: the rasterizer conformance suite and the float64 reference
compositor. Imports the registry, `splat` and core; nothing imports it but tests."""
