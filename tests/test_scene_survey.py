"""The scene survey (`framework.scene.survey`) on studio captures whose content is known by construction."""

from __future__ import annotations

import math

import pytest
import torch

from framework.plugins import load_plugins
from framework.registry import BODIES
from framework.scene.survey import (
    SurveyError,
    cached_survey,
    joint_rotation_ranges,
    survey_dataset,
)

load_plugins()
ARM_JOINTS = {"upperarm.L", "lowerarm.L", "upperarm.R", "lowerarm.R"}  # what motions.arm_raises drives


def _studio(tmp_path_factory, **kwargs):
    from plugins.dataset.synthetic_studio import SyntheticStudioDataset

    settings = {"resolution": 64, "num_views": 4, "num_frames": 6, "body": "procedural", "supersample": 1, "workers": 1}
    settings.update(kwargs)
    name = "_".join(f"{k}{v}" for k, v in sorted(kwargs.items())) or "base"
    return SyntheticStudioDataset(root=str(tmp_path_factory.mktemp("studio") / name), **settings)


@pytest.fixture(scope="module")
def body():
    return BODIES.build("procedural")


@pytest.fixture(scope="module")
def looks(tmp_path_factory, body):
    """Surveys of the same arms-only capture in matte and glossy cloth, and of a near-static capture (128 px)."""
    size = {"resolution": 128, "num_views": 8, "num_frames": 4}
    out = {}
    for name, kwargs in {
        "matte": {"motion": "arms"},
        "glossy": {"motion": "arms", "look": "glossy"},
        "idle": {"motion": "idle"},
    }.items():
        out[name] = survey_dataset(_studio(tmp_path_factory, **size, **kwargs), body, progress=False)
    return out


def test_survey_of_an_arms_only_capture_reports_exactly_the_arm_joints(tmp_path_factory, body):
    dataset = _studio(tmp_path_factory, motion="arms")
    survey, path, cached = cached_survey(dataset, body, progress=False)
    assert not cached and path.parent == dataset.root and path.suffix == ".yaml"
    assert set(survey.moving_joints) == ARM_JOINTS
    assert all(survey.joints[n] == 0.0 for n in survey.still_joints)  # untouched joints have no motion at all
    assert survey.views == len(dataset.views) and survey.frames == len(dataset.frame_ids)
    assert 0 < survey.silhouette_fraction < 0.5 and set(survey.silhouette_px_per_view) == set(dataset.views)
    again, path2, cached2 = cached_survey(dataset, body, progress=False)
    assert cached2 and path2 == path and again == survey  # read back from the YAML, field for field


def test_joint_rotation_range_is_the_largest_angle_between_two_frames():
    poses = torch.zeros(4, 3, 3)
    poses[:, 1, 2] = torch.tensor([0.0, 0.2, 0.7, 0.4])  # about z: 0..0.7 rad
    poses[1, 2] = torch.tensor([0.1, 0.0, 0.0])  # about x, +0.1 then -0.1: 0.2 rad apart
    poses[3, 2] = torch.tensor([-0.1, 0.0, 0.0])
    ranges = joint_rotation_ranges(poses)
    assert ranges.tolist() == pytest.approx([0.0, 0.7, 0.2], abs=1e-6)


def test_view_dependence_rises_with_a_specular_highlight(looks):
    """Matte cloth varies across views only by resampling; a highlight that moves with the viewer varies more."""
    assert looks["glossy"].view_dependence > 1.8 * looks["matte"].view_dependence > 0


def test_pose_dependence_separates_a_near_static_capture(looks):
    """Arm raises fold and re-light the cloth; a slight sway barely changes it."""
    assert looks["matte"].pose_dependence > 3 * looks["idle"].pose_dependence
    assert set(looks["idle"].moving_joints) <= {"head", "upperarm.L", "upperarm.R"}


def test_skin_offset_grows_when_the_mesh_leaves_the_masks(tmp_path_factory, body):
    """The stored mesh is the rendered surface (offset ~0); shrunk by 20% about its centre, it misses the masks."""
    dataset = _studio(tmp_path_factory, motion="arms", resolution=96)
    exact = survey_dataset(dataset, body, max_frames=2, progress=False)
    original = dataset.vertices

    def shrunk(frame: int) -> torch.Tensor:
        v = original(frame)
        return v.mean(0) + 0.8 * (v - v.mean(0))

    dataset.vertices = shrunk
    moved = survey_dataset(dataset, body, max_frames=2, progress=False)
    assert exact.skin_offset_px < 0.25 < 1.0 < moved.skin_offset_px
    assert math.isclose(exact.silhouette_px, moved.silhouette_px)  # the masks did not change


def test_a_dataset_without_a_body_cannot_be_surveyed(body):
    class Static:
        registry_name = "static_scene"

        def poses(self):
            return None

    with pytest.raises(SurveyError, match="data=static_scene: the scene survey needs a body dataset"):
        survey_dataset(Static(), body)
