"""The animatable package: written by the export entry point, re-posed from its files alone by an independent numpy
implementation of its documented formula, and compared with the avatar's own render."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from plyfile import PlyData
from trained_avatar import load_tiny

SH_C1 = 0.4886025119029199


@pytest.fixture(scope="module")
def package(tiny_avatar, tmp_path_factory):
    ckpt, cache = tiny_avatar
    root = tmp_path_factory.mktemp("package")
    out = root / "export"
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(cache))
    cmd = [
        sys.executable,
        "-m",
        "framework.export",
        f"ckpt={ckpt}",
        "motion=train",
        "frame=3",
        "animatable=true",
        f"out_dir={out}",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return ckpt, cache, out, proc


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def repose_from_files(folder, frame: int, corrections: bool = True) -> dict[str, np.ndarray]:
    """The README's steps 1-5 in float64 numpy, reading only canonical.ply and rig.npz (step 1 optional)."""
    from scipy.spatial.transform import Rotation

    v = PlyData.read(str(folder / "canonical.ply"))["vertex"].data
    x = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    q = np.stack([v[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    s = np.stack([v[f"scale_{i}"] for i in range(3)], 1).astype(np.float64)
    o = np.asarray(v["opacity"], np.float64)
    dc = np.stack([v[f"f_dc_{c}"] for c in range(3)], 1)[:, None]  # [N, 1, 3]
    rest = np.stack([v[f"f_rest_{i}"] for i in range(45)], 1).reshape(-1, 3, 15).transpose(0, 2, 1)
    sh = np.concatenate([dc, rest], 1).astype(np.float64)  # [N, 16, 3]
    rig = np.load(folder / "rig.npz")
    if corrections:  # step 1
        o, s, q = (
            rig[k][frame].astype(np.float64)
            for k in ("corrected_opacity_logits", "corrected_log_scales", "corrected_quats")
        )
        kc = rig["corrected_sh"].shape[2]
        sh[:, :kc] = rig["corrected_sh"][frame]
    P = np.einsum("nk,kij->nij", rig["skin_weights"].astype(np.float64), rig["bone_transforms"][frame][:, :3])  # 2
    A, t = P[:, :, :3], P[:, :, 3]
    U, D, Vt = np.linalg.svd(A)  # 3: polar decomposition A = R S
    R = U @ Vt
    S = np.swapaxes(Vt, 1, 2) @ (D[:, :, None] * Vt)
    means = np.einsum("nij,nj->ni", R if str(rig["centres"]) == "rigid" else A, x) + t  # 3: the mean
    qR = Rotation.from_matrix(R).as_quat()[:, [3, 0, 1, 2]]
    quats = quat_multiply(qR, q)
    if str(rig["stretch"]) == "diag":
        Q = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # columns = the Gaussian's axes
        k = np.einsum("nil,nij,njl->nl", Q, S, Q)
        s = s + np.log(np.maximum(k, 1e-4))
    assert np.abs(sh[:, 4:]).max() == 0  # the tiny avatar has SH up to degree 1, which this reference rotates
    vec = np.stack([-sh[:, 3], -sh[:, 1], sh[:, 2]], 1)  # [N, 3 (xyz), 3 channels]: colour = C1 * vec . d
    vec = np.einsum("nij,njc->nic", R, vec)  # 5: degree 1 turns like a vector
    sh[:, 1], sh[:, 2], sh[:, 3] = -vec[:, 1], vec[:, 2], -vec[:, 0]
    return {
        "means": means,
        "quats": quats,
        "log_scales": s,
        "opacity_logits": o,
        "sh": sh,
        "sh_degree": int(rig["sh_degree"]),
    }


def test_package_holds_the_documented_arrays(package):
    _, _, out, proc = package
    folder = out / "train_animatable"
    assert "animatable package" in proc.stdout
    assert (folder / "README.md").read_text().startswith("The animatable avatar package")
    rig = np.load(folder / "rig.npz")
    n = len(PlyData.read(str(folder / "canonical.ply"))["vertex"].data)
    F, J = rig["bone_transforms"].shape[:2]
    assert str(rig["format"]) == "splatrig-animatable-2"
    assert str(rig["centres"]) == "rigid" and str(rig["stretch"]) == "diag"  # paper_full's deformer
    # the paper's additive w0 + F_dw: rows near 1, not renormalised (the tiny avatar's F_dw is random but small)
    sums = rig["skin_weights"].sum(1)
    assert rig["skin_weights"].shape == (n, J) and np.abs(sums - 1).max() < 0.5 and np.abs(sums - 1).max() > 1e-3
    assert rig["parents"].shape == (J,) and rig["parents"][0] == -1 and rig["rest_joints"].shape == (J, 3)
    assert len(rig["joint_names"]) == J and rig["poses"].shape == (F, J, 3)
    assert np.allclose(rig["bone_transforms"][:, :, 3], [0, 0, 0, 1])
    assert rig["corrected_opacity_logits"].shape == (F, n) and rig["corrected_quats"].shape == (F, n, 4)
    assert rig["corrected_sh"].shape[2] == 1  # the latent corrector changes the DC term only


def test_package_reposes_like_the_avatar(package, monkeypatch):
    """Every frame re-posed from the files alone renders like the avatar (float64 reference vs float32 avatar)."""
    from framework.animation.frames import frame_batch
    from framework.animation.sources import load_motion
    from framework.registry import RASTERIZERS

    ckpt, cache, out, _ = package
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    motion, frames = load_motion(module, dm, "train")
    cams = dm.split("novel_view").cameras.index(0)
    torch_ref = RASTERIZERS.build("torch_ref")

    def render(g: dict[str, np.ndarray]) -> torch.Tensor:
        t = {k: torch.tensor(v).float() for k, v in g.items() if k != "sh_degree"}
        return torch_ref.render(
            t["means"],
            t["quats"],
            t["log_scales"].exp(),
            t["opacity_logits"].sigmoid(),
            t["sh"],
            cams,
            sh_degree=g["sh_degree"],
            background=module.avatar.background,
        ).rgb

    for f in range(motion.num_frames):
        with torch.no_grad():
            ours = module.render_batch(
                frame_batch(cams, torch.as_tensor(motion.poses[f]), torch.as_tensor(motion.roots[f]), frames[f])
            ).render.rgb
            theirs = render(repose_from_files(out / "train_animatable", f))
            uncorrected = render(repose_from_files(out / "train_animatable", f, corrections=False))
        assert ours.abs().mean() > 0.01
        err = (ours - theirs).abs()
        assert err.max() < 2e-3 and err.mean() < 1e-5, (f, float(err.max()), float(err.mean()))
        assert (ours - uncorrected).abs().max() > 2e-2  # the stored corrections are what makes it match


def test_reading_the_package_back_poses_the_same_gaussians(package, monkeypatch):
    """framework.formats.animatable.pose_frame (for Python users of a package) gives the avatar's posed Gaussians."""
    from framework.animation.frames import posed_gaussians
    from framework.animation.sources import load_motion
    from framework.formats.animatable import pose_frame, read_package

    ckpt, cache, out, _ = package
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    module, dm = load_tiny(ckpt)
    motion, frames = load_motion(module, dm, "train")
    pkg = read_package(out / "train_animatable")
    assert pkg.num_frames == motion.num_frames and pkg.corrections is not None
    for f in (0, motion.num_frames - 1):
        ours = posed_gaussians(module, torch.as_tensor(motion.poses[f]), torch.as_tensor(motion.roots[f]), frames[f])
        theirs = pose_frame(pkg, f)
        for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
            assert torch.allclose(getattr(theirs, name), getattr(ours, name), atol=1e-5), name


def test_a_version_1_package_reads_as_blended_centres(package, tmp_path):
    """Packages written before `centres` existed posed means by A x + t: they still read, as blended."""
    import shutil

    from framework.formats.animatable import pose_frame, read_package

    _, _, out, _ = package
    old = tmp_path / "old"
    shutil.copytree(out / "train_animatable", old)
    with np.load(old / "rig.npz") as data:
        arrays = {k: data[k] for k in data.files if k != "centres"}
    arrays["format"] = np.asarray("splatrig-animatable-1")
    np.savez(old / "rig.npz", **arrays)
    pkg, new = read_package(old), read_package(out / "train_animatable")
    assert pkg.centres == "blended" and new.centres == "rigid"
    assert (pose_frame(pkg, 0).means - pose_frame(new, 0).means).abs().max() > 1e-4  # the two forms differ
    pkg.centres = "rigid"
    torch.testing.assert_close(pose_frame(pkg, 0).means, pose_frame(new, 0).means)
