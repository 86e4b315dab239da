"""Reusable test machinery for third parties too: the rasterizer conformance suite, the float64 reference
compositor and the hypothesis profiles of the numerical-extremes properties. Imports the registry, `splat` and core;
nothing imports it but tests."""
