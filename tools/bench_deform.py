"""Cost of the pose path on this machine: polar decomposition, SH rotation, corrector + LBS forward/backward.

    python tools/bench_deform.py [--n 50000] [--repeats 5] [--json out.json]

Variants run side by side in one process; medians after one warm-up, Markdown table printed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def timed(fn, repeats: int) -> list[float]:
    fn()
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=50000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--grid", type=int, default=32)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()

    from framework.geometry import axis_angle_to_rotmat
    from framework.model.gaussian_init import from_body_surface
    from framework.plugins import load_plugins
    from framework.registry import REGISTRIES
    from framework.rig.polar import polar_rotation
    from framework.rig.sh_rotation import rotate_sh
    from plugins.body.procedural import ProceduralBody

    load_plugins()
    torch.manual_seed(0)
    n = a.n
    body = ProceduralBody()
    bounds = torch.stack([body.rest_vertices.min(0).values - 0.1, body.rest_vertices.max(0).values + 0.1])
    g0 = from_body_surface(body, n, seed=0)
    pose = torch.randn(1, body.num_joints, 3) * 0.3
    T = body.bone_transforms(pose)[0]
    w = torch.softmax(torch.randn(n, body.num_joints) * 3, -1)
    A = torch.einsum("nj,jab->nab", w, T[:, :3, :3])
    R = axis_angle_to_rotmat(torch.randn(n, 3))
    sh = torch.randn(n, 16, 3)

    def svd_polar():
        U, _, Vh = torch.linalg.svd(A)
        return U @ Vh

    rows = {
        "polar (Newton fwd, no grad)": timed(lambda: polar_rotation(A), a.repeats),
        "polar (torch SVD fwd, reference)": timed(svd_polar, a.repeats),
        "SH rotation deg 3 (fwd)": timed(lambda: rotate_sh(sh, R), a.repeats),
    }
    for cname, dname in (("none", "lbs"), ("latent", "lbs"), ("latent", "lbs_residual")):
        corr = REGISTRIES["corrector"].build(cname)
        corr.bind(body.num_pose_features)
        deff = REGISTRIES["deformer"].build(dname, grid_resolution=a.grid)
        deff.bind(body, bounds)

        def step(corr=corr, deff=deff):
            params = {
                k: getattr(g0, k).clone().requires_grad_()
                for k in ("means", "quats", "log_scales", "sh", "opacity_logits", "latents")
            }
            g = g0.replace(**params)
            out = deff(corr(g, body.pose_features(pose)[0]), T)
            p = out.posed
            loss = p.means.sum() + p.quats.sum() + p.log_scales.sum() + p.sh.sum() + p.opacity_logits.sum()
            loss = loss + out.aux.get("weight_std", torch.zeros(())).sum()
            loss.backward()

        rows[f"corrector={cname} + deformer={dname} fwd+bwd"] = timed(step, a.repeats)

    print(f"\nN = {n}, torch threads = {torch.get_num_threads()}\n")
    print("| variant | median ms | min ms | max ms |")
    print("|---|---|---|---|")
    for k, v in rows.items():
        print(f"| {k} | {statistics.median(v):.1f} | {min(v):.1f} | {max(v):.1f} |")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({k: {"median_ms": statistics.median(v), "all_ms": v} for k, v in rows.items()}, f, indent=1)


if __name__ == "__main__":
    main()
