"""Splatting math with no state, in torch (and JAX): camera projection of Gaussians, the SH colour basis, the (Gaussian,
pixel) pair enumeration, row bands for huge images and the JAX kernels (the compiled CPU twins are in
`framework.kernels`). Imports torch, jax and the core modules (`framework.types`, `geometry`, `guards`) only."""
