"""Splatting math with no state: camera projection of Gaussians, the SH colour basis, the (Gaussian, pixel) pair
enumeration, row bands for huge images and the JAX kernels. Imports torch, jax and the core modules
(`framework.types`, `geometry`, `guards`) only."""
