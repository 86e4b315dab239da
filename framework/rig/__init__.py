"""Rig math with no learnable state, in torch: forward kinematics, linear blend skinning, polar decomposition, SH
rotation, the blend-weight field and closest points on a mesh (their compiled twins are in `framework.kernels`).
Imports the core modules and `framework.splat` (the SH basis) only."""
