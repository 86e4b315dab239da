"""`+scene=auto`: turn a scene survey into model choices, each printed with the number it came from, each
overridable from the command line (a key the user set is never touched).

Rules (thresholds in `conf/scene/auto.yaml`, under `scene.thresholds`):
- frozen joints: every joint (but the root) whose rotation range over the training frames is at most `moving_deg`
  (`scene.frozen_joints`; they leave F_a's pose input and the LBS sum, see `framework.model.frozen_body`).
- SH degree: the number of `sh_view_dependence` thresholds the view-dependent colour spread exceeds (0 for matte
  cloth, 3 only for strongly view-dependent appearance), at least `min_sh_degree` (`gaussians.sh_degree`).
- corrector F_a: switched off (`corrector=none`) when the pose-dependent colour spread is below
  `corrector_pose_dependence` (set at the noise floor: F_a measured worth keeping in training even for a near-static
  capture; pruning folds a corrector whose output hardly varies, `framework.compaction.corrector_fold`).
- F_a at compaction: kept whole (`scene.fold_corrector=false`, read by `framework.prune`'s `fold_tolerance=auto`)
  when the pose-dependent colour spread reaches `corrector_fold_pose_dependence`. Folding checks the training poses
  it averages over; where appearance follows the pose, novel poses need F_a's per-pose output (a partial fold cost
  about 0.1 dB on the studio's walking and glossy scenes and bought little frame rate).
- F_a's width: `corrector_narrow_hidden` (`corrector.hidden`, the paper's 128 otherwise) when the pose-dependent
  colour spread is below `corrector_narrow_pose_dependence`: a scene whose appearance changes little with the pose
  needs a smaller function of it, and F_a runs on every Gaussian at every novel pose.
- weight residual F_dw: switched off (`deformer=lbs`) when the body mesh's silhouette sits within
  `weight_residual_skin_offset_px` of the masks (the surface follows the body model's skinning).
- Gaussian budget: `gaussians_per_silhouette_px` x the mean silhouette area in pixels at the training resolution (the
  visible surface at the image's sampling density), at least `min_gaussians` (`gaussians.num`), and densification
  capped at `max_gaussians_factor` times that (`densifier.max_gaussians`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib import resources
from typing import Any

from omegaconf import DictConfig, OmegaConf, open_dict

from framework.scene.survey import SceneSurvey

COMPONENT_KEYS = ("corrector", "deformer")


@dataclass
class Choice:
    """One auto decision: the config key it sets, the value, and the measurement and rule behind it."""

    key: str  # config key (a group name for component switches)
    value: Any  # the value auto chose; None = leave the configured value
    measure: str  # "view dependence 0.0120"
    rule: str  # "<= 0.03: degree 0"
    aliases: tuple[str, ...] = ()  # other keys whose override counts as setting this one by hand
    overridden: bool = False
    applied: bool = False

    def line(self) -> str:
        shown = "kept as configured" if self.value is None else f"{self.key}={_show(self.value)}"
        if self.overridden:
            return f"{self.key}: set by hand (auto would choose {_show(self.value)}: {self.measure}, {self.rule})"
        return f"{shown}  <- {self.measure} ({self.rule}); override with {self.key}=..."


def _show(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(str(v) for v in value) + "]"
    return "keep" if value is None else str(value)


def choose(survey: SceneSurvey, thresholds: dict[str, Any], root_joint: str | None = None) -> list[Choice]:
    """The choices a survey supports (see the module docstring); `root_joint` is never frozen."""
    t = thresholds
    still = [n for n in survey.still_joints if n != root_joint]
    largest = max((survey.joints[n] for n in still), default=0.0)
    ranges = f"{len(still)} joints with a rotation range <= {largest:.1f}°" if still else "every joint moves"
    sh_levels = [float(x) for x in t["sh_view_dependence"]]
    floor = int(t.get("min_sh_degree", 0))
    degree = max(floor, sum(survey.view_dependence > x for x in sh_levels))
    corrector_need = survey.pose_dependence >= float(t["corrector_pose_dependence"])
    keep_corrector = survey.pose_dependence >= float(t["corrector_fold_pose_dependence"])
    narrow_below = t.get("corrector_narrow_pose_dependence")  # absent (thresholds from before it): never narrowed
    narrow = corrector_need and narrow_below is not None and survey.pose_dependence < float(narrow_below)
    if not corrector_need:
        width_rule = "F_a off"
    elif narrow_below is None:
        width_rule = "no narrowing threshold: width as configured"
    else:
        width_rule = (
            f"< {narrow_below}: width {t['corrector_narrow_hidden']}"
            if narrow
            else f">= {narrow_below}: width as configured"
        )
    residual_need = survey.skin_offset_px >= float(t["weight_residual_skin_offset_px"])
    num = max(int(t["min_gaussians"]), int(round(float(t["gaussians_per_silhouette_px"]) * survey.silhouette_px)))
    cap = int(round(float(t["max_gaussians_factor"]) * num))
    return [
        Choice("scene.frozen_joints", still, ranges, f"<= {survey.moving_deg:g}°: frozen"),
        Choice(
            "gaussians.sh_degree",
            degree,
            f"view dependence {survey.view_dependence:.4f}",
            f"thresholds {sh_levels}, at least {floor}: degree {degree}",
        ),
        Choice(
            "corrector",
            None if corrector_need else "none",
            f"pose dependence {survey.pose_dependence:.4f}",
            f"{'>=' if corrector_need else '<'} {t['corrector_pose_dependence']}: "
            f"{'F_a kept' if corrector_need else 'F_a off'}",
        ),
        Choice(
            "scene.fold_corrector",
            not keep_corrector,
            f"pose dependence {survey.pose_dependence:.4f}",
            f"{'>=' if keep_corrector else '<'} {t['corrector_fold_pose_dependence']}: "
            f"{'F_a kept whole at compaction' if keep_corrector else 'compaction may fold F_a'}",
        ),
        Choice(
            "corrector.hidden",
            int(t["corrector_narrow_hidden"]) if narrow else None,
            f"pose dependence {survey.pose_dependence:.4f}",
            width_rule,
        ),
        Choice(
            "deformer",
            None if residual_need else "lbs",
            f"skin offset {survey.skin_offset_px:.2f} px",
            f"{'>=' if residual_need else '<'} {t['weight_residual_skin_offset_px']} px: "
            f"{'F_dw kept' if residual_need else 'F_dw off'}",
        ),
        Choice(
            "gaussians.num",
            num,
            f"silhouette {survey.silhouette_px:.0f} px at {survey.width}x{survey.height}",
            f"x {t['gaussians_per_silhouette_px']} per px, >= {t['min_gaussians']}",
            aliases=("profile.num_gaussians",),
        ),
        Choice(
            "densifier.max_gaussians",
            cap,
            f"budget {num}",
            f"x {t['max_gaussians_factor']}",
            aliases=("profile.max_gaussians",),
        ),
    ]


def override_keys(overrides: list[str]) -> set[str]:
    """Config keys named by command-line overrides (`+a.b=1`, `corrector=none`, `~x`), hydra.* left out."""
    keys = set()
    for item in overrides:
        key = re.split(r"[=]", item, maxsplit=1)[0].lstrip("+~").strip()
        if key and not key.startswith("hydra."):
            keys.add(key.split("@")[0])
    return keys


def _set_by_hand(choice: Choice, user_keys: set[str]) -> bool:
    """A component switch is set by choosing the component (`corrector=latent`, `corrector.name=...`); tuning one of
    its options (`deformer.grid_resolution=32`) is not a choice of the component. Other keys: the key or a sub-key."""
    for key in (choice.key, *choice.aliases):
        if choice.key in COMPONENT_KEYS:
            if key in user_keys or f"{key}.name" in user_keys:
                return True
        elif any(u == key or u.startswith(key + ".") for u in user_keys):
            return True
    return False


def group_option(group: str, option: str, current: dict[str, Any]) -> dict[str, Any]:
    """The YAML of conf/<group>/<option>.yaml, with the values of keys it shares with the current node kept."""
    node = OmegaConf.to_container(OmegaConf.load(str(resources.files("framework.conf") / group / f"{option}.yaml")))
    assert isinstance(node, dict)
    return {k: current.get(k, v) if k != "name" else v for k, v in node.items()}


def apply_choices(cfg: DictConfig, choices: list[Choice], user_keys: set[str]) -> list[Choice]:
    """Write each choice into `cfg` unless the user set its key (marked `overridden`); returns the choices."""
    for choice in choices:
        if _set_by_hand(choice, user_keys):
            choice.overridden = True
            continue
        if choice.value is None:
            continue
        with open_dict(cfg):
            if choice.key in COMPONENT_KEYS:
                current = OmegaConf.to_container(cfg[choice.key], resolve=True)
                assert isinstance(current, dict)
                if current.get("name") == choice.value:
                    continue
                if choice.key == "deformer" and current.get("name") != "lbs_residual":
                    continue  # only the residual deformer has an F_dw to switch off
                cfg[choice.key] = group_option(choice.key, str(choice.value), current)
            elif choice.key.split(".")[0] in COMPONENT_KEYS and OmegaConf.select(cfg, choice.key) is None:
                continue  # an option of a component the configuration does not have (F_a's width, F_a set off)
            else:
                OmegaConf.update(cfg, choice.key, choice.value, merge=False, force_add=True)
        choice.applied = True
    return choices


def choices_table(choices: list[Choice]) -> str:
    """Markdown table of the choices (for TensorBoard's text tab and the run folder)."""
    rows = ["| key | value | from | rule | by hand |", "|---|---|---|---|---|"]
    for c in choices:
        rows.append(f"| {c.key} | {_show(c.value)} | {c.measure} | {c.rule} | {'yes' if c.overridden else ''} |")
    return "\n".join(rows)
