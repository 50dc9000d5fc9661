"""The learnability probe: it reads the demo cameras' cues back at the environment's rendering."""

import numpy as np
import pytest

from pi0_armfix.sim import render
from pi0_armfix.sim.world import DemoSpec
from pi0_armfix.tools import learnability_probe as probe

SPEC = DemoSpec()


def test_probe_scenes_put_half_the_targets_near_the_goal():
    rng = np.random.default_rng(0)
    _, head = probe.head_scenes(rng, 400, SPEC)
    _, wrist = probe.wrist_scenes(rng, 400, SPEC)
    assert 0.5 < np.mean(head[:, 0] < 4 * SPEC.arrive_radius) < 0.7
    assert 0.5 < np.mean(np.linalg.norm(wrist, axis=1) < 4 * SPEC.reach_tolerance) < 0.85


def test_probe_scenes_render_like_the_environments_cameras():
    scenes, offsets = probe.wrist_scenes(np.random.default_rng(1), 2, SPEC)
    images = render.render_wrist(scenes, "right", 32)
    assert images.shape == (2, 32, 32, 3) and images.dtype == np.uint8
    assert not np.array_equal(images[0], images[1])  # the marker moves with the offset


@pytest.mark.slow  # the slow lane: trains the probe's network
def test_a_short_probe_reads_the_target_distance_from_the_head_camera():
    result = probe.probe_size(32, SPEC, train=800, test=200, steps=150)
    assert result["head"]["distance_rmse_m"] < 0.2  # the targets span 1.5 m
    assert set(result["wrist"]) >= {"offset_rmse_per_axis", "within_tolerance_accuracy_near"}
