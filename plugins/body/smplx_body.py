"""`smplx`: SMPL-X (55 joints: 22 body, jaw, two eyes, 15 per hand) through `smplx`, from a model file you supply.

Loading, shaping and posing are shared with `body=smpl` (`framework.bodies.smpl_family`): the file comes from
https://smpl-x.is.tue.mpg.de (`SMPLX_NEUTRAL.npz` / `.pkl`, or the MALE / FEMALE files; use the gender your poses
were fitted with: EasyMocap's SMPL-X example fits `--gender male`), poses are absolute rotations (flat hand mean), and
the body's shape is fixed by `betas` (null: the capture's fitted shapes, see `framework.lightning.module`).

F_a's pose input (`pose_input`): every joint is posed and skinned, but by default only the 22 body joints (pelvis to
wrists, SMPL's joints without its two hand stubs) enter the appearance corrector, 66 values instead of 165:
- fingers and eyes are small in the image and move the clothing not at all; EasyMocap fits each hand with 6 PCA
  coefficients from 2D keypoints, so finger rotations are the noisiest part of the pose;
- an MLP fed 99 values that carry no appearance signal can only fit them per frame, which hurts novel poses.
`pose_input: all` feeds all 55 joints; a list of joint names (e.g. the body joints plus `jaw`) picks them yourself.
"""

from __future__ import annotations

from framework.bodies.model_files import smplx_requirement
from framework.bodies.smpl_family import SmplFamilyBody
from framework.registry import register

NUM_SMPLX_JOINTS = 55
BODY_JOINTS = 22  # pelvis .. right_wrist: the joints SMPL and SMPL-X share


def smplx_joint_names() -> list[str]:
    """The 55 skeleton joints in SMPL-X's order (smplx's own list; it goes on with landmarks we do not use)."""
    from smplx.joint_names import JOINT_NAMES

    return list(JOINT_NAMES[:NUM_SMPLX_JOINTS])


def pose_input_indices(pose_input: str | list[str], joint_names: list[str]) -> list[int] | None:
    """Joint indices for `pose_input` ("body", "all" or joint names); None means every joint."""
    if isinstance(pose_input, str):
        if pose_input == "body":
            return list(range(BODY_JOINTS))
        if pose_input == "all":
            return None
        raise ValueError(f"smplx body: pose_input must be 'body', 'all' or a list of joint names; got {pose_input!r}.")
    unknown = [n for n in pose_input if n not in joint_names]
    if unknown or not pose_input:
        raise ValueError(
            f"smplx body: pose_input lists unknown joint(s) {unknown or '(none given)'}; SMPL-X joints are "
            f"{', '.join(joint_names[:25])}, left_index1 .. right_thumb3."
        )
    return [joint_names.index(n) for n in pose_input]


@register("body", "smplx", requires=smplx_requirement)
class SMPLXBody(SmplFamilyBody):
    """SMPL-X with fixed shape `betas`; `pose_input` chooses the joints F_a sees (see the module docstring)."""

    def __init__(
        self,
        model_path: str | None = None,
        gender: str = "neutral",
        betas: list[float] | None = None,
        num_betas: int = 10,
        pose_blendshapes: bool = False,
        pose_input: str | list[str] = "body",
    ) -> None:
        super().__init__(
            model_path=model_path,
            model_type="smplx",
            gender=gender,
            betas=betas,
            num_betas=num_betas,
            pose_blendshapes=pose_blendshapes,
        )
        if self.num_joints != NUM_SMPLX_JOINTS:
            raise ValueError(
                f"smplx body: {self.model_file} has {self.num_joints} joints, expected SMPL-X's {NUM_SMPLX_JOINTS}; "
                f"is it an SMPL-X file?"
            )
        self.joint_names = smplx_joint_names()
        self.pose_input_joints = pose_input_indices(
            list(pose_input) if not isinstance(pose_input, str) else pose_input, self.joint_names
        )
