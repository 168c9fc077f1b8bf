"""The stages' host-side optimiser state and checkpoints: known answers, round trips, refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from taichi_gs.stages import checkpoint
from taichi_gs.stages.refine import PRESETS
from taichi_gs.stages.row_adam import RowAdam


def test_row_adam_matches_the_adam_update_written_out():
    adam = RowAdam(3, (2,), beta1=0.9, beta2=0.999, eps=1e-8)
    grads = [np.array([0.5, -2.0]), np.array([0.1, 1.0]), np.array([-0.3, 0.2])]
    m, v, value = np.zeros(2), np.zeros(2), np.array([1.0, 1.0])
    for t, g in enumerate(grads, start=1):
        m, v = 0.9 * m + 0.1 * g, 0.999 * v + 0.001 * g**2
        value = value - 0.01 * (m / (1 - 0.9**t)) / (np.sqrt(v / (1 - 0.999**t)) + 1e-8)
    got = np.array([1.0, 1.0])
    for g in grads:
        got = adam.step(1, got, g, 0.01)
    np.testing.assert_allclose(got, value, rtol=1e-12)
    assert adam.steps.tolist() == [0, 3, 0]  # only the stepped row moved
    assert not adam.moments[0].any() and not adam.moments[2].any()


def test_row_adam_state_round_trips_and_refuses_another_shape():
    adam = RowAdam(2, (2, 6))
    adam.step(0, np.zeros((2, 6)), np.ones((2, 6)), 0.1)
    restored = RowAdam(2, (2, 6))
    restored.load_state(adam.state("exposure"), "exposure")
    np.testing.assert_array_equal(restored.moments, adam.moments)
    np.testing.assert_array_equal(restored.steps, adam.steps)
    with pytest.raises(ValueError, match="shape"):
        RowAdam(3, (2, 6)).load_state(adam.state("exposure"), "exposure")


def test_checkpoint_round_trip_and_config_match(tmp_path):
    path = tmp_path / "checkpoint.npz"
    config = PRESETS["fast"]
    arrays = {"poses": np.eye(4)[None].repeat(3, 0), **checkpoint.prefixed("model", {"means": np.ones((5, 3))})}
    checkpoint.save(path, 40, config, arrays, {"history": [{"iteration": 10, "depth": 0.5}], "rng": {"state": 7}})
    saved = checkpoint.load(path, config)
    assert saved is not None and saved.iteration == 40
    np.testing.assert_array_equal(saved.arrays["poses"], arrays["poses"])
    np.testing.assert_array_equal(saved.prefixed("model")["means"], np.ones((5, 3)))
    assert saved.records == {"history": [{"iteration": 10, "depth": 0.5}], "rng": {"state": 7}}
    assert checkpoint.load(path, dataclasses.replace(config, seed=config.seed + 1)) is None  # another run's
    assert checkpoint.load(tmp_path / "none.npz", config) is None
    np.savez(tmp_path / "old.npz", iteration=40, config=np.array("{}"))  # an earlier layout: not resumed
    assert checkpoint.load(tmp_path / "old.npz", config) is None
    with pytest.raises(ValueError, match="reserved"):
        checkpoint.save(path, 1, config, {"iteration": np.zeros(1)}, {})
