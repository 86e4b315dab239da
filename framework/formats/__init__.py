"""Files an avatar is written to and read back from: the 3DGS PLY layout and the animatable NPZ package.

May import the core (types, geometry, errors), the rig math (framework.rig: LBS, SH rotation) and numpy / plyfile;
never lightning/, model/ or the entry points (whoever holds a trained module hands its tensors down).
"""
