"""Image-space measures shared by losses and metrics: the LPIPS network and its shipped weights. Imports torch and
the core modules only."""
