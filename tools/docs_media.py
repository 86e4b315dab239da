"""Pictures for the README from a trained avatar: the viewer in a browser and frames of a BVH-driven video.

    python tools/docs_media.py --ckpt <run>/checkpoints/final.ckpt [--camera-index 0]

1. Writes docs/motions/jumping_jacks.bvh: two procedural jumping jacks made with bvhio (CMU joint names, Y up,
   centimetres, 60 fps), so the pictures need no downloaded motion.
2. Renders it with `python -m framework.render` (retargeted onto the avatar, resampled to 25 fps, one dataset camera)
   and writes four frames side by side to docs/images/bvh_jumping_jacks.png.
3. Opens `python -m framework.view` in headless Chromium and writes docs/images/viewer.png (as opened) and
   docs/images/viewer_posed.png (the left shoulder raised with its slider, the held-out motion selected).
Needs Chromium (Debian: apt-get install chromium).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

# (name, parent, offset in cm): a CMU-style T-pose skeleton facing +Z
SKELETON = [
    ("Hips", None, (0, 95, 0)),
    ("Spine", "Hips", (0, 10, 0)),
    ("Spine1", "Spine", (0, 22, 0)),
    ("Neck", "Spine1", (0, 22, 0)),
    ("Head", "Neck", (0, 10, 0)),
    ("LeftShoulder", "Spine1", (4, 17, 0)),
    ("LeftArm", "LeftShoulder", (14, 0, 0)),
    ("LeftForeArm", "LeftArm", (28, 0, 0)),
    ("LeftHand", "LeftForeArm", (24, 0, 0)),
    ("RightShoulder", "Spine1", (-4, 17, 0)),
    ("RightArm", "RightShoulder", (-14, 0, 0)),
    ("RightForeArm", "RightArm", (-28, 0, 0)),
    ("RightHand", "RightForeArm", (-24, 0, 0)),
    ("LeftUpLeg", "Hips", (9, -6, 0)),
    ("LeftLeg", "LeftUpLeg", (0, -42, 0)),
    ("LeftFoot", "LeftLeg", (0, -42, 0)),
    ("RightUpLeg", "Hips", (-9, -6, 0)),
    ("RightLeg", "RightUpLeg", (0, -42, 0)),
    ("RightFoot", "RightLeg", (0, -42, 0)),
]


def jumping_jacks(path: Path, fps: int = 60, seconds: float = 2.0) -> Path:
    """Arms from down (-70 deg) to overhead (+80 deg) about the forward axis, legs apart, a small hop; 1 s a jump."""
    import glm
    from bvhio import BvhContainer, BvhJoint, writeBvh
    from scipy.spatial.transform import Rotation
    from SpatialTransform import Pose

    n = int(round(fps * seconds))
    t = np.arange(n) / fps
    s = 0.5 * (1 - np.cos(2 * np.pi * t))  # 0 -> 1 -> 0 each second
    angles = {  # joint -> [n] degrees about Z (the BVH's forward axis)
        "LeftArm": -70 + 150 * s,
        "RightArm": 70 - 150 * s,
        "LeftForeArm": 15 * s,
        "RightForeArm": -15 * s,
        "LeftUpLeg": 14 * s,
        "RightUpLeg": -14 * s,
        "LeftFoot": -14 * s,
        "RightFoot": 14 * s,
    }
    joints = {}
    for name, parent, offset in SKELETON:
        joint = BvhJoint(name, glm.vec3(*offset))
        joint.Channels = (["Xposition", "Yposition", "Zposition"] if parent is None else []) + [
            "Zrotation",
            "Xrotation",
            "Yrotation",
        ]
        if not any(p == name for _, p, _ in SKELETON):
            joint.EndSite = glm.vec3(0, 8, 0) if name == "Head" else glm.vec3(*offset) * 0.3
        for i in range(n):
            w, x, y, z = Rotation.from_euler("z", angles.get(name, np.zeros(n))[i], degrees=True).as_quat(
                scalar_first=True
            )
            position = glm.vec3(0, 95 + 6 * np.sin(np.pi * s[i]) ** 2, 0) if parent is None else glm.vec3(*offset)
            joint.Keyframes.append(Pose(position, glm.quat(w, x, y, z)))
        joints[name] = joint
        if parent is not None:
            joints[parent].Children.append(joint)
    path.parent.mkdir(parents=True, exist_ok=True)
    writeBvh(str(path), BvhContainer(joints["Hips"], n, 1.0 / fps), percision=4)
    return path


def render_strip(ckpt: Path, bvh: Path, out: Path, camera_index: int) -> Path:
    import imageio.v3 as iio

    with tempfile.TemporaryDirectory() as tmp:
        cmd = [
            sys.executable,
            "-m",
            "framework.render",
            f"ckpt={ckpt}",
            f"motion={bvh}",
            "cameras=fixed",
            f"camera_index={camera_index}",
            "resolution=256",
            "fps=25",
            f"out_dir={tmp}",
        ]
        subprocess.run(cmd, check=True, cwd=ROOT)
        frames = sorted(Path(tmp, "frames").glob("*.png"))
        picks = [frames[i] for i in (0, 6, 12, 19)]  # 0, 0.24, 0.48, 0.76 s: the first jump at 25 fps
        strip = np.concatenate([iio.imread(p)[:, 32:-32] for p in picks], axis=1)
        iio.imwrite(out, strip)
    return out


def viewer_screenshots(ckpt: Path, out_dir: Path) -> list[Path]:
    from framework.testing.browser import HeadlessChromium
    from framework.testing.viewer import CLOSE_NOTIFICATIONS, FRAMES_SERVED, SLIDER, running_viewer, settled_screenshot

    paths = [out_dir / "viewer.png", out_dir / "viewer_posed.png"]
    with running_viewer(ckpt, "resolution=512", cwd=ROOT) as url, HeadlessChromium(1280, 760, timeout=120) as b:
        b.goto(url)
        b.wait_for(f"{FRAMES_SERVED} >= 1", timeout=300)
        b.evaluate(CLOSE_NOTIFICATIONS)
        paths[0].write_bytes(settled_screenshot(b, timeout=600))
        served = b.evaluate(FRAMES_SERVED)
        left, right, x, y, _ = b.evaluate(SLIDER.format(label="rotate y (deg)"))
        b.drag(x, y, left + 0.3 * (right - left), y)  # about -70 deg: the left arm goes up
        b.wait_for(f"{FRAMES_SERVED} > {served}", timeout=300)
        b.evaluate(CLOSE_NOTIFICATIONS)
        paths[1].write_bytes(settled_screenshot(b, timeout=600))
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ckpt", required=True, type=Path)
    ap.add_argument("--camera-index", type=int, default=0, help="dataset camera for the BVH video")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images")
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    bvh = jumping_jacks(ROOT / "docs" / "motions" / "jumping_jacks.bvh")
    print(f"wrote {bvh}")
    print(f"wrote {render_strip(args.ckpt.resolve(), bvh, args.out / 'bvh_jumping_jacks.png', args.camera_index)}")
    for path in viewer_screenshots(args.ckpt.resolve(), args.out):
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
