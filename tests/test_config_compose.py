"""Every option of every config group composes, every experiment composes, and every component it names exists."""

from __future__ import annotations

import inspect
from importlib import resources

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf

from framework.build import SPLIT_OVERRIDES
from framework.plugins import load_plugins
from framework.registry import REGISTRIES

GROUP_KIND = {
    "data": "dataset",
    "body": "body",
    "corrector": "corrector",
    "deformer": "deformer",
    "rasterizer": "rasterizer",
    "densifier": "densifier",
}


def _options(group: str) -> list[str]:
    folder = resources.files("framework.conf") / group
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def _groups() -> list[str]:
    root = resources.files("framework.conf")
    return sorted(
        p.name
        for p in root.iterdir()
        # experiments, +scene=auto, the trade-off points and the presets are appended with +
        if p.is_dir() and not p.name.startswith("_") and p.name not in ("experiment", "scene", "tradeoff", "preset")
    )


GROUP_OPTIONS = [(g, o) for g in _groups() for o in _options(g)]
EXPERIMENTS = _options("experiment")
TRADEOFF_POINTS = _options("tradeoff")


def _compose(overrides: list[str]):
    """The composed job config, resolved, with the runtime-only `hydra` node split off into `_choices`."""
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name="train", overrides=overrides, return_hydra_config=True)
    choices = dict(cfg.hydra.runtime.choices)
    data = OmegaConf.to_container(cfg, resolve=False)
    data.pop("hydra")
    data["paths"]["output_dir"] = "outputs/compose-test"  # stands in for ${hydra:runtime.output_dir}
    job = OmegaConf.create(data)
    OmegaConf.resolve(job)
    job._choices = choices  # type: ignore[attr-defined]
    return job


def _check_keys(cls: type, node: dict, name: str) -> None:
    """The keys bind to the constructor; those its `**kwargs` takes are fields of the class's `config_schemas` (a
    sequence dataset's keys beyond its layout's: SequenceOptions, and the studio's StudioSettings)."""
    from framework.data.sequence_dataset import SequenceDataset
    from framework.dataset_keys import split_config

    node = {k: v for k, v in node.items() if k != SPLIT_OVERRIDES}
    bound = inspect.signature(cls).bind_partial(**node)
    rest = [p.name for p in inspect.signature(cls).parameters.values() if p.kind is inspect.Parameter.VAR_KEYWORD]
    if rest and issubclass(cls, SequenceDataset):
        split_config(bound.arguments.get(rest[0], {}), *cls.config_schemas, dataset=name)


def _check_components(cfg) -> None:
    """Every named component exists and accepts every key its config node passes to the constructor."""
    load_plugins()
    for group, kind in GROUP_KIND.items():
        node = OmegaConf.to_container(cfg[group])
        name = node.pop("name", None)
        if name is not None:
            assert name in REGISTRIES[kind], f"{group}: '{name}' is not a registered {kind}"
            cls = REGISTRIES[kind].entry(name).cls
            try:
                _check_keys(cls, node, name)
            except (TypeError, ValueError) as exc:
                msg = f"{group}={name}: config keys {sorted(node)} do not fit {cls.__name__}: {exc}"
                raise AssertionError(msg) from None
    for key, spec in cfg.loss.terms.items():
        if float(spec.weight) != 0.0:
            assert spec.get("name", key) in REGISTRIES["loss"], f"loss term '{key}' is not a registered loss"


def test_train_config_has_every_group_and_no_experiment_entry():
    text = (resources.files("framework.conf") / "train.yaml").read_text()
    defaults = OmegaConf.create(text).defaults
    names = [next(iter(d)) if not isinstance(d, str) else d for d in defaults]
    for group in (
        "data",
        "body",
        "gaussians",
        "corrector",
        "deformer",
        "rasterizer",
        "loss",
        "densifier",
        "optim",
        "trainer",
        "logger",
        "callbacks",
        "paths",
    ):
        assert group in names, f"train.yaml does not list the '{group}' group"
    assert "experiment" not in names
    assert names[-1] == "_self_"


@pytest.mark.parametrize(("group", "option"), GROUP_OPTIONS, ids=[f"{g}={o}" for g, o in GROUP_OPTIONS])
def test_every_group_option_composes(group: str, option: str):
    cfg = _compose([f"{group}={option}"])
    assert cfg._choices[group] == option
    _check_components(cfg)


@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_experiment_composes(experiment: str):
    cfg = _compose([f"+experiment={experiment}"])
    assert cfg.task_name == experiment
    _check_components(cfg)


@pytest.mark.parametrize("point", TRADEOFF_POINTS)
def test_every_tradeoff_point_composes(point: str):
    """sweeps/tradeoff.yaml's points are appended like experiments; each names real components with fitting keys."""
    cfg = _compose([f"+tradeoff={point}"])
    assert cfg.task_name == f"tradeoff_{point}"
    _check_components(cfg)


@pytest.mark.parametrize("experiment", ["paper_full", "static_fit"])
def test_scene_auto_composes_with_an_experiment_and_changes_only_the_scene_node(experiment: str):
    """`+scene=auto` is appended like an experiment; what it changes in the model is decided at run time."""
    plain = OmegaConf.to_container(_compose([f"+experiment={experiment}"]))
    auto = OmegaConf.to_container(_compose([f"+experiment={experiment}", "+scene=auto"]))
    assert {k for k in set(auto) | set(plain) if auto.get(k) != plain.get(k)} - {"_choices"} == {"scene"}
    assert auto["scene"]["auto"] and auto["scene"]["survey"] and "thresholds" in auto["scene"]


def test_ablation_rows_differ_from_paper_full_in_one_place():
    """Each Table 4 ablation changes its own row: the composed config differs from paper_full, and only there."""
    full = OmegaConf.to_container(_compose(["+experiment=paper_full"]))
    expected = {
        "no_first_stage": {"stages"},
        "no_joint_optimisation": {"pose_refine"},
        "no_corrector": {"corrector"},
        "posenc_instead_of_latent": {"corrector"},
        "all_sh_correction": {"corrector"},
        "no_alpha_loss": {"loss"},
        "no_weight_std_loss": {"loss"},
        "no_boundary_mask": {"loss"},
        "foreground_only_loss": {"loss"},
    }
    for name, keys in expected.items():
        cfg = OmegaConf.to_container(_compose([f"+experiment={name}"]))
        changed = {k for k in set(cfg) | set(full) if cfg.get(k) != full.get(k)} - {"task_name", "_choices"}
        assert changed == keys, f"{name} changes {changed}, expected {keys}"


@pytest.mark.parametrize("data", ["zju_mocap", "easymocap", "synthetic_studio_gpu", "static_scene"])
def test_paper_full_runs_on_any_dataset_option(data: str):
    """`+experiment=paper_full data=zju_mocap data.root=...` is how real data is trained: the experiment must not
    push keys into the data node that only the synthetic studio understands."""
    cfg = _compose(["+experiment=paper_full", f"data={data}", "data.root=/somewhere"])
    _check_components(cfg)


def test_own_capture_options_compose_with_paper_full():
    """An EasyMocap capture with an SMPL-X body: the data node takes the body's model file and gender (for SMPL-X
    hand PCA poses), and the composed nodes fit their constructors."""
    cfg = _compose(
        [
            "+experiment=paper_full",
            "data=easymocap",
            "data.root=/cap",
            "body=smplx",
            "body.model_path=/models/SMPLX_MALE.pkl",
            "body.gender=male",
        ]
    )
    _check_components(cfg)
    assert cfg.data.body_model_path == "/models/SMPLX_MALE.pkl" and cfg.data.body_gender == "male"
    assert cfg.body.pose_input == "body" and cfg.body.betas is None  # null: the capture's fitted shape
    cfg = _compose(["data=easymocap", "data.root=/cap", "body=procedural"])
    assert cfg.data.body_model_path is None and cfg.data.body_gender == "neutral"


@pytest.mark.parametrize(
    ("data", "body"),
    [("easymocap", "none"), ("easymocap", "smplx"), ("zju_mocap", "smpl"), ("synthetic_studio", "procedural")],
)
def test_check_config_composes(data: str, body: str):
    """`python -m framework.data.check data=... body=...`: its own primary config with the data and body groups
    (every option of those groups is bound to its constructor by test_every_group_option_composes)."""
    with initialize_config_module(config_module="framework.conf", version_base="1.3"):
        cfg = compose(config_name="check", overrides=[f"data={data}", "data.root=/somewhere", f"body={body}"])
    job = OmegaConf.create(OmegaConf.to_container(cfg, resolve=True))
    assert job.data.name == data and job.body.name == (None if body == "none" else body)
    assert job.frames == 8 and 0 < job.min_iou < 1 and 0 < job.min_inside <= 1 and job.out_dir


def test_experiment_wins_over_defaults_and_profile_is_overridable():
    cfg = _compose(["+experiment=static_fit", "profile=gpu"])
    assert cfg.task_name == "static_fit"
    assert cfg.profile.name == "gpu"
    cfg = _compose(["+experiment=paper_full", "profile=cpu"])
    assert cfg.trainer.max_steps == cfg.profile.max_steps


@pytest.mark.parametrize(
    "argv",
    [
        ["train.py"],
        ["train.py", "+experiment=static_fit", "--cfg", "job"],
        ["train.py", "--cfg", "job", "--config-name", "ablations", "+experiment=no_corrector"],
        ["train.py", "-m", "+experiment=static_fit,paper_full", "seed=1"],
    ],
)
def test_profile_is_added_where_hydras_parser_accepts_it(argv: list[str], monkeypatch):
    from hydra._internal.utils import get_args_parser

    from framework.train import choose_profile

    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    out = choose_profile(argv)
    args = get_args_parser().parse_args(out[1:])
    assert "profile=cpu" in args.overrides
    assert [a for a in args.overrides if a != "profile=cpu"] == [a for a in argv[1:] if "=" in a and a[0] != "-"]
    assert choose_profile([*argv, "profile=gpu"]) == [*argv, "profile=gpu"]  # the user's choice wins


def test_gpu_profile_picks_the_gsplat_backend_unless_told_otherwise(monkeypatch):
    import importlib.util

    from framework.train import choose_profile

    monkeypatch.setattr("torch.cuda.is_available", lambda: True)
    real_find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda n, *a: object() if n == "gsplat" else real_find_spec(n, *a))
    assert choose_profile(["t", "+experiment=paper_full"]) == [
        "t",
        "profile=gpu",
        "rasterizer=gsplat",
        "+experiment=paper_full",
    ]
    kept = ["t", "+experiment=paper_full", "rasterizer=jax"]
    assert choose_profile(kept) == ["t", "profile=gpu", "+experiment=paper_full", "rasterizer=jax"]
