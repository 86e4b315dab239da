"""`python -m framework.survey data=NAME [data.root=...]`: what a capture needs, measured from the data alone.

Prints the scene survey (which joints move, views, frames, silhouette area, view- and pose-dependent colour, how
well the body mesh follows the masks) and what `+scene=auto` would choose from it, and writes the survey as YAML
beside the dataset (training with `scene.survey=true` or `+scene=auto` reads it back instead of measuring again).
"""

from __future__ import annotations

import os
import sys

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as framework.train: no spinning OpenMP threads on a busy CPU

from omegaconf import DictConfig

from framework.errors import reported_as_message


def run(cfg: DictConfig) -> None:
    from framework.build import build_split
    from framework.plugins import load_plugins
    from framework.scene.auto import choose
    from framework.scene.survey import cached_survey, survey_body

    load_plugins()
    dataset = build_split(cfg.data, "train")
    body = survey_body(cfg.body, dataset)
    s = cfg.scene
    survey, path, cached = cached_survey(
        dataset,
        body,
        max_frames=int(s.max_frames),
        blur_px=float(s.blur_px),
        moving_deg=float(s.moving_deg),
        force=bool(cfg.force),
    )
    print(survey.report())
    print(f"  survey {'read from' if cached else 'written to'} {path}\n")
    root = body.joint_names[body.parents.tolist().index(-1)]
    print("what +scene=auto would choose (thresholds: conf/scene/auto.yaml):")
    for choice in choose(survey, dict(s.thresholds), root_joint=root):
        print(f"  {choice.line()}")


def main() -> None:
    from framework.cli import hydra_main
    from framework.train import choose_profile

    sys.argv = choose_profile(sys.argv)  # the synthetic studio's size follows the hardware profile, as in training

    @hydra_main("survey")
    def _main(cfg: DictConfig) -> None:
        with reported_as_message():
            run(cfg)

    _main()


if __name__ == "__main__":
    main()
