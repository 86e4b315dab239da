"""Appearance of the synthetic subject: clothing albedo with fine detail, plus pose-dependent wrinkle shading.

Why a 3D (solid) texture: the albedo is evaluated at the hit point's REST-pose position (barycentrics of the posed hit
applied to the rest vertices), so it follows the surface under any pose, needs no UVs, and has no seams. Garments
are assigned per face from the dominant skinning joint (shirt on torso and arms, trousers on pelvis and legs, shoes,
skin on hands, neck and face, hair on the top and back of the head).

Detail a model must capture (periods at 512 px, subject ~1.7 m ~ 430 px): shirt stripes of 4 cm (~10 px) with a
small dot print (2.5 cm grid), a darker seam line down the sides and around the shoulders; trousers with a fine
twill (1.5 cm) and side seams; shoes with laces.

Pose-dependent appearance (what a pose-conditioned model can learn and an average-appearance model cannot):
- wrinkles: near each flexing joint (elbows, knees, hips, shoulders) a band pattern darkens the cloth, scaled by the
  joint's rotation angle: m = 1 - strength * clip(angle / 1.4, 0, 1) * exp(-d^2 / 2 sigma^2) * (0.5 + 0.5 sin(...)),
  d the rest-pose distance to the joint; `wrinkle_multiplier` gives m per vertex for a pose. A broad fold shade
  (sigma 12 cm, up to 35% darker at full flexion) goes with it, so the effect survives at low resolutions.
- cast self-shadows from a fixed studio light, done by the renderer's shadow rays (`raycast.Shading(shadows=True)`).
"""

from __future__ import annotations

import numpy as np

from framework.data.motions import FLEX_JOINTS, Rig

SKIN, SHIRT, TROUSERS, SHOES, HAIR = range(5)
BROAD_SIGMA = 0.12  # m: reach of the broad fold shading around a flexed joint
BROAD_STRENGTH = 0.35  # darkening at full flexion

_SKIN_JOINTS = ("wrist", "hand", "neck", "head", "finger", "metacarpal", "eye", "jaw", "tongue", "ear")
_LEG_JOINTS = ("upperleg", "lowerleg", "pelvis", "root")
_FOOT_JOINTS = ("foot", "toe")


def _joint_region(name: str) -> int:
    n = name.lower()
    if any(k in n for k in _FOOT_JOINTS):
        return SHOES
    if any(k in n for k in _SKIN_JOINTS):
        return SKIN
    if any(k in n for k in _LEG_JOINTS):
        return TROUSERS
    return SHIRT


class Appearance:
    """Per-body appearance: garment regions per face and the albedo / wrinkle functions."""

    def __init__(
        self,
        rest_vertices: np.ndarray,
        faces: np.ndarray,
        skin_weights: np.ndarray,
        rig: Rig,
        seed: int = 0,
        wrinkle_strength: float = 0.55,
        broad_strength: float = BROAD_STRENGTH,
    ) -> None:
        self.rest = np.asarray(rest_vertices, dtype=np.float64)  # [V, 3]
        self.faces = np.asarray(faces, dtype=np.int64)  # [F, 3]
        W = np.asarray(skin_weights, dtype=np.float64)  # [V, J]
        self.rig = rig
        face_w = W[self.faces].sum(1)  # [F, J]
        dom = face_w.argmax(1)
        joint_region = np.array([_joint_region(n) for n in rig.joint_names])
        self.region = joint_region[dom]  # [F]
        # hair: top and back of the head
        if "head" in rig.index:
            hj = rig.rest_joints[rig.index["head"]]
            c = self.rest[self.faces].mean(1)
            hair = (self.region == SKIN) & (dom == rig.index["head"])
            hair &= (c[:, 2] > hj[2] + 0.1) | ((c[:, 1] > hj[1] + 0.02) & (c[:, 2] > hj[2] + 0.02))
            self.region[hair] = HAIR
        rng = np.random.default_rng(seed)
        shirts = np.array([[0.75, 0.15, 0.15], [0.15, 0.35, 0.7], [0.2, 0.55, 0.3], [0.85, 0.6, 0.15]])
        self.shirt_a = shirts[rng.integers(len(shirts))]
        self.shirt_b = np.array([0.92, 0.9, 0.85])
        self.trousers = np.array([0.18, 0.22, 0.38]) * rng.uniform(0.9, 1.1)
        self.skin = np.array([0.85, 0.66, 0.52]) * rng.uniform(0.92, 1.05)
        self.wrinkle_strength = wrinkle_strength
        self.broad_strength = broad_strength
        self.z0 = self.rest[:, 2].min()
        self._flex = [(s, rig.index[s]) for s in FLEX_JOINTS if s in rig.index]

    # ---------------------------------------------------------------------------------------------- albedo
    def albedo(self, face_ids: np.ndarray, rest_points: np.ndarray) -> np.ndarray:
        """[N] face ids, [N, 3] rest-pose surface points -> [N, 3] albedo in [0, 1]."""
        p = rest_points.astype(np.float64)
        x, y, z = p[:, 0], p[:, 1], p[:, 2] - self.z0
        reg = self.region[face_ids]
        out = np.empty((len(p), 3))
        # shirt: 4 cm stripes, 2.5 cm dot print on the light stripes, side/shoulder seams
        stripe = 0.5 + 0.5 * np.tanh(6.0 * np.sin(2 * np.pi * z / 0.04))
        gx, gz = (x / 0.025) % 1.0 - 0.5, (z / 0.025 + 0.5 * (np.floor(x / 0.025) % 2)) % 1.0 - 0.5
        dots = (gx**2 + gz**2) < 0.2**2
        shirt = self.shirt_a * stripe[:, None] + self.shirt_b * (1 - stripe[:, None])
        shirt = np.where((dots & (stripe < 0.5))[:, None], self.shirt_a * 0.6, shirt)
        seam = np.abs(y - 0.0) < 0.006  # side seam where the front meets the back (facing -y: y ~ 0 at the sides)
        shirt = np.where(seam[:, None], shirt * 0.45, shirt)
        # trousers: fine twill and side seams
        twill = 0.85 + 0.15 * np.sin(2 * np.pi * (z + x + y) / 0.015)
        trousers = self.trousers * twill[:, None]
        trousers = np.where(seam[:, None], np.array([0.75, 0.6, 0.3]), trousers)
        # shoes: dark with white laces across the front
        laces = (y < -0.05) & (np.sin(2 * np.pi * z / 0.012) > 0.6)
        shoes = np.where(laces[:, None], np.array([0.9, 0.9, 0.9]), np.array([0.12, 0.1, 0.1]))
        hair = np.array([0.22, 0.14, 0.08]) * (0.85 + 0.15 * np.sin(2 * np.pi * (x * 3 + z) / 0.01))[:, None]
        out[:] = self.skin
        for r, val in ((SHIRT, shirt), (TROUSERS, trousers), (SHOES, shoes), (HAIR, hair)):
            sel = reg == r
            out[sel] = val[sel]
        return np.clip(out, 0, 1).astype(np.float32)

    # ---------------------------------------------------------------------------------------------- wrinkles
    def wrinkle_multiplier(self, pose: np.ndarray) -> np.ndarray:
        """[J, 3] axis-angle pose -> [V] shading multipliers in (0, 1] (1 = no wrinkle)."""
        pose = np.asarray(pose, dtype=np.float64)
        m = np.ones(len(self.rest))
        for sem, j in self._flex:
            angle = float(np.linalg.norm(pose[j]))
            if angle < 1e-3:
                continue
            center = self.rig.rest_joints[j]
            d = self.rest - center  # [V, 3]
            axis = self.rig.bone_dir(sem)
            along = d @ axis  # distance along the bone
            radial = d - along[:, None] * axis
            # folds: bands across the bone, slanted around the limb so they read as creases
            ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            e1 = np.cross(axis, ref)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(axis, e1)
            az = np.arctan2(radial @ e1, radial @ e2)
            band = 0.5 + 0.5 * np.sin(2 * np.pi * along / 0.022 + 1.5 * np.sin(az))
            sigma = 0.07
            fall = np.exp(-(d**2).sum(1) / (2 * sigma**2))
            flex = min(angle / 1.4, 1.0)
            m *= 1.0 - self.wrinkle_strength * flex * fall * band
            # the bunched cloth around a bent joint also shades broadly (visible at CPU resolutions, where the
            # 2.2 cm bands are finer than a pixel and average out)
            broad = np.exp(-(d**2).sum(1) / (2 * BROAD_SIGMA**2))
            m *= 1.0 - self.broad_strength * flex * broad
        return m.astype(np.float32)
