"""What a training run does with `scene.*` before it builds the model: survey the data, apply `+scene=auto`'s
choices (leaving keys the user set alone), hold frozen joints at their mean training rotation; and log it all."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from framework.scene.auto import Choice, apply_choices, choices_table, choose, override_keys
from framework.scene.survey import SceneSurvey, cached_survey, survey_body


@dataclass
class SceneSetup:
    survey: SceneSurvey | None = None
    survey_path: Path | None = None
    choices: list[Choice] = field(default_factory=list)
    frozen_pose: dict[str, list[float]] = field(default_factory=dict)

    def log(self, writer: Any, step: int = 0) -> None:
        """The survey's numbers and each choice (value and the number it came from) in TensorBoard."""
        if writer is None or not hasattr(writer, "add_scalar"):
            return
        if self.survey is not None:
            p = self.survey
            writer.add_text("scene/survey", "    " + p.report().replace("\n", "\n    "), step)
            for name in ("view_dependence", "pose_dependence", "pose_noise", "skin_offset_px", "silhouette_px"):
                writer.add_scalar(f"scene/survey/{name}", float(getattr(p, name)), step)
            writer.add_scalar("scene/survey/moving_joints", float(len(p.moving_joints)), step)
        if self.choices:
            writer.add_text("scene/choices", choices_table(self.choices), step)
            for c in self.choices:
                value = len(c.value) if isinstance(c.value, list) else c.value
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    writer.add_scalar(f"scene/choice/{c.key}", float(value), step)

    def summary(self) -> dict[str, Any]:
        return {
            "survey": None if self.survey is None else self.survey.to_dict(),
            "survey_path": None if self.survey_path is None else str(self.survey_path),
            "choices": [
                {
                    "key": c.key,
                    "value": c.value,
                    "measure": c.measure,
                    "rule": c.rule,
                    "by_hand": c.overridden,
                    "applied": c.applied,
                }
                for c in self.choices
            ],
            "frozen_pose": self.frozen_pose,
        }


def command_line_overrides() -> list[str]:
    """This job's command-line overrides (empty outside a Hydra run)."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return list(HydraConfig.get().overrides.task)
    except ValueError:
        return []


def prepare_scene(cfg: DictConfig, train_set, overrides: list[str], progress: bool = True) -> SceneSetup:
    """Survey (scene.survey or scene.auto), apply auto's choices to `cfg` in place (scene.auto), and compute the
    rotations frozen joints are held at (scene.frozen_joints, chosen or given)."""
    from framework.build import build_component

    scene = cfg.scene
    setup = SceneSetup()
    body = None
    if scene.survey or scene.auto:
        body = survey_body(cfg.body, train_set)
        survey, path, cached = cached_survey(
            train_set,
            body,
            max_frames=scene.max_frames,
            blur_px=scene.blur_px,
            moving_deg=scene.moving_deg,
            progress=progress,
        )
        setup.survey, setup.survey_path = survey, path
        print(f"[splatrig] {survey.report()}", file=sys.stderr)
        print(f"[splatrig]   survey {'read from' if cached else 'written to'} {path}", file=sys.stderr)
    if scene.auto:
        if setup.survey is None or body is None:
            raise AssertionError("scene.auto needs the survey")
        root = body.joint_names[int(body.parents.tolist().index(-1))]
        choices = choose(setup.survey, dict(scene.thresholds), root_joint=root)
        setup.choices = apply_choices(cfg, choices, override_keys(overrides))
        for c in setup.choices:
            print(f"[splatrig] scene=auto: {c.line()}", file=sys.stderr)
    frozen = list(scene.frozen_joints)
    poses = train_set.poses()
    if frozen and poses is not None:
        from framework.model.frozen_body import frozen_constants

        if body is None or body.registry_name != cfg.body.name:
            body = build_component("body", cfg.body)
        setup.frozen_pose = frozen_constants(poses[list(train_set.frame_ids)], body.joint_names, frozen)
    return setup
