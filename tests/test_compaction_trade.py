"""tools/compaction_trade.py: each setting is the compaction it names, measured against the reference; a model
compared with itself reads 0 dB, and the settings it cannot parse fail with one error naming the fix."""

from __future__ import annotations

import csv

import pytest
import torch
from tool_module import load_tool


@pytest.fixture(scope="module")
def tool():
    return load_tool("compaction_trade")


def test_settings_parse_as_yaml_values_and_unknown_keys_are_refused(tool):
    assert tool.parse_setting("kept=fold_tolerance=null") == ("kept", {"fold_tolerance": None})
    assert tool.parse_setting("fast=prune_tolerance=0.045,refit_steps=600") == (
        "fast",
        {"prune_tolerance": 0.045, "refit_steps": 600},
    )
    with pytest.raises(SystemExit, match="'fold' is not one of framework.prune's keys"):
        tool.parse_setting("x=fold=0.1")
    with pytest.raises(SystemExit, match="expected NAME=KEY=VALUE"):
        tool.parse_setting("fold_tolerance")


def test_trade_rows_are_the_compactions_they_name(tool, tiny_avatar, tmp_path_factory, monkeypatch):
    ckpt, cache = tiny_avatar  # F_a with a random head, F_dw on
    monkeypatch.setenv("SPLATRIG_CACHE_DIR", str(cache))
    out = tmp_path_factory.mktemp("trade")
    untouched = dict(fold_tolerance=None, prune_tolerance=None, min_weight=0.0, sh_tolerance=0.0, refit_steps=0)
    settings = {tool.AS_TRAINED: {}, "untouched": untouched, "folded whole": dict(untouched, fold_tolerance=1.0)}
    flags = [
        f"--setting={name}=" + ",".join(f"{k}={'null' if v is None else v}" for k, v in options.items())
        for name, options in settings.items()
        if options
    ]
    tool.main(
        [
            "--reference",
            str(ckpt),
            "--ckpt",
            str(ckpt),
            "--out",
            str(out),
            "--warmup",
            "1",
            "--repeats",
            "1",
            "--rounds",
            "1",
            *flags,
        ]
    )
    rows = {r["setting"]: r for r in csv.DictReader(open(out / "compaction_trade.csv"))}
    assert list(rows) == [tool.AS_TRAINED, "untouched", "folded whole"]
    n = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]["avatar.gaussians.params.means"].shape[0]
    trained, kept, folded = rows[tool.AS_TRAINED], rows["untouched"], rows["folded whole"]
    # the model against itself: the same renders, 0 dB exactly; F_a on every row
    assert float(trained["psnr_novel_view"]) == 0.0 and float(trained["psnr_novel_pose"]) == 0.0
    assert int(trained["num_gaussians"]) == n and int(trained["corrector_rows"]) == n
    # nothing removed, F_a kept: only F_dw baked and weights stored, which render the same to float rounding
    assert int(kept["num_gaussians"]) == n and int(kept["corrector_rows"]) == n
    assert abs(float(kept["psnr_novel_view"])) < 0.01 and abs(float(kept["psnr_novel_pose"])) < 0.01
    # a tolerance of 1.0 accepts any fold: F_a is gone (and with it its rows)
    assert int(folded["corrector_rows"]) == 0
    assert (
        "avatar.corrector.head.weight"
        not in torch.load(out / "folded_whole.ckpt", map_location="cpu", weights_only=False)["state_dict"]
    )
    assert float(folded["fps_ratio"]) > 0 and float(folded["smaller"]) > float(kept["smaller"])  # no MLP, no latents
    assert (out / "compaction_trade.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "| untouched |" in (out / "compaction_trade.md").read_text()
    # resumable: a second run reuses the compact model made with the same options, and remakes one whose options
    # changed under the same name
    stamp = (out / "untouched.ckpt").stat().st_mtime_ns
    again = [
        "--reference",
        str(ckpt),
        "--ckpt",
        str(ckpt),
        "--out",
        str(out),
        "--warmup",
        "1",
        "--repeats",
        "1",
        "--rounds",
        "1",
        flags[0],
    ]
    tool.main(again)
    assert (out / "untouched.ckpt").stat().st_mtime_ns == stamp
    tool.main([*again[:-1], flags[0].replace("refit_steps=0", "refit_steps=2")])
    assert (out / "untouched.ckpt").stat().st_mtime_ns != stamp


def test_target_is_met_inside_the_budget_and_no_loss_means_none(tool):
    row = tool.TradeRow(
        "s", "-", 1, 1, 2.0, psnr_novel_view=-0.29, psnr_novel_pose=0.1, novel_pose_fps=1.0, fps_ratio=1.5
    )
    assert row.meets(1.5, 0.3) and not row.meets(1.51, 0.3) and not row.meets(1.5, 0.29)
    assert not row.meets(1.0, 0.0)  # the glossy scene's "no loss": -0.29 dB is a loss
    row.psnr_novel_view = 0.0
    assert row.meets(1.0, 0.0) and tool.target_words(1.0, 0.0) == ">= 1x at no loss"


def test_missing_checkpoint_is_one_clear_error(tool, tmp_path):
    with pytest.raises(SystemExit, match="--ckpt .*no such checkpoint file"):
        tool.main(["--reference", __file__, "--ckpt", str(tmp_path / "b.ckpt")])
