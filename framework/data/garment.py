"""A loose garment for the synthetic studio: a skirt whose motion is not the body's skinning.

Why: a body model's skinning moves a point with the nearest body surface, so weights taken from the body (our
initialisation, as the paper's) are wrong for loose clothing. The skirt's hem sits around the thighs but moves with
the pelvis, late and with a swing, so it gives the blend-weight residual F_dw and the pose corrector something to fix.

Geometry (rest pose, body frame): an elliptic cone around the pelvis, from a waist ring `waist_above` m above the
pelvis joint down `length` m; each ring's radii cover the torso and leg vertices at its height (arms excluded) plus
`margin`, never shrink downwards, and widen by `flare` at the hem. `drop` [V] is 0 at the waist and 1 at the hem.

Motion, per frame f, from the pelvis's world transform M_f (root transform times the pelvis skinning transform):
- the waist ring follows M_f exactly; lower rings follow a lagged copy S_f (exponential smoothing of M_f with factor
  `lag` per frame: translation lerp, rotation normalised-quaternion lerp) more and more: x_f = (1 - u) M_f x + u S_f x
  with u = drop;
- the hem swings like a damped pendulum about the waist centre: a tilt phi_f (axis-angle, horizontal axis) driven by
  the waist centre's horizontal acceleration (the hem trails it), phi_{f+1} = phi_f + v_{f+1},
  v_{f+1} = (1 - damping) v_f - stiffness phi_f - gain (z x a_f); each vertex turns by u * phi_f about the waist.
Time is in frames: the motion depends on how densely the sequence samples the clips, as the poses do.
There are no collisions: a leg kicked forward may pass through the skirt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_ARM_WORDS = ("arm", "wrist", "hand", "clavicle", "shoulder", "finger", "metacarpal", "thumb")


@dataclass
class Skirt:
    rest: np.ndarray  # [V, 3] rest-pose positions in the body frame
    faces: np.ndarray  # [F, 3]
    drop: np.ndarray  # [V] 0 at the waist ... 1 at the hem

    @property
    def num_vertices(self) -> int:
        return len(self.rest)


def build_skirt(
    rest_vertices: np.ndarray,
    skin_weights: np.ndarray,
    joint_names: list[str],
    pelvis: np.ndarray,
    rings: int = 10,
    segments: int = 48,
    length: float = 0.42,
    waist_above: float = 0.06,
    margin: float = 0.02,
    flare: float = 1.25,
) -> Skirt:
    """The rest-pose skirt around a body (see the module docstring)."""
    rest = np.asarray(rest_vertices, dtype=np.float64)
    arm_joint = np.array([any(w in n.lower() for w in _ARM_WORDS) for n in joint_names])
    pts = rest[~arm_joint[np.asarray(skin_weights).argmax(1)]]  # torso, pelvis and legs
    top = float(pelvis[2]) + waist_above
    zs = top - length * np.linspace(0.0, 1.0, rings)
    band = pts[np.abs(pts[:, 2] - top) < 0.04]
    centre = band[:, :2].mean(0) if len(band) else np.asarray(pelvis[:2], dtype=np.float64)
    radii = np.zeros((rings, 2))
    for k, z in enumerate(zs):
        slab = pts[np.abs(pts[:, 2] - z) < 0.04]
        extent = np.abs(slab[:, :2] - centre).max(0) if len(slab) else np.array([0.1, 0.1])
        radii[k] = extent + margin
    radii = np.maximum.accumulate(radii, axis=0)  # never narrower below
    u = np.linspace(0.0, 1.0, rings)
    radii *= (1.0 + (flare - 1.0) * u)[:, None]
    theta = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_xy = np.stack([np.cos(theta), np.sin(theta)], -1)  # [S, 2]
    verts = np.concatenate(
        [np.column_stack([centre + ring_xy * radii[k], np.full(segments, zs[k])]) for k in range(rings)]
    )  # [rings * S, 3]
    k, s = np.meshgrid(np.arange(rings - 1), np.arange(segments), indexing="ij")
    a = (k * segments + s).ravel()
    b = (k * segments + (s + 1) % segments).ravel()
    c, d = a + segments, b + segments
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)]).astype(np.int64)
    return Skirt(rest=verts, faces=faces, drop=np.repeat(u, segments))


def _quat_of(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()  # [..., 4] xyzw


def _rot_of(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(q).as_matrix()


def lagged_transforms(M: np.ndarray, lag: float) -> np.ndarray:
    """[F, 4, 4] rigid transforms -> their smoothed copy S: S_0 = M_0, S_f = lerp(S_{f-1}, M_f, 1 - lag)."""
    if not 0.0 <= lag < 1.0:
        raise ValueError(f"garment: lag must be in [0, 1), got {lag}.")
    S = np.array(M, dtype=np.float64, copy=True)
    q_prev = _quat_of(S[0, :3, :3])
    for f in range(1, len(M)):
        q = _quat_of(M[f, :3, :3])
        if np.dot(q, q_prev) < 0:
            q = -q
        q_new = lag * q_prev + (1 - lag) * q
        q_new /= np.linalg.norm(q_new)
        S[f, :3, :3] = _rot_of(q_new)
        S[f, :3, 3] = lag * S[f - 1, :3, 3] + (1 - lag) * M[f, :3, 3]
        q_prev = q_new
    return S


def pendulum_tilts(
    waist: np.ndarray, stiffness: float = 0.15, damping: float = 0.25, gain: float = 8.0, limit: float = 0.6
) -> np.ndarray:
    """Waist centre positions [F, 3] (world) -> hem tilts [F, 3] (axis-angle about horizontal axes, |phi| <= limit)."""
    F = len(waist)
    acc = np.zeros((F, 3))
    if F >= 3:
        acc[1:-1] = waist[2:] - 2 * waist[1:-1] + waist[:-2]
    acc[:, 2] = 0.0
    drive = np.cross(np.array([0.0, 0.0, 1.0]), acc)  # tilting about z x a moves the hem against a
    phi = np.zeros((F, 3))
    v = np.zeros(3)
    for f in range(F - 1):
        v = (1 - damping) * v - stiffness * phi[f] - gain * drive[f]
        phi[f + 1] = phi[f] + v
        n = np.linalg.norm(phi[f + 1])
        if n > limit:
            phi[f + 1] *= limit / n
    return phi


def skirt_motion(skirt: Skirt, pelvis_world: np.ndarray, lag: float = 0.5, swing: float = 1.0) -> np.ndarray:
    """Posed skirt vertices [F, V, 3] (world) for the pelvis's world transforms [F, 4, 4] (see the module docstring).
    `swing` scales the pendulum's drive (0: no swing)."""
    from framework.data.motions import axis_angle_to_matrix

    M = np.asarray(pelvis_world, dtype=np.float64)
    S = lagged_transforms(M, lag)
    x = np.concatenate([skirt.rest, np.ones((skirt.num_vertices, 1))], 1)  # [V, 4]
    follow = np.einsum("fij,vj->fvi", M[:, :3], x)  # [F, V, 3]
    lagged = np.einsum("fij,vj->fvi", S[:, :3], x)
    u = skirt.drop[None, :, None]
    posed = (1 - u) * follow + u * lagged
    top = skirt.drop == 0
    waist = follow[:, top].mean(1)  # [F, 3]
    phi = pendulum_tilts(waist, gain=8.0 * swing)
    R = axis_angle_to_matrix(phi[:, None] * skirt.drop[None, :, None])  # [F, V, 3, 3]
    return waist[:, None] + np.einsum("fvij,fvj->fvi", R, posed - waist[:, None])


def skirt_albedo(rest_points: np.ndarray) -> np.ndarray:
    """[N, 3] rest-pose points on the skirt -> [N, 3] albedo: a tartan of 5 cm checks with 1 cm pin stripes."""
    p = np.asarray(rest_points, dtype=np.float64)
    u = np.arctan2(p[:, 1], p[:, 0]) * 0.2  # ~arc length around the skirt (m)
    a = (np.floor(u / 0.05) + np.floor(p[:, 2] / 0.05)) % 2
    base = np.where(a[:, None] > 0, [0.12, 0.32, 0.22], [0.08, 0.16, 0.34])
    stripe = (np.abs((u / 0.05) % 1.0 - 0.5) < 0.1) | (np.abs((p[:, 2] / 0.05) % 1.0 - 0.5) < 0.1)
    return np.where(stripe[:, None], np.array([0.85, 0.75, 0.25]), base).astype(np.float32)
