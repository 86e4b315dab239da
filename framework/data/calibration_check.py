"""Does a capture's calibration agree with its masks and body fits? Scores, diagnoses and overlay pictures.

For sampled frames, the posed body (stored vertices, or the body model posed by the parameters) is projected with
each camera as the dataset delivers it (undistorted, downscaled) and compared with that camera's mask:
- inside: the share of projected vertices that land inside the mask (vertices behind the camera or outside the image
  count as outside). A correct rig gives ~0.95-1.0 (masks also cover clothes and hair the body lacks).
- IoU: intersection over union of the projected mesh silhouette and the mask; ~0.6-0.9 for a correct rig (clothes),
  near 0 for a wrong camera. A mesh whose faces are unknown is splatted as discs as large as its vertex spacing.
A camera is flagged when its mean IoU or inside share is below the thresholds, or its IoU is far below the other
cameras'. Each flagged camera is then re-scored under the mistakes users make, and the one that fixes it is named:
- T in the wrong unit (millimetres for metres, or the reverse): T scaled by 1/1000 or 1000;
- extrinsics stored camera-to-world instead of world-to-camera (R, T swapped for their inverse), or R transposed;
- two cameras swapped, or a mis-ordered camera list: the camera's masks fit another camera's calibration.
Frames whose fit disagrees with every good camera are listed (a failed body fit), and single (camera, frame) outliers
(a bad mask, a dropped or unsynchronised frame).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np

NEAR = 1e-3  # metres: points closer to the camera plane are not projected
UNIT_FACTORS = (1e-3, 1e3)
SUPERSAMPLE = 4  # silhouettes of triangle meshes are drawn on a 4x finer grid
TOO_LARGE = "T in the wrong unit: millimetres where metres are expected (1000x too large)"
TOO_SMALL = "T in the wrong unit: metres where millimetres are expected (1000x too small)"


# ----------------------------------------------------------------------------------------------------------- scoring
@dataclass
class Geometry:
    """The posed body of one frame in world space: points [V, 3] (float64) and, when known, triangles [F, 3]."""

    points: np.ndarray
    faces: np.ndarray | None = None
    spacing: float = 0.0  # typical distance between neighbouring points (metres), for point splats

    def __post_init__(self) -> None:
        if self.faces is None and self.spacing <= 0 and len(self.points) > 1:
            from scipy.spatial import cKDTree

            step = max(1, len(self.points) // 20000)
            pts = self.points[::step]  # a surface sample: spacing grows as sqrt(step)
            d, _ = cKDTree(pts).query(pts, k=2)
            self.spacing = float(np.median(d[:, 1])) / np.sqrt(step)


def project(points: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[V, 3] world -> pixel coordinates [V, 2] in K's convention (centres at +0.5 for ours) and camera depth [V]."""
    p = points @ w2c[:3, :3].T + w2c[:3, 3]  # [V, 3]
    z = p[:, 2]
    q = p @ K.T
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = q[:, :2] / np.where(np.abs(q[:, 2:3]) > 1e-12, q[:, 2:3], 1e-12)
    return uv, z


def silhouette(geom: Geometry, uv: np.ndarray, z: np.ndarray, K: np.ndarray, height: int, width: int) -> np.ndarray:
    """bool [H, W]: the projected mesh (triangles in front of the camera), or discs around the projected points."""
    import cv2

    out = np.zeros((height, width), np.uint8)
    front = z > NEAR
    lim = 8.0 * max(height, width)  # keep far-off points from overflowing cv2's fixed-point coordinates
    pix = np.clip(uv - 0.5, -lim, lim)  # cv2's pixel centres are at integers
    if geom.faces is not None:
        # cv2 fills every pixel a polygon touches; on a 4x finer grid, area-averaged back, a pixel is in when its
        # centre is (to 1/8 pixel), so the IoU is not biased by a one-pixel rim
        tris = geom.faces[front[geom.faces].all(1)]
        if not len(tris):
            return out.astype(bool)
        fine = np.zeros((height * SUPERSAMPLE, width * SUPERSAMPLE), np.uint8)
        corners = (uv * SUPERSAMPLE).clip(-lim * SUPERSAMPLE, lim * SUPERSAMPLE) - 0.5
        cv2.fillPoly(fine, list(np.round(corners[tris] * 16).astype(np.int32)), 255, cv2.LINE_8, shift=4)
        return cv2.resize(fine, (width, height), interpolation=cv2.INTER_AREA) >= 128
    keep = front & (pix[:, 0] >= -0.5) & (pix[:, 0] < width - 0.5) & (pix[:, 1] >= -0.5) & (pix[:, 1] < height - 0.5)
    if not keep.any():
        return out.astype(bool)
    j, i = np.round(pix[keep]).astype(int).T
    out[np.clip(i, 0, height - 1), np.clip(j, 0, width - 1)] = 1
    radius = int(np.ceil(K[0, 0] * geom.spacing / max(float(np.median(z[keep])), NEAR)))
    radius = int(np.clip(radius, 1, max(height, width) // 8 + 1))
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.dilate(out, kernel).astype(bool)


def score(geom: Geometry, mask: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> tuple[float, float, np.ndarray]:
    """(inside share, IoU, silhouette) of `geom` seen by camera (K, w2c) against bool `mask` [H, W]."""
    H, W = mask.shape
    uv, z = project(geom.points, K, w2c)
    j, i = np.floor(uv[:, 0]), np.floor(uv[:, 1])
    ok = (z > NEAR) & (j >= 0) & (j < W) & (i >= 0) & (i < H)
    inside = float(mask[i[ok].astype(int), j[ok].astype(int)].sum()) / max(len(uv), 1)
    sil = silhouette(geom, uv, z, K, H, W)
    union = np.logical_or(sil, mask).sum()
    iou = float(np.logical_and(sil, mask).sum() / union) if union else float("nan")
    return inside, iou, sil


# ----------------------------------------------------------------------------------------------------------- report
@dataclass
class CameraRow:
    index: int
    name: str
    inside: float  # mean over the sampled frames
    iou: float
    frames: int
    verdict: str = "ok"
    worst_frame: int = -1


@dataclass
class CheckReport:
    rows: list[CameraRow]
    findings: list[str]
    frame_iou: dict[int, float]  # frame -> mean IoU over the cameras that look right
    scores: dict[tuple[int, int], tuple[float, float]] = field(default_factory=dict)  # (view, frame) -> inside, IoU

    @property
    def ok(self) -> bool:
        return not self.findings

    def markdown(self, frame_names: Callable[[int], str] = str) -> str:
        lines = ["| # | camera | frames | vertices inside mask | mask IoU | verdict |", "|---|---|---|---|---|---|"]
        for r in self.rows:
            lines.append(f"| {r.index} | {r.name} | {r.frames} | {r.inside:.1%} | {r.iou:.3f} | {r.verdict} |")
        lines.append("")
        if self.frame_iou:
            worst = sorted(self.frame_iou.items(), key=lambda kv: kv[1])[:3]
            lines.append(
                "Lowest frame IoU (good cameras): " + ", ".join(f"frame {frame_names(f)} {v:.3f}" for f, v in worst)
            )
            lines.append("")
        if self.findings:
            lines.append("Problems found:")
            lines += [f"- {f}" for f in self.findings]
        else:
            lines.append("No problems found: every camera's masks agree with the projected body.")
        return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------------- diagnosis
@dataclass
class Rig:
    """Cameras as the dataset delivers them: K [C, 3, 3] (ours), world_to_cam [C, 4, 4], names, image size."""

    K: np.ndarray
    w2c: np.ndarray
    names: list[str]
    height: int
    width: int


def _variants(w2c: np.ndarray) -> Iterable[tuple[str, np.ndarray]]:
    """The rig mistakes we test, each as (what it means, corrected world_to_cam)."""
    R, T = w2c[:3, :3], w2c[:3, 3]
    for s in UNIT_FACTORS:
        fixed = w2c.copy()
        fixed[:3, 3] = T * s
        yield TOO_LARGE if s < 1 else TOO_SMALL, fixed
    inv = np.eye(4)
    inv[:3, :3], inv[:3, 3] = R.T, -R.T @ T
    yield "R and T are camera-to-world (the inverse of world-to-camera)", inv
    tr = w2c.copy()
    tr[:3, :3] = R.T
    yield "R is transposed (or its Rodrigues vector has the wrong sign)", tr
    for s in UNIT_FACTORS:  # both mistakes at once
        both = inv.copy()
        both[:3, 3] = inv[:3, 3] * s
        yield f"R and T are camera-to-world and T is {1 / s:g}x off in scale", both


def diagnose(
    rig: Rig,
    frames: list[int],
    geometry: Callable[[int], Geometry],
    mask: Callable[[int, int], np.ndarray],
    scores: dict[tuple[int, int], tuple[float, float]],
    min_inside: float = 0.8,
    min_iou: float = 0.5,
    frame_name: Callable[[int], str] = str,
    probe_frames: int = 3,
) -> CheckReport:
    """Turn per-(view, frame) scores into verdicts; re-score flagged cameras under the usual mistakes."""
    C = len(rig.names)
    rows = []
    for c in range(C):
        ins = [scores[c, f][0] for f in frames]
        ious = [scores[c, f][1] for f in frames]
        iou = float(np.nanmean(ious)) if np.isfinite(ious).any() else 0.0
        worst = frames[int(np.nanargmin(ious))] if np.isfinite(ious).any() else frames[0]
        rows.append(CameraRow(c, rig.names[c], float(np.mean(ins)), iou, len(frames), worst_frame=worst))
    median_iou = float(np.median([r.iou for r in rows]))
    bad = [r.index for r in rows if r.iou < min_iou or r.inside < min_inside]
    low = [r.index for r in rows if r.index not in bad and r.iou < median_iou - 0.25]
    flagged = bad + low
    probe = frames[:: max(1, len(frames) // probe_frames)][:probe_frames]

    def rescore(c: int, K: np.ndarray, w2c: np.ndarray) -> float:
        return float(np.nanmean([score(geometry(f), mask(c, f), K, w2c)[1] for f in probe]))

    findings: list[str] = []
    # ---- the whole rig in the wrong unit (every camera far away): say it once
    centres = np.array([-(w[:3, :3].T @ w[:3, 3]) for w in rig.w2c])
    subject = np.median(np.concatenate([geometry(f).points for f in probe]), axis=0)
    distance = float(np.median(np.linalg.norm(centres - subject, axis=1)))
    fixes: dict[int, str] = {}
    for c in flagged:
        best, best_iou = None, rows[c].iou
        for what, w2c in _variants(rig.w2c[c]):
            v = rescore(c, rig.K[c], w2c)
            if v >= max(min_iou, best_iou + 0.15):
                best, best_iou = what, v
        if best is not None:
            fixes[c] = f"{best} (IoU {rows[c].iou:.2f} -> {best_iou:.2f} when corrected)"
    unit_cams: list[int] = []
    for marker, verdict, how in (
        (
            TOO_LARGE,
            "T in millimetres",
            "T is in millimetres where metres are expected ({n} of {C} cameras, {d:.0f} "
            "units from the subject; a studio is a few metres across): divide every T by 1000 (EasyMocap's extri.yml "
            "stores metres)",
        ),
        (
            TOO_SMALL,
            "T in metres",
            "T is in metres where millimetres are expected ({n} of {C} cameras, {d:.4f} units "
            "from the subject): multiply every T by 1000 (ZJU-MoCap's annots.npy stores millimetres)",
        ),
    ):
        cams = [c for c, f in fixes.items() if f.startswith(marker)]
        if cams and len(cams) >= max(2, len(bad) // 2):  # the whole rig in the wrong unit: say it once
            findings.append(how.format(n=len(cams), C=C, d=distance))
            for c in cams:
                rows[c].verdict = verdict
            unit_cams += cams
    # ---- swapped or mis-ordered cameras: whose calibration do this camera's masks fit?
    remaining = [c for c in flagged if c not in fixes]
    fits: dict[int, tuple[int, float]] = {}
    # a swap or a mis-ordered list leaves most cameras right; when most are wrong, the search is skipped (it costs
    # C - 1 projections per camera)
    for c in remaining if len(remaining) <= C // 2 else []:
        cands = [(rescore(c, rig.K[d], rig.w2c[d]), d) for d in range(C) if d != c]
        v, d = max(cands)
        if v >= max(min_iou, rows[c].iou + 0.15):
            fits[c] = (d, v)
    seen: set[int] = set()
    for c, (d, v) in fits.items():
        if c in seen:
            continue
        n_c, n_d = rig.names[c], rig.names[d]
        if fits.get(d, (None,))[0] == c:
            seen |= {c, d}
            findings.append(
                f"cameras {n_c} and {n_d} are swapped: the masks of {n_c} fit the calibration of {n_d} (IoU "
                f"{v:.2f}) and the reverse (IoU {fits[d][1]:.2f}); exchange their calibration entries (K, dist, R, T) "
                f"or their image folders"
            )
            rows[c].verdict, rows[d].verdict = f"swapped with {n_d}", f"swapped with {n_c}"
        else:
            seen.add(c)
            chain = _cycle(c, fits)
            how = " -> ".join(rig.names[x] for x in chain)
            findings.append(
                f"camera {n_c}: its masks fit the calibration of camera {n_d} (IoU {v:.2f}, {rows[c].iou:.2f} with "
                f"its own){f'; the camera list is mis-ordered along {how}' if len(chain) > 2 else ''}: the names in "
                f"the calibration do not match the image folders"
            )
            rows[c].verdict = f"fits the calibration of {n_d}"
    for c, fix in fixes.items():
        if c in unit_cams:
            continue
        findings.append(f"camera {rig.names[c]}: {fix}")
        rows[c].verdict = fix.split(" (")[0]
    for c in bad:
        if rows[c].verdict == "ok":
            r = rows[c]
            why = (
                "its masks are much larger than the body (segmentation keeps background?)"
                if r.inside >= min_inside
                else "no simple mistake explains it (check K and dist, or re-calibrate this camera)"
            )
            findings.append(f"camera {r.name}: mask IoU {r.iou:.2f}, {r.inside:.0%} of vertices inside: {why}")
            r.verdict = "BAD"
    for c in low:
        if rows[c].verdict != "ok":
            continue
        rows[c].verdict = "low IoU"
        findings.append(
            f"camera {rig.names[c]}: mask IoU {rows[c].iou:.2f} is well below the other cameras' (median "
            f"{median_iou:.2f}); look at its overlay (a slightly wrong K, dist or pose of this camera?)"
        )
    # ---- frames: every good camera disagrees -> the body fit of that frame; single outliers
    good = [c for c in range(C) if rows[c].verdict == "ok"]
    frame_iou = {f: float(np.nanmean([scores[c, f][1] for c in good])) for f in frames} if good else {}
    bad_frames = [f for f, v in frame_iou.items() if not v >= min_iou]
    if bad_frames:
        listed = ", ".join(f"{frame_name(f)} (IoU {frame_iou[f]:.2f})" for f in bad_frames[:8])
        findings.append(
            f"{len(bad_frames)} frame(s) disagree with every good camera: {listed}; the body fit of those frames "
            f"failed: re-fit them or leave them out of train_frames"
        )
    outliers = [(c, f) for c in good for f in frames if f not in bad_frames and not scores[c, f][1] >= min_iou]
    if outliers:
        listed = ", ".join(
            f"camera {rig.names[c]} frame {frame_name(f)} (IoU {scores[c, f][1]:.2f})" for c, f in outliers[:8]
        )
        findings.append(
            f"{len(outliers)} single image(s) disagree while the same frame fits the other cameras: {listed}; a "
            f"bad mask, or a camera that is not synchronised"
        )
    return CheckReport(rows, findings, frame_iou, scores)


def _cycle(start: int, fits: dict[int, tuple[int, float]]) -> list[int]:
    """The chain start -> fits[start] -> ... until it repeats or leaves the fitted cameras."""
    chain = [start]
    while chain[-1] in fits and fits[chain[-1]][0] not in chain:
        chain.append(fits[chain[-1]][0])
    if chain[-1] in fits:
        chain.append(fits[chain[-1]][0])
    return chain
