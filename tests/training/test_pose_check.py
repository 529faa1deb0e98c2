"""Whether a training view that fits far worse has a wrong pose (training/pose_check.py): its
camera fitted alone against the trained model."""
import dataclasses

import numpy as np
import pytest

from mi_nerfpp.core.poses import rotation_matrix
from mi_nerfpp.data import load_dataset
from mi_nerfpp.data.dataset import Split
from mi_nerfpp.training.config import TrainConfig
from mi_nerfpp.training.pose_check import WRONG, check_outliers, check_pose, registered
from mi_nerfpp.training.raybank import RayBank
from mi_nerfpp.training.train import Trainer

SMALL = dict(batch_rays=512, fg_samples=16, bg_samples=16, fine_samples=16,
             checkpoint_every=0, preview_every=0)
VIEW = 3
TURN = 4.0          # degrees: about two pixels of the 32x24 capture


@pytest.fixture(scope='module')
def trained(capture, tmp_path_factory):
    trainer = Trainer(load_dataset(capture), str(tmp_path_factory.mktemp('pose_check')),
                      TrainConfig.from_options(iterations=300, **SMALL))
    assert trainer.run()
    return trainer


def _turned(split, view, degrees, axis):
    """``split`` with camera ``view`` turned by ``degrees`` about ``axis`` (its centre kept)."""
    cameras = list(split.cameras)
    c2w = cameras[view].c2w.copy()
    c2w[:3, :3] = rotation_matrix(np.radians(degrees) * np.asarray(axis, float)) @ c2w[:3, :3]
    cameras[view] = dataclasses.replace(cameras[view], c2w=c2w)
    return dataclasses.replace(split, cameras=cameras)


def test_a_turned_camera_is_named_and_turned_back_and_a_right_one_is_left(trained):
    right = check_pose(trained.model, trained.rays.level(1), VIEW, seed=1)
    assert not right.wrong_pose and right.kept > WRONG, right
    assert right.turn_degrees < 0.5 * TURN, right
    axis = np.array([0.3, 1.0, 0.2])
    turned = RayBank(_turned(trained.train, VIEW, TURN, axis / np.linalg.norm(axis)))
    wrong = check_pose(trained.model, turned, VIEW, seed=1)
    assert wrong.before > 2 * right.before, (wrong, right)     # the turn shows in the error
    assert wrong.wrong_pose and wrong.kept < WRONG, wrong
    assert abs(wrong.turn_degrees - TURN) < 0.5 * TURN, wrong  # and is mostly taken back
    # The model is left as it was: the right camera scores as before.
    again = check_pose(trained.model, trained.rays.level(1), VIEW, steps=0, seed=1)
    assert again.before == pytest.approx(right.before, rel=1e-5)


def test_only_the_named_outliers_are_checked(trained):
    names = [f'v{i}.png' for i in range(len(trained.train))]
    signs = {'views': [{'name': n} for n in names], 'outliers': [names[VIEW]]}
    checks = check_outliers(trained, signs)
    assert list(checks) == [names[VIEW]]
    assert set(checks[names[VIEW]]) == {'error_kept', 'turn_degrees', 'shift', 'wrong_pose'}
    assert check_outliers(trained, {'views': signs['views'], 'outliers': []}) == {}


def _turn_between(a, b) -> float:
    """Degrees between the rotations of two 4x4 camera-to-world matrices."""
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))))


def test_cameras_rendered_neutral_are_registered_back_to_their_true_poses(trained):
    # Three training views as a split of their own (registered() renders them neutral, as it
    # renders held-out views: no learned correction); the middle one turned.
    views = (VIEW - 1, VIEW, VIEW + 1)
    split = Split([trained.train.cameras[v] for v in views], [''] * 3,
                  [trained.train.images[v] for v in views])
    axis = np.array([1.0, 0.2, -0.4])
    turned = _turned(split, 1, TURN, axis / np.linalg.norm(axis))
    fitted = registered(trained.model, turned)
    true = split.cameras
    assert _turn_between(turned.cameras[1].c2w, true[1].c2w) == pytest.approx(TURN)
    assert _turn_between(fitted.cameras[1].c2w, true[1].c2w) < 0.5 * TURN
    for v in (0, 2):                # views at their true poses stay near them
        assert _turn_between(fitted.cameras[v].c2w, true[v].c2w) < 0.5 * TURN
    assert fitted.images is turned.images
