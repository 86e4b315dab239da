"""Rig math with no learnable state: forward kinematics, linear blend skinning, polar decomposition, SH rotation, the
blend-weight field and closest points on a mesh. Imports the core modules and `framework.splat` (the SH basis) only."""
