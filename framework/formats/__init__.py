"""Files an avatar is written to and read back from: the 3DGS PLY layout and the animatable NPZ package.

May import the core types, geometry and deformation math (framework.types, geometry, lbs, sh_rotation) and numpy /
plyfile; never lightning/ or the entry points (whoever holds a trained module hands its tensors down).
"""
