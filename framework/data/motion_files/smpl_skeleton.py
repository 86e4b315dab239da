"""The SMPL skeleton (shared by SMPL, SMPL-H and SMPL-X for its first 22 joints) without the licensed model file.

Joint names (framework.bodies.smpl_family) and parents are SMPL's kinematic tree. `SCHEMATIC_REST` is a hand-made
T-pose in SMPL's canonical frame (metres; Y up, the subject facing +Z, its left on +X), used only for bone directions
when retargeting AMASS files onto a body that is not SMPL; an SMPL avatar uses its own rest joints instead.
"""

from __future__ import annotations

import numpy as np

from framework.bodies.smpl_family import SMPL_JOINT_NAMES

SMPL_PARENTS = np.array([-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21])
BODY_JOINTS = 22  # joints 0..21 are the same in SMPL, SMPL-H and SMPL-X (then hands / fingers / face)

_LEFT_HALF = {  # (x, y, z) of the subject's left-side joints; the right side mirrors x
    "hip": (0.06, -0.09, 0.0),
    "knee": (0.10, -0.47, 0.0),
    "ankle": (0.09, -0.87, -0.04),
    "foot": (0.12, -0.92, 0.08),
    "collar": (0.07, 0.42, -0.01),
    "shoulder": (0.17, 0.45, -0.02),
    "elbow": (0.43, 0.44, -0.04),
    "wrist": (0.69, 0.44, -0.04),
    "hand": (0.77, 0.44, -0.05),
}
_MIDDLE = {
    "pelvis": (0.0, 0.0, 0.0),
    "spine1": (0.0, 0.11, -0.01),
    "spine2": (0.0, 0.24, 0.0),
    "spine3": (0.0, 0.30, 0.01),
    "neck": (0.0, 0.51, -0.03),
    "head": (0.0, 0.58, 0.02),
}


def _schematic() -> np.ndarray:
    out = []
    for name in SMPL_JOINT_NAMES:
        if name in _MIDDLE:
            out.append(_MIDDLE[name])
        else:
            side, part = name.split("_", 1)
            x, y, z = _LEFT_HALF[part]
            out.append((x if side == "left" else -x, y, z))
    return np.asarray(out, dtype=np.float64)


SCHEMATIC_REST = _schematic()  # [24, 3]
