"""Landing-target mode's pad tracker: when a LANDING_TARGET is streamed (companion.landing_target).

The stream follows the pad estimator's own fixes: a bearing at the visibility threshold, or one
the estimator takes by the rule it flies by in offboard mode (a start at ``acquire_threshold``,
an unsure fix its gate accepts). Real frames of the simulator's camera, the shipped CNN."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.landing_target import PadTracker
from companion.packaged import shipped_policy
from companion.policy_net import load_policy
from companion.runtime import level_observation
from sitl_sim.config import load_sim
from sitl_sim.render.ground import PadGeometry, nominal_ground
from sitl_sim.render.scene import Camera, make_renderer


@pytest.fixture(scope="module")
def frames():
    """Level frames 30 m above the paper's pad (0.5 m north of it), at 10 Hz."""
    camera = load_sim().camera
    scene = make_renderer(camera.renderer)
    try:
        scene.configure(nominal_ground(), PadGeometry(), None)
        cam = Camera(scene, camera, np.random.default_rng(3))
        pos, level = np.array([0.5, 0.0, -30.0]), np.array([1.0, 0.0, 0.0, 0.0])
        yield [cam.capture(pos, level) for _ in range(20)]
    finally:
        scene.close()


def _track(policy, images):
    tracker = PadTracker(policy)
    return [
        tracker.step(level_observation(30.0, time_s=0.1 * k, image=img, frame_id=k))
        for k, img in enumerate(images)
    ]


def test_the_shipped_model_tracks_the_pad_it_sees(frames):
    results = _track(load_policy(shipped_policy()), frames)
    assert all(r.seen and r.error is None for r in results)
    assert results[0].visibility >= 0.9
    rel = results[-1].target_rel_ned_m
    assert rel is not None and abs(rel[0] + 0.5) < 0.3 and abs(rel[1]) < 0.3  # pad 0.5 m south


def test_a_pad_below_the_visibility_threshold_streams_on_the_estimators_fixes(frames):
    """A CNN unsure of a pad it places right (a carried pad at 75-100 m sits between the
    thresholds): the estimator starts at ``acquire_threshold`` and goes on with gated unsure
    fixes; the stream follows it. Before, it waited for ``visibility_threshold`` and a
    landing-target flight never started."""
    shipped = load_policy(shipped_policy())
    cfg = replace(shipped.config, visibility_threshold=0.99999, acquire_threshold=0.5)
    unsure = replace(shipped, config=cfg)
    results = _track(unsure, frames)
    assert all(r.visibility < 0.99999 for r in results)
    assert all(r.seen for r in results)
    rel = results[-1].target_rel_ned_m
    assert rel is not None and abs(rel[0] + 0.5) < 0.3 and abs(rel[1]) < 0.3
    # no pad in view: nothing is seen and nothing is streamed, whatever the thresholds
    grey = [np.full_like(frames[0], 96)] * 10
    for policy in (shipped, unsure):
        assert not any(r.seen or r.target_rel_ned_m is not None for r in _track(policy, grey))
