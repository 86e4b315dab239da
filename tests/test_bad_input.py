"""Bad input, tried as a user would: every case ends with ONE `error:` line and exit status 2, never a traceback, and
its message is the one docs/errors.md shows (tests/errors_table.py).

Cases run in-process through the same functions the entry points call (`framework.train.run`,
`framework.evaluate.evaluate_from_config`, `framework.render.render_from_config`) inside `reported_as_message`,
with configs composed by Hydra as on the command line; two run through the real command line as well.
"""

from __future__ import annotations

import contextlib
import io
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from errors_table import check_documented, normalise, rows
from test_divergence import DIVERGENCE_CASES

from framework.errors import reported_as_message

# the tiny avatar on a 4-view, 4-frame ZJU-layout sequence of the procedural body (tests/test_zju_mocap.py writes it)
ZJU = [
    "data=zju_mocap",
    "data.protocol=null",
    "data.downscale=1",
    "body=procedural",
    "deformer=lbs",
    "deformer.grid_resolution=8",
    "gaussians=body_surface",
    "gaussians.num=200",
    "corrector=none",
    "trainer.max_steps=3",
    "callbacks.progress_bar=false",
    "eval.after_fit=false",
    "logger=none",
]


@dataclass(frozen=True)
class Case:
    id: str
    entry: str  # train | evaluate | render
    bad_input: str  # what the docs table shows
    overrides: list[str] = field(default_factory=list)  # {placeholders} filled from the `world` fixture
    hint: str = ""  # COMMAND_LINE_CASES: the did-you-mean the message must hold


def seq(variant: str) -> list[str]:
    return [*ZJU, f"data.root={{{variant}}}"]


CASES = [
    # ---- config values (framework/config_checks.py)
    Case(
        "zju_root_missing",
        "train",
        "`data=zju_mocap data.root=/nonexistent/seq`",
        ["data=zju_mocap", "data.root=/nonexistent/seq"],
    ),
    Case("zju_root_unset", "train", "`data=zju_mocap` (no `data.root`)", ["data=zju_mocap"]),
    Case("sh_degree_7", "train", "`gaussians.sh_degree=7`", ["gaussians.sh_degree=7"]),
    Case("negative_loss_weight", "train", "`loss.terms.l1.weight=-1`", ["loss.terms.l1.weight=-1"]),
    Case("zero_steps", "train", "`trainer.max_steps=0`", ["trainer.max_steps=0"]),
    Case("negative_steps", "train", "`trainer.max_steps=-5`", ["trainer.max_steps=-5"]),
    Case(
        "stage1_longer_than_run",
        "train",
        "`+experiment=paper_full trainer.max_steps=100 stages.stage1_steps=200`",
        ["+experiment=paper_full", "trainer.max_steps=100", "stages.stage1_steps=200"],
    ),
    Case("resolution_0", "train", "`data.resolution=0`", ["data.resolution=0"]),
    Case("small_work_threads_0", "train", "`small_work_threads=0`", ["small_work_threads=0"]),
    Case("unknown_component", "train", "`rasterizer.name=torch_reff`", ["rasterizer.name=torch_reff"]),
    # ---- dataset files (framework/data/zju/, framework/data/sequence_dataset.py)
    Case(
        "image_size_mismatch", "train", "`data.root=` a sequence with one 48x30 image among 48x48 ones", seq("imgsize")
    ),
    Case(
        "mask_size_mismatch", "train", "`data.root=` a sequence whose mask of frame 1, view 2 is 48x40", seq("masksize")
    ),
    Case(
        "mask_empty",
        "train",
        "`data.root=` a sequence whose mask of frame 2, view 1 is all background",
        [*seq("emptymask"), "data.train_frames=[2,3,1]", "data.train_views=[1]"],
    ),
    Case("mask_missing", "train", "`data.root=` a sequence without the mask of frame 0, view 2", seq("nomask")),
    Case("image_missing", "train", "`data.root=` a sequence without the image of frame 2, view 2", seq("noimage")),
    Case(
        "image_corrupted",
        "train",
        "`data.root=` a sequence whose image of frame 0, view 3 is not an image",
        seq("corrupt"),
    ),
    Case(
        "image_truncated",
        "train",
        "`data.root=` a sequence whose image of frame 3, view 0 is cut in half",
        seq("trunc"),
    ),
    Case("camera_not_rotation", "train", "`data.root=` a sequence whose camera 1 has R scaled by 1.3", seq("rot")),
    Case("camera_negative_focal", "train", "`data.root=` a sequence whose camera 2 has fx = -50", seq("focal")),
    Case(
        "pose_joint_count_differs",
        "train",
        "`data.root=` a sequence whose frame 1 has 16 joints, the others 17",
        seq("joints"),
    ),
    Case(
        "pose_joint_count_vs_body",
        "train",
        "`data.root=` a sequence posed with 16 joints, `body=procedural` (17)",
        seq("joints16"),
    ),
    Case("pose_non_finite", "train", "`data.root=` a sequence with a NaN in the pose of frame 2", seq("nan")),
    # ---- checkpoints (framework/lightning/checkpoint_io.py, framework/lightning/module.py)
    Case("resume_ckpt_truncated", "train", "`ckpt=` a checkpoint cut in half", [*seq("seq"), "ckpt={truncated}"]),
    Case(
        "resume_other_body",
        "train",
        "`ckpt=` a checkpoint of `body=procedural` with `body.segments=8`",
        [*seq("seq"), "body.segments=8", "ckpt={ckpt}"],
    ),
    Case(
        "resume_other_model",
        "train",
        "`ckpt=` an avatar checkpoint, resumed as `+experiment=static_fit`",
        ["+experiment=static_fit", "data.resolution=16", "ckpt={ckpt}"],
    ),
    Case("evaluate_no_ckpt", "evaluate", "no `ckpt=`", []),
    Case("evaluate_ckpt_missing", "evaluate", "`ckpt=` a file that does not exist", ["ckpt={root}/none.ckpt"]),
    Case("evaluate_ckpt_truncated", "evaluate", "`ckpt=` a checkpoint cut in half", ["ckpt={truncated}"]),
    Case("evaluate_ckpt_not_torch", "evaluate", "`ckpt=` a text file", ["ckpt={garbage}"]),
    Case(
        "evaluate_ckpt_foreign",
        "evaluate",
        "`ckpt=` a torch file that is not a splatrig checkpoint",
        ["ckpt={foreign}"],
    ),
    Case("evaluate_unknown_metric", "evaluate", "`metrics=[psnrr]`", ["ckpt={ckpt}", "metrics=[psnrr]"]),
    Case(
        "evaluate_record_two_splits",
        "evaluate",
        "`record_as=novel_pose_true_poses splits=[novel_view,novel_pose]`",
        ["ckpt={ckpt}", "record_as=novel_pose_true_poses", "splits=[novel_view,novel_pose]"],
    ),
    Case(
        "evaluate_record_no_run",
        "evaluate",
        "`record_as=` with a checkpoint outside a training run",
        ["ckpt={loose_ckpt}", "record_as=novel_pose_true_poses", "splits=[novel_pose]"],
    ),
    Case("render_no_ckpt", "render", "no `ckpt=`", []),
    Case(
        "render_motion_joints",
        "render",
        "`motion=` an .npz whose poses have 5 joints",
        ["ckpt={ckpt}", "motion={motion_joints}"],
    ),
    Case(
        "render_motion_non_finite",
        "render",
        "`motion=` an .npz with a NaN in frame 1",
        ["ckpt={ckpt}", "motion={motion_nan}"],
    ),
    Case(
        "render_motion_no_poses",
        "render",
        "`motion=` an .npz without `poses`",
        ["ckpt={ckpt}", "motion={motion_nokey}"],
    ),
    Case("render_motion_truncated", "render", "`motion=` an .npz cut in half", ["ckpt={ckpt}", "motion={motion_cut}"]),
    Case(
        "render_camera_index",
        "render",
        "`cameras=fixed camera_index=99`",
        ["ckpt={ckpt}", "motion=train", "cameras=fixed", "camera_index=99"],
    ),
    Case("render_resolution_0", "render", "`resolution=0`", ["ckpt={ckpt}", "resolution=0"]),
    Case("prune_refit_steps_negative", "prune", "`refit_steps=-1`", ["ckpt={ckpt}", "refit_steps=-1"]),
    Case("prune_tolerance_negative", "prune", "`prune_tolerance=-0.01`", ["ckpt={ckpt}", "prune_tolerance=-0.01"]),
    Case("prune_fold_tolerance_word", "prune", "`fold_tolerance=never`", ["ckpt={ckpt}", "fold_tolerance=never"]),
    Case("prune_rounds_zero", "prune", "`prune_rounds=0`", ["ckpt={ckpt}", "prune_rounds=0"]),
    Case(
        "prune_timing_rasterizer_unknown",
        "prune",
        "`timing_rasterizer=numbaa`",
        ["ckpt={ckpt}", "timing_rasterizer=numbaa"],
    ),
]

# Overrides the command line cannot take (framework.cli) and a resume checkpoint that does not exist: found before
# anything is built, so these run as a user would (a fresh process each) without the `world` fixture.
COMMAND_LINE_CASES = [
    Case("option_unknown", "train", "`rasterizer=numbaa`", ["rasterizer=numbaa"], "; did you mean numba?"),
    Case(
        "experiment_unknown",
        "train",
        "`+experiment=paper_ful`",
        ["+experiment=paper_ful"],
        "; did you mean paper_full?",
    ),
    Case(
        "key_unknown", "train", "`trainer.max_step=100`", ["trainer.max_step=100"], "; did you mean trainer.max_steps?"
    ),
    # a value of the wrong type fails while composing (the types: framework/config_schema.py)
    Case("value_not_int", "train", "`trainer.max_steps=abc`", ["trainer.max_steps=abc"], "expected an integer"),
    Case("value_not_int_sh", "train", "`gaussians.sh_degree=1.5`", ["gaussians.sh_degree=1.5"], "expected an integer"),
    Case("value_not_bool", "train", "`pose_refine.enabled=maybe`", ["pose_refine.enabled=maybe"], "true or false"),
    # the studio's counts follow the dataset-key rule (framework.dataset_keys): the old name says the new one
    Case(
        "key_renamed",
        "train",
        "`data=synthetic_studio data.views=4`",
        ["data=synthetic_studio", "data.views=4"],
        "; it is now data.num_views",
    ),
    # `motion=`, as in render and view, is a key of export's config (it used to be unknown)
    Case(
        "key_unknown_export",
        "export",
        "`motion=novel_pose fram=3`",
        ["ckpt=/nonexistent/last.ckpt", "motion=novel_pose", "fram=3"],
        "; did you mean frame?",
    ),
    # the dataset's root does not exist either: the checkpoint is checked first, before the data is opened
    Case(
        "resume_ckpt_missing",
        "train",
        "`ckpt=/nonexistent/last.ckpt`",
        ["data=zju_mocap", "data.root=/nonexistent/seq", "ckpt=/nonexistent/last.ckpt"],
    ),
]


def invoke(entry: str, overrides: list[str], out_dir: Path) -> tuple[int, str]:
    """Compose the entry point's config as Hydra does on the command line and run it like its main: (status, stderr)."""
    from hydra import compose, initialize_config_module

    from framework.evaluate import evaluate_from_config
    from framework.prune import prune_from_config
    from framework.render import render_from_config
    from framework.train import run

    extra = {"train": [f"paths.output_dir={out_dir}"], "prune": [f"out={out_dir / 'compact.ckpt'}"]}.get(
        entry, [f"out_dir={out_dir}"]
    )
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name=entry, overrides=[*overrides, *extra])
    function = {
        "train": run,
        "evaluate": evaluate_from_config,
        "render": render_from_config,
        "prune": prune_from_config,
    }[entry]
    err = io.StringIO()
    status = 0
    with contextlib.redirect_stderr(err):
        try:
            with reported_as_message():
                function(cfg)
        except SystemExit as exc:
            status = int(exc.code or 0)
    return status, err.getvalue()


def _variants(root: Path) -> dict[str, Path]:
    """The sequence and one broken copy per case."""
    from test_zju_mocap import write_body_sequence

    from plugins.body.procedural import ProceduralBody

    base = root / "seq"
    write_body_sequence(base, ProceduralBody(), C=4, F=4, size=48)
    ims = np.load(base / "annots.npy", allow_pickle=True).item()["ims"]

    def clone(name: str) -> Path:
        shutil.copytree(base, root / f"seq_{name}")
        return root / f"seq_{name}"

    def edit_annots(d: Path, fn) -> None:
        a = np.load(d / "annots.npy", allow_pickle=True).item()
        fn(a["cams"])
        np.save(d / "annots.npy", np.array(a, dtype=object), allow_pickle=True)

    def edit_params(d: Path, frame: int, fn) -> None:
        p = np.load(d / "params" / f"{frame}.npy", allow_pickle=True).item()
        fn(p)
        np.save(d / "params" / f"{frame}.npy", np.array(p, dtype=object), allow_pickle=True)

    def mask(d: Path, frame: int, view: int) -> Path:
        return d / "mask" / (ims[frame]["ims"][view][:-4] + ".png")

    out = {"seq": base}
    d = out["imgsize"] = clone("imgsize")
    cv2.imwrite(str(d / ims[1]["ims"][1]), np.zeros((30, 48, 3), np.uint8))
    d = out["masksize"] = clone("masksize")
    cv2.imwrite(str(mask(d, 1, 2)), np.full((40, 48), 255, np.uint8))
    d = out["emptymask"] = clone("emptymask")
    cv2.imwrite(str(mask(d, 2, 1)), np.zeros((48, 48), np.uint8))
    d = out["nomask"] = clone("nomask")
    mask(d, 0, 2).unlink()
    d = out["noimage"] = clone("noimage")
    (d / ims[2]["ims"][2]).unlink()
    d = out["corrupt"] = clone("corrupt")
    (d / ims[0]["ims"][3]).write_bytes(b"garbage, not an image")
    d = out["trunc"] = clone("trunc")
    data = (d / ims[3]["ims"][0]).read_bytes()
    (d / ims[3]["ims"][0]).write_bytes(data[: len(data) // 2])
    edit_annots(out.setdefault("rot", clone("rot")), lambda c: c["R"].__setitem__(1, c["R"][1] * 1.3))
    edit_annots(out.setdefault("focal", clone("focal")), lambda c: c["K"][2].__setitem__((0, 0), -50.0))
    drop_joint = lambda p: p.__setitem__("poses", p["poses"][:, :-3])  # noqa: E731
    edit_params(out.setdefault("joints", clone("joints")), 1, drop_joint)
    d = out["joints16"] = clone("joints16")
    for f in range(4):
        edit_params(d, f, drop_joint)
    edit_params(out.setdefault("nan", clone("nan")), 2, lambda p: p["poses"].__setitem__((0, 7), np.nan))
    return out


@pytest.fixture(scope="module")
def world(tmp_path_factory: pytest.TempPathFactory):
    """Broken sequences, a trained checkpoint and broken copies of it, broken motion files (built once)."""
    root = tmp_path_factory.mktemp("bad_input")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SPLATRIG_CACHE_DIR", str(root / "cache"))
        paths: dict[str, Path] = {"root": root, **_variants(root)}
        status, err = invoke(
            "train",
            [*ZJU, f"data.root={paths['seq']}", "trainer.max_steps=2", "callbacks.checkpoint_every=1"],
            root / "run",
        )
        assert status == 0, err
        paths["ckpt"] = root / "run" / "checkpoints" / "last.ckpt"
        data = paths["ckpt"].read_bytes()
        (root / "truncated.ckpt").write_bytes(data[: len(data) // 2])
        (root / "garbage.ckpt").write_text("not a checkpoint\n")
        (root / "loose").mkdir()
        (root / "loose" / "checkpoints").mkdir()
        paths["loose_ckpt"] = root / "loose" / "checkpoints" / "last.ckpt"  # a copy with no run record beside it
        paths["loose_ckpt"].write_bytes(data)
        torch.save({"weights": torch.zeros(3)}, root / "foreign.ckpt")
        np.savez(root / "motion_joints.npz", poses=np.zeros((3, 5, 3), np.float32))
        poses = np.zeros((3, 17, 3), np.float32)
        poses[1, 4, 2] = np.nan
        np.savez(root / "motion_nan.npz", poses=poses)
        np.savez(root / "motion_nokey.npz", rotations=np.zeros((3, 17, 3), np.float32))
        motion = (root / "motion_joints.npz").read_bytes()
        (root / "motion_cut.npz").write_bytes(motion[: len(motion) // 2])
        for name in ("truncated", "garbage", "foreign", "motion_joints", "motion_nan", "motion_nokey", "motion_cut"):
            paths[name] = next(root.glob(f"{name}.*"))
        yield paths


def _one_error_line(status: int, err: str) -> str:
    assert status == 2, f"exit status {status}:\n{err[-3000:]}"
    assert "Traceback" not in err, err[-3000:]
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, err[-3000:]
    return lines[0]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_gives_one_message(case: Case, world: dict[str, Path], tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(world["root"] / "cache"))
    placeholders = {k: str(v) for k, v in world.items()}
    status, err = invoke(case.entry, [o.format(**placeholders) for o in case.overrides], tmp_path / "out")
    line = _one_error_line(status, err)
    check_documented(case.id, case.entry, case.bad_input, normalise(line, {"<tmp>": world["root"]}))


def test_every_documented_case_is_tested() -> None:
    """A row of docs/errors.md that no test triggers would go stale: there is none, and no case lacks a row."""
    assert set(rows()) == {c.id for c in [*CASES, *COMMAND_LINE_CASES]} | set(DIVERGENCE_CASES)


def run_command_line(entry: str, args: list[str], tmp_path: Path) -> subprocess.CompletedProcess:
    extra = [f"paths.root={tmp_path}"] if entry == "train" else []
    cmd = [sys.executable, "-m", f"framework.{entry}", *args, *extra]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)


def _last_line_is_the_error(proc: subprocess.CompletedProcess) -> str:
    """Exit status 2 and stderr ending in its one `error:` line, with no traceback and no Hydra advice."""
    line = _one_error_line(proc.returncode, proc.stderr)
    assert [x for x in proc.stderr.splitlines() if x.strip()][-1] == line, proc.stderr
    assert "To append to your config" not in proc.stderr and "HYDRA_FULL_ERROR" not in proc.stderr, proc.stderr
    return line


@pytest.mark.parametrize("case", COMMAND_LINE_CASES, ids=[c.id for c in COMMAND_LINE_CASES])
def test_command_line_error_before_anything_is_built(case: Case, tmp_path: Path) -> None:
    """Hydra's composition errors (framework.cli) end like ours: one line, with the closest valid name."""
    line = _last_line_is_the_error(run_command_line(case.entry, case.overrides, tmp_path))
    assert case.hint in line
    check_documented(case.id, case.entry, case.bad_input, line)


@pytest.mark.parametrize(
    ("entry", "args", "note"),
    [
        ("train", ["ckpt_path=/nonexistent/last.ckpt"], "ckpt_path= is the older name of ckpt="),
        ("export", ["ckpt=/nonexistent/last.ckpt", "pose=novel_pose"], "pose= is the older name of motion="),
    ],
)
def test_older_key_names_still_work_with_one_note(entry: str, args: list[str], note: str, tmp_path: Path) -> None:
    """train's `ckpt_path=` is now `ckpt=` and export's `pose=` is `motion=`, as in the other entry points; the older
    names still work and print one note (here the checkpoint is missing, so the run stops at the usual message)."""
    proc = run_command_line(entry, args, tmp_path)
    line = _last_line_is_the_error(proc)
    assert proc.stderr.count(note) == 1, proc.stderr
    assert line.startswith("error: ckpt=/nonexistent/last.ckpt: no such checkpoint file"), line


def test_job_runs_without_hydra_full_error(tmp_path: Path, monkeypatch) -> None:
    """framework.cli sets HYDRA_FULL_ERROR=1 only while Hydra composes: the job and the processes it starts see the
    environment the user gave."""
    from hydra.core.global_hydra import GlobalHydra

    from framework.cli import hydra_main

    seen = {}

    @hydra_main("evaluate")
    def job(cfg) -> None:
        seen.update(env=os.environ.get("HYDRA_FULL_ERROR"), ckpt=cfg.ckpt)

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", ["evaluate", "ckpt=x", f"out_dir={tmp_path}"])
    monkeypatch.chdir(tmp_path)
    try:
        job()
    finally:
        GlobalHydra.instance().clear()
    assert seen == {"env": None, "ckpt": "x"}
    assert "HYDRA_FULL_ERROR" not in os.environ


@pytest.mark.parametrize("case_id", ["evaluate_no_ckpt", "render_motion_no_poses"])
def test_command_line_prints_the_same_one_line(case_id: str, world: dict[str, Path], tmp_path: Path) -> None:
    """The real entry points (Hydra's main, a fresh process): exit status 2, no traceback, the documented line
    (framework.train's command line is run by tests/test_training.py and tests/test_divergence.py)."""
    case = next(c for c in CASES if c.id == case_id)
    placeholders = {k: str(v) for k, v in world.items()}
    extra = [f"paths.root={tmp_path}"] if case.entry == "train" else [f"out_dir={tmp_path}"]
    cmd = [sys.executable, "-m", f"framework.{case.entry}", *[o.format(**placeholders) for o in case.overrides], *extra]
    env = dict(os.environ, SPLATRIG_CACHE_DIR=str(world["root"] / "cache"))
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    line = _one_error_line(proc.returncode, proc.stderr)
    assert normalise(line, {"<tmp>": world["root"]}) == rows()[case_id][2]
