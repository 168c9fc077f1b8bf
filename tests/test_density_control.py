"""Stage 3's adaptive density control on hand-made scenes: which Gaussians are cloned, split or
pruned given their positional-gradient statistics and scales, that Adam moments follow their
Gaussians through the surgery, and the opacity reset."""

from __future__ import annotations

import numpy as np
import pytest

from taichi_gs.geometry import quat_to_rotmat
from taichi_gs.splats import Splats, logit
from taichi_gs.stages.deblur.density_control import DensitySchedule, heavier_than_share, reset_opacity
from taichi_gs.stages.deblur.model import TRAINED, BlurScene

K = np.array([[30.0, 0.0, 16.0], [0.0, 30.0, 12.0], [0.0, 0.0, 1.0]])
SPLIT_SCALE, MIN_OPACITY, MAX_SCALE, THRESHOLD = 0.01, 0.005, 0.2, 1.0


def _scene() -> Splats:
    """Six Gaussians, each with its own fate under the thresholds above (see ``GRAD``):
    0 small + large gradient: cloned; 1 large + large gradient: split; 2 small, small gradient: kept;
    3 nearly transparent: pruned; 4 oversize: pruned; 5 large, gradient just below the threshold: kept."""
    n = 6
    means = np.stack([np.arange(n) * 0.3 - 0.75, np.linspace(-0.2, 0.2, n), np.full(n, 3.0)], axis=1)
    scales = np.array([[0.005, 0.004, 0.006], [0.05, 0.02, 0.03], [0.004] * 3, [0.02] * 3, [0.5, 0.05, 0.05],
                       [0.03, 0.05, 0.02]])
    quats = np.array([[1, 0, 0, 0], [0.9, 0.3, -0.2, 0.1], [1, 0, 0, 0], [1, 0, 0, 0], [1, 0, 0, 0], [0.8, 0, 0.6, 0]])
    quats = quats / np.linalg.norm(quats, axis=1, keepdims=True)
    opacity = np.array([0.6, 0.8, 0.5, 0.001, 0.7, 0.4])
    colors = (np.arange(n * 3).reshape(n, 1, 3) * 0.1).astype(np.float32)
    return Splats(means.astype(np.float32), quats.astype(np.float32), np.log(scales).astype(np.float32),
                  logit(opacity).astype(np.float32), colors)


GRAD = np.array([3.0, 2.0, 0.5, 0.2, 0.1, 0.99])  # mean image-plane gradient (px) of each Gaussian


def _model(grad_mean: np.ndarray = GRAD) -> BlurScene:
    model = BlurScene(_scene(), K, 32, 24)
    model.density.grad_count = np.full(model.count, 4.0)
    model.density.grad_sum = grad_mean * model.density.grad_count
    # distinctive Adam moments: row i of every parameter holds i + 1 (first) and 10 (i + 1) (second)
    for name, (m, v) in model.store.adam.moments.items():
        shape = m.shape
        rows = np.arange(1, shape[0] + 1, dtype=np.float32).reshape((-1,) + (1,) * (len(shape) - 1))
        m.from_numpy(np.ascontiguousarray(np.broadcast_to(rows, shape), np.float32))
        v.from_numpy(np.ascontiguousarray(np.broadcast_to(10 * rows, shape), np.float32))
    model.store.adam.t = 7
    return model


def _densify(model: BlurScene, seed: int = 0, max_gaussians: int = 100) -> tuple[int, int]:
    return model.density.densify_and_prune(model.store, THRESHOLD, SPLIT_SCALE, MIN_OPACITY, MAX_SCALE, max_gaussians,
                                   np.random.default_rng(seed))


def test_clone_split_prune_known_answer():
    model = _model()
    before = model.arrays()
    added, removed = _densify(model, seed=3)
    after = model.arrays()
    assert (added, removed) == (2, 2)
    assert model.count == 6  # 6 + clone of 0 + split of 1 - pruned 3 and 4
    # order: survivors [0, 1, 2, 5], then the clone of 0, then the second half of 1's split
    origin = [0, 1, 2, 5, 0, 1]
    for name in TRAINED:
        if name in ("means", "log_scales"):
            continue
        np.testing.assert_array_equal(after[name], before[name][origin], err_msg=name)
    for row in (0, 2, 3, 4):  # untouched or cloned: identical position and size
        np.testing.assert_array_equal(after["means"][row], before["means"][origin[row]])
        np.testing.assert_array_equal(after["log_scales"][row], before["log_scales"][origin[row]])

    # split: two samples of the old Gaussian, mirrored about its centre, each 1.6x smaller
    offset = after["means"][5] - before["means"][1]
    np.testing.assert_allclose(after["means"][1], before["means"][1] - offset, atol=1e-6)
    scales = np.exp(before["log_scales"][1].astype(np.float64))
    expected = quat_to_rotmat(before["quats"][1:2])[0] @ (np.random.default_rng(3).normal(size=(1, 3))[0] * scales)
    np.testing.assert_allclose(offset, expected, rtol=1e-4, atol=1e-7)
    for row in (1, 5):
        np.testing.assert_allclose(after["log_scales"][row], before["log_scales"][1] - np.log(1.6), atol=1e-6)

    # every kept Gaussian still has an opacity >= the floor and a scale <= the cap
    assert np.all(after["opacity_logits"] >= logit(MIN_OPACITY))
    assert np.all(after["log_scales"].max(axis=1) <= np.log(MAX_SCALE))
    # statistics restart; the Adam step count survives
    np.testing.assert_array_equal(model.density.grad_sum, np.zeros(6))
    np.testing.assert_array_equal(model.density.grad_count, np.zeros(6))
    assert model.store.adam.t == 7


def test_adam_moments_follow_their_gaussians():
    model = _model()
    _densify(model)
    for name, (m, v) in model.store.adam.moments.items():
        first, second = m.to_numpy()[: model.count], v.to_numpy()[: model.count]
        row_ids = first.reshape(model.count, -1)
        # survivors keep their own moments (original rows 0, 1, 2, 5 held 1, 2, 3, 6); new rows start at 0
        np.testing.assert_array_equal(row_ids[:, 0], [1, 2, 3, 6, 0, 0], err_msg=name)
        assert np.all(row_ids == row_ids[:, :1]), name
        np.testing.assert_array_equal(second, 10 * first, err_msg=name)


def test_growth_respects_the_cap_largest_gradient_first():
    model = _model()
    added, removed = _densify(model, max_gaussians=7)  # room for one: Gaussian 0 (gradient 3.0) wins
    assert (added, removed) == (1, 2)
    after = model.arrays()
    assert model.count == 5
    np.testing.assert_array_equal(after["means"][4], after["means"][0])  # the clone of 0
    assert model.arrays()["log_scales"][1] == pytest.approx(_scene().log_scales[1])  # 1 not split

    full = _model()
    assert _densify(full, max_gaussians=6) == (0, 2)  # no room: nothing grows, pruning still runs


def test_rows_given_by_error_grow_after_the_gradients_in_their_order():
    model = _model()
    before = model.arrays()
    # 0 and 1 grow by gradient; 1 is given again (grows once), then 2 and 5 by error, 2 first
    added, removed = model.density.densify_and_prune(model.store, THRESHOLD, SPLIT_SCALE, MIN_OPACITY, MAX_SCALE, 9,
                                                     np.random.default_rng(0), also=np.array([1, 2, 5]))
    assert (added, removed) == (3, 2)  # room for three: 0, 1 (gradient), then 2; 5 is left out
    after = model.arrays()
    # survivors 0, 1 (split: its first half stays in place), 2, 5, then 0's clone, 2's clone, 1's second half
    np.testing.assert_array_equal(after["means"][4], before["means"][0])
    np.testing.assert_array_equal(after["means"][5], before["means"][2])
    assert after["log_scales"][1] == pytest.approx(before["log_scales"][1] - np.log(1.6))
    assert after["log_scales"][3] == pytest.approx(before["log_scales"][5])  # 5 untouched


def test_nothing_above_threshold_only_prunes():
    model = _model(np.zeros(6))
    before = model.arrays()
    assert _densify(model) == (0, 2)
    np.testing.assert_array_equal(model.arrays()["means"], before["means"][[0, 1, 2, 5]])


def test_reset_opacity_clamps_and_forgets_opacity_moments():
    model = _model()
    before = model.arrays()
    moments_before = {name: (m.to_numpy(), v.to_numpy()) for name, (m, v) in model.store.adam.moments.items()}
    reset_opacity(model.store, 0.01)
    after = model.arrays()
    opacity = 1 / (1 + np.exp(-after["opacity_logits"].astype(np.float64)))
    was = 1 / (1 + np.exp(-before["opacity_logits"].astype(np.float64)))
    np.testing.assert_allclose(opacity[was > 0.01], 0.01, rtol=1e-5)
    np.testing.assert_array_equal(after["opacity_logits"][was <= 0.01], before["opacity_logits"][was <= 0.01])
    assert (was > 0.01).sum() == 5 and (was <= 0.01).sum() == 1
    for name in TRAINED:
        if name != "opacity_logits":
            np.testing.assert_array_equal(after[name], before[name], err_msg=name)
    for name, (m, v) in model.store.adam.moments.items():
        if name == "opacity_logits":
            assert not m.to_numpy().any() and not v.to_numpy().any()
        else:
            np.testing.assert_array_equal(m.to_numpy(), moments_before[name][0], err_msg=name)
            np.testing.assert_array_equal(v.to_numpy(), moments_before[name][1], err_msg=name)


def test_the_store_carries_moments_through_keep_append_and_reset():
    from taichi_gs.gaussian_store import GaussianStore

    model = _model()
    store = GaussianStore(model.arrays(), TRAINED)
    for name, (m, v) in model.store.moments().items():
        store.adam.moments[name][0].from_numpy(np.ascontiguousarray(m))
        store.adam.moments[name][1].from_numpy(np.ascontiguousarray(v))
    store.adam.t = 7
    store.keep(np.array([True, False, True, True, False, True]))
    rows = {name: value[:1] for name, value in store.arrays().items()}
    store.append(rows)
    assert store.count == 5 and store.adam.t == 7
    for name, (m, v) in store.moments().items():
        lead = m.reshape(5, -1)[:, 0]
        np.testing.assert_array_equal(lead, [1, 3, 4, 6, 0], err_msg=name)  # survivors' rows, then a fresh one
        np.testing.assert_array_equal(v.reshape(5, -1)[:, 0], [10, 30, 40, 60, 0], err_msg=name)
    store.reset("colors", np.zeros((5, 1, 3)))
    assert not store.moments()["colors"][0].any() and store.moments()["means"][0].any()
    restored = GaussianStore(model.arrays(), TRAINED)
    restored.load_state(store.state())
    for name in store.fields:
        np.testing.assert_array_equal(restored.arrays()[name], store.arrays()[name])
    with pytest.raises(ValueError, match="lack"):
        store.append({"means": np.zeros((1, 3))})


def test_footprint_limit_is_pixels_times_distance_to_the_nearest_camera_over_focal():
    from taichi_gs.stages.deblur.density_control import footprint_limit

    means = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 0.0], [0.0, 4.0, 0.0]])
    centres = np.array([[0.0, 0.0, 0.0], [3.0, 0.0, 1.0]])
    np.testing.assert_allclose(footprint_limit(means, centres, 100.0, 0.5), [0.5 * 2 / 100, 0.5 * 1 / 100, 0.5 * 4 / 100])


def test_split_oversized_halves_until_every_gaussian_fits_its_limit():
    model = _model()
    before = model.arrays()
    sizes = np.exp(before["log_scales"].max(axis=1))
    limit = sizes / np.array([0.99, 2.0, 0.99, 3.0, 0.99, 0.99])  # 1 needs two splits (1.6^2 > 2), 3 needs three
    added = model.density.split_oversized(model.store, limit, max_gaussians=100, rng=np.random.default_rng(0))
    assert added == (1 + 2) + (1 + 2 + 4)
    after = model.arrays()
    assert model.count == 6 + added
    children = after["log_scales"].max(axis=1)
    np.testing.assert_allclose(np.sort(np.exp(children[6:]))[:4], np.sort(np.repeat(sizes[3] / 1.6**3, 4))[:4], rtol=1e-5)
    for row in (0, 2, 4, 5):  # within their limit: untouched
        np.testing.assert_array_equal(after["means"][row], before["means"][row])
    # the children of Gaussian 1 share its colour and stay near it (within a few of its sigmas)
    near_1 = np.linalg.norm(after["means"] - before["means"][1], axis=1) < 3 * sizes[1]
    assert near_1.sum() >= 4
    # Adam moments: the originals keep theirs, the new rows start at 0
    m, _ = model.store.adam.moments["colors"]
    assert np.all(m.to_numpy()[6:model.count] == 0) and np.all(m.to_numpy()[0] == 1)
    # a cap stops the splitting
    capped = _model()
    assert capped.density.split_oversized(capped.store, limit, max_gaussians=8, rng=np.random.default_rng(0)) == 2
    assert capped.count == 8


def test_densify_accepts_a_split_limit_per_gaussian():
    """Gaussian 0 (small, large gradient) is split instead of cloned when its own limit is below its size."""
    model = _model()
    limit = np.full(model.count, SPLIT_SCALE)
    limit[0] = 0.001
    before = model.arrays()
    model.density.densify_and_prune(model.store, THRESHOLD, limit, MIN_OPACITY, MAX_SCALE, 100, np.random.default_rng(3))
    after = model.arrays()
    np.testing.assert_allclose(after["log_scales"][0], before["log_scales"][0] - np.log(1.6), atol=1e-6)


def test_morton_order_interleaves_x_y_z_and_reorder_moves_moments_with_rows():
    from taichi_gs.gaussian_store import morton_order

    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], float)  # code x + 2y + 4z
    shuffled = np.random.default_rng(0).permutation(8)
    np.testing.assert_array_equal(morton_order(corners[shuffled]), np.argsort(shuffled))
    assert morton_order(np.zeros((0, 3))).size == 0

    model = _model()
    before, moments = model.arrays(), model.store.moments()
    model.density.grad_sum = np.arange(6.0)
    order = np.array([3, 0, 5, 1, 4, 2])
    model.store.reorder(order)
    model.density.reorder(order)
    for name in TRAINED:
        np.testing.assert_array_equal(model.arrays()[name], before[name][order], err_msg=name)
        np.testing.assert_array_equal(model.store.moments()[name][0], moments[name][0][order], err_msg=name)
    np.testing.assert_array_equal(model.density.grad_sum, order.astype(float))
    assert model.store.adam.t == 7
    with pytest.raises(ValueError, match="permutation"):
        model.store.reorder(np.array([0, 0, 1, 2, 3, 4]))


def test_observe_adds_each_gaussians_gradient_in_pixels_and_skips_the_unseen():
    """The device statistic against |dL/dmean| z / f written here in NumPy (z along the camera's axis);
    a Gaussian with an exactly zero gradient is not counted."""
    model = _model()
    rng = np.random.default_rng(2)
    grads = rng.normal(size=(model.count, 3)).astype(np.float32)
    grads[2] = 0.0
    model.gaussians.grads["means"].from_numpy(grads)
    pose = np.eye(4)
    pose[:3, :3] = quat_to_rotmat(np.array([0.9, 0.1, -0.3, 0.2]) / np.linalg.norm([0.9, 0.1, -0.3, 0.2]))
    pose[:3, 3] = [0.2, -0.1, -0.5]
    sums, counts = model.density.grad_sum.copy(), model.density.grad_count.copy()
    model.density.observe(model.store, pose, K[0, 0])
    z = np.abs((model.arrays()["means"].astype(np.float64) - pose[:3, 3]) @ pose[:3, 2])
    expected = np.linalg.norm(grads.astype(np.float64), axis=1) * z / K[0, 0]
    seen = np.arange(model.count) != 2
    np.testing.assert_allclose(model.density.grad_sum[seen], sums[seen] + expected[seen], rtol=1e-6)
    np.testing.assert_array_equal(model.density.grad_count, counts + seen)
    assert model.density.grad_sum[2] == sums[2]


def test_device_statistics_equal_the_host_accumulation_of_each_steps_values():
    """observe() sums on the device what the host summed before (each step's values read, added in float64);
    a host read in between (as densification and checkpoints do), changed in place, goes back first."""
    from taichi_gs.render import density_stats

    model = _model()
    rng = np.random.default_rng(5)
    sums, counts = model.density.grad_sum.copy(), model.density.grad_count.copy()
    for step in range(6):
        grads = rng.normal(size=(model.count, 3)).astype(np.float32)
        grads[step % model.count] = 0.0  # unseen this step
        model.gaussians.grads["means"].from_numpy(grads)
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(scale=0.2, size=3)
        params, g = model.gaussians.params, model.gaussians.grads
        pixels = density_stats.image_plane_gradient(params["means"], g["means"], model.count, pose, K[0, 0])
        seen = pixels >= 0
        sums[seen] += pixels[seen]
        counts[seen] += 1
        model.density.observe(model.store, pose, K[0, 0])
        if step == 2:  # read mid-way, changed in place: the device continues from the changed values
            np.testing.assert_array_equal(model.density.grad_sum, sums)
            model.density.grad_sum[1] += 0.25
            sums[1] += 0.25
    np.testing.assert_array_equal(model.density.grad_sum, sums)
    np.testing.assert_array_equal(model.density.grad_count, counts)
    state = model.state()
    np.testing.assert_array_equal(state["grad_sum"], sums)
    np.testing.assert_array_equal(state["grad_count"], counts)


def test_the_lightest_gaussians_up_to_a_share_of_the_weight_are_dropped():
    weights = np.array([5.0, 0.1, 3.0, 0.2, 0.0, 1.7])  # total 10: sorted 0.0, 0.1, 0.2, 1.7, 3.0, 5.0
    np.testing.assert_array_equal(heavier_than_share(weights, 0.0), [1, 1, 1, 1, 0, 1])  # weightless rows only
    np.testing.assert_array_equal(heavier_than_share(weights, 0.035), [1, 0, 1, 0, 0, 1])  # 0.35 of 10: three rows
    np.testing.assert_array_equal(heavier_than_share(weights, 0.19), [1, 0, 1, 0, 0, 1])  # 1.7 more would pass it
    np.testing.assert_array_equal(heavier_than_share(weights, 0.21), [1, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(heavier_than_share(weights, 1.0), [1, 0, 0, 0, 0, 0])  # one is always kept
    np.testing.assert_array_equal(heavier_than_share(np.zeros(3), 0.5), [1, 1, 1])  # nothing seen: keep all
    np.testing.assert_array_equal(heavier_than_share(np.ones(4), 0.5), [0, 0, 1, 1])  # ties: lower rows first


def test_drop_lightest_keeps_the_heavy_rows_with_their_moments_and_restarts_the_statistics():
    model = _model()
    before = model.arrays()
    weights = np.array([4.0, 0.5, 9.0, 0.0, 0.3, 6.0])
    assert model.density.drop_lightest(model.store, weights, 0.05) == 3  # 0.0 + 0.3 + 0.5 = 0.8 of 19.8
    assert model.count == 3
    for name in TRAINED:
        np.testing.assert_array_equal(model.arrays()[name], before[name][[0, 2, 5]], err_msg=name)
    first = model.store.adam.moments["means"][0].to_numpy()[: model.count, 0]
    np.testing.assert_array_equal(first, [1, 3, 6])
    np.testing.assert_array_equal(model.density.grad_sum, np.zeros(3))
    assert model.density.drop_lightest(model.store, np.ones(3), 0.0) == 0


def test_the_last_densification_is_the_last_interval_inside_the_window():
    schedule = DensitySchedule(densify_from=70, densify_until=315, densify_every=70, grad_threshold_px=1.0,
                               split_scale=0.01, prune_opacity=0.005, prune_scale=1.0, max_gaussians=10)
    assert [done for done in range(1, 400) if schedule.densifies(done)] == [70, 140, 210, 280]
    assert [done for done in range(1, 400) if schedule.last_densification(done)] == [280]
    exact = DensitySchedule(70, 280, 70, 1.0, 0.01, 0.005, 1.0, 10)
    assert [done for done in range(1, 400) if exact.last_densification(done)] == [280]
