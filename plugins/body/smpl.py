"""`smpl`: SMPL (or SMPL-X through `model_type: smplx`) loaded through `smplx` from a model file the user supplies.

The loading, shaping and posing live in `framework.bodies.smpl_family` (shared with `body=smplx`, which adds SMPL-X's
joint names and the choice of F_a's pose-input joints); see its docstring for the conventions.
"""

from __future__ import annotations

from framework.bodies.model_files import expected_filename, resolve_model_file, smplx_requirement
from framework.bodies.smpl_family import SMPL_JOINT_NAMES, SmplFamilyBody
from framework.registry import register

__all__ = ["SMPLBody", "SMPL_JOINT_NAMES", "expected_filename", "resolve_model_file"]


@register("body", "smpl", requires=smplx_requirement)
class SMPLBody(SmplFamilyBody):
    """SMPL (24 joints) or SMPL-X (55 joints) with fixed shape `betas`; every joint enters F_a's pose input."""
