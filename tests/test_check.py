"""`python -m framework.data.check`: a correct EasyMocap-layout capture passes; T in millimetres, two swapped cameras
and a mis-ordered camera list are each named as what they are; the mesh can come from stored vertices or from the
parameters; overlays and reports are written; bad input is one message."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_module
from test_easymocap import make_capture, write_calibration, write_easymocap, write_zju

from framework.data.calibration_check import Geometry, score
from framework.data.check import run
from framework.errors import SplatrigError
from plugins.body.procedural import ProceduralBody

C = 6


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    cap = make_capture(ProceduralBody(), C=C, F=3, size=96, seed=2)
    return cap, write_easymocap(tmp_path_factory.mktemp("check") / "good", cap)


def _check(root: Path, out: Path, *extra: str) -> tuple[int, dict]:
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose("check", [f"data.root={root}", "data.downscale=1", f"out_dir={out}", *extra])
    code = run(cfg)
    return code, json.loads((out / "report.json").read_text())


def _variant(base: Path, dst: Path, cap, **calib) -> Path:
    """A copy of the capture (symlinked images and fits) with its own calibration."""
    dst.mkdir(parents=True)
    for name in ("images", "mask-schp", "output-smpl-3d"):
        os.symlink(base / name, dst / name)
    args = {"K_cv": cap.K_opencv, "D": cap.D, "R": cap.R, "T": cap.T, **calib}
    write_calibration(dst, cap.names, args["K_cv"], args["D"], args["R"], args["T"], size=(96, 96))
    return dst


def test_correct_capture_passes_and_writes_overlays(capture, tmp_path: Path) -> None:
    cap, root = capture
    code, rep = _check(root, tmp_path / "out", "body=procedural")
    assert code == 0 and rep["ok"] and not rep["findings"]
    assert [r["verdict"] for r in rep["cameras"]] == ["ok"] * C
    assert min(r["iou"] for r in rep["cameras"]) > 0.8 and min(r["inside"] for r in rep["cameras"]) > 0.97
    overlays = sorted(p.name for p in (tmp_path / "out").glob("overlay_*.png"))
    assert overlays == [f"overlay_{c:02d}_{n}.png" for c, n in enumerate(cap.names)]
    import cv2

    img = cv2.imread(str(tmp_path / "out" / overlays[0]))
    assert img.shape == (512, 512, 3) and img.std() > 10
    assert "No problems found" in (tmp_path / "out" / "report.md").read_text()


def test_millimetre_translation_is_named(capture, tmp_path: Path) -> None:
    cap, root = capture
    mm = _variant(root, tmp_path / "mm", cap, T=cap.T * 1000.0)
    code, rep = _check(mm, tmp_path / "out")  # stored vertices without faces: point-splat silhouettes
    assert code == 1 and not rep["ok"]
    assert any(
        f.startswith("T is in millimetres where metres are expected (6 of 6 cameras") and "divide every T by 1000" in f
        for f in rep["findings"]
    ), rep["findings"]
    assert all(r["verdict"] == "T in millimetres" and r["iou"] < 0.1 for r in rep["cameras"])


def test_zju_layout_with_metres_is_named(capture, tmp_path: Path) -> None:
    """The same check on the ZJU-MoCap layout, whose annots.npy stores T in millimetres: metres there are named."""
    cap, _ = capture
    root = write_zju(tmp_path / "zju", cap)
    annots = np.load(root / "annots.npy", allow_pickle=True).item()
    ok = _check(root, tmp_path / "ok", "data=zju_mocap", "data.protocol=null", "body=procedural")
    assert ok[0] == 0, ok[1]["findings"]
    annots["cams"]["T"] = [t / 1000.0 for t in annots["cams"]["T"]]  # metres written where millimetres belong
    np.save(root / "annots.npy", annots, allow_pickle=True)
    code, rep = _check(root, tmp_path / "out", "data=zju_mocap", "data.protocol=null", "body=procedural")
    assert code == 1 and all(r["verdict"] == "T in metres" for r in rep["cameras"])
    assert any(
        f.startswith("T is in metres where millimetres are expected (6 of 6 cameras")
        and "multiply every T by 1000" in f
        for f in rep["findings"]
    ), rep["findings"]


@pytest.mark.parametrize("order", [[0, 3, 2, 1, 4, 5], [0, 2, 4, 3, 1, 5]], ids=["two swapped", "mis-ordered list"])
def test_swapped_and_misordered_cameras_are_named(capture, tmp_path: Path, order: list[int]) -> None:
    cap, root = capture
    wrong = _variant(
        root, tmp_path / "wrong", cap, K_cv=cap.K_opencv[order], D=cap.D[order], R=cap.R[order], T=cap.T[order]
    )
    code, rep = _check(wrong, tmp_path / "out", "body=procedural")
    assert code == 1
    moved = [c for c in range(C) if order[c] != c]
    verdicts = {r["name"]: r["verdict"] for r in rep["cameras"]}
    assert [n for n, v in verdicts.items() if v != "ok"] == [cap.names[c] for c in moved]
    if len(moved) == 2:
        a, b = (cap.names[c] for c in moved)
        assert any(f.startswith(f"cameras {a} and {b} are swapped") for f in rep["findings"]), rep["findings"]
    else:
        # images of camera c were taken by the camera whose calibration is now stored under order.index(c)
        for c in moved:
            assert verdicts[cap.names[c]] == f"fits the calibration of {cap.names[order.index(c)]}"
        assert any("the camera list is mis-ordered" in f for f in rep["findings"]), rep["findings"]


def test_mesh_from_parameters_when_no_vertices_are_stored(capture, tmp_path: Path) -> None:
    cap, root = capture
    bare = tmp_path / "bare"
    bare.mkdir()
    for name in ("images", "mask-schp", "intri.yml", "extri.yml"):
        os.symlink(root / name, bare / name)
    (bare / "output" / "smpl").mkdir(parents=True)
    for p in (root / "output-smpl-3d" / "smpl").iterdir():
        os.symlink(p, bare / "output" / "smpl" / p.name)
    code, rep = _check(bare, tmp_path / "out", "body=procedural", "data.body=procedural")
    assert code == 0 and min(r["iou"] for r in rep["cameras"]) > 0.8


def test_scores_against_a_brute_force_reference() -> None:
    """Inside share and IoU of one triangle pair (a square) seen head-on, against counting pixel centres."""
    pts = np.array([[-0.5, -0.5, 4.0], [0.5, -0.5, 4.0], [0.5, 0.5, 4.0], [-0.5, 0.5, 4.0]])
    geom = Geometry(pts, np.array([[0, 1, 2], [0, 2, 3]]))
    K = np.array([[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]])  # the square spans pixels 11..21 (centres at +0.5)
    mask = np.zeros((32, 32), bool)
    mask[8:20, 11:21] = True
    inside, iou, sil = score(geom, mask, K, np.eye(4))
    jj, ii = np.meshgrid(np.arange(32) + 0.5, np.arange(32) + 0.5)
    ref = (jj > 11) & (jj < 21) & (ii > 11) & (ii < 21)  # pixel centres inside the projected square
    np.testing.assert_array_equal(sil, ref)
    assert inside == 0.25  # only the corner (11, 11) lands in the mask; (21, 21) etc. do not
    assert iou == (ref & mask).sum() / (ref | mask).sum() == 90 / 130


def test_command_line_exit_status_and_missing_root(capture, tmp_path: Path) -> None:
    cap, root = capture
    mm = _variant(root, tmp_path / "mm", cap, T=cap.T * 1000.0)
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable,
        "-m",
        "framework.data.check",
        f"data.root={mm}",
        "data.downscale=1",
        "frames=2",
        f"out_dir={tmp_path / 'cli'}",
    ]
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert "T is in millimetres" in proc.stdout and "| 0 | 01 |" in proc.stdout
    assert "masks from mask-schp" in proc.stderr  # says which mask folder it used
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose("check", [f"out_dir={tmp_path / 'none'}"])
    with pytest.raises(SplatrigError, match=r"^data.root is not set: pass data.root=/path/to/your/capture$"):
        run(cfg)  # the entry point prints it as one line and exits with status 2
