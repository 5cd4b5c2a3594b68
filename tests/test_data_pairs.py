import hashlib
import subprocess
import sys

import numpy as np
import pytest
from conftest import MODELNET_DIR

from dit_jax.data import mixed, pairs, views


def _batch(shapes, n=200, **kw):
    ds = pairs.PairDataset(shapes, pairs.PairConfig(**kw))
    return ds, ds.batch(np.arange(n))


def _counterparts(b, i):
    """Source points with a counterpart, moved by the ground truth, and those counterparts."""
    has = b["correspondence"][i] >= 0
    moved = b["src"][i][has] @ b["R"][i].T + b["t"][i]
    return moved, b["tgt"][i][b["correspondence"][i][has]]


def test_clean_pairs_are_exact(modelnet_test):
    _, b = _batch(modelnet_test, 50, setting="clean")
    assert b["src"].shape == (50, 1000, 3) and b["tgt"].shape == (50, 1000, 3)
    for i in range(50):
        assert (b["correspondence"][i] >= 0).all()
        moved, target = _counterparts(b, i)
        np.testing.assert_allclose(moved, target, atol=2e-6)
        # The target is shuffled: its point order tells nothing.
        assert (b["correspondence"][i] != np.arange(1000)).mean() > 0.99


@pytest.mark.parametrize("setting,clip", [("low_noise_partial", 0.001), ("high_noise_partial", 0.05)])
def test_partial_settings_statistics(modelnet_test, setting, clip):
    _, b = _batch(modelnet_test, 200, setting=setting)
    assert b["src"].shape == (200, 800, 3) and b["tgt"].shape == (200, 800, 3)
    shared = (b["correspondence"] >= 0).sum(axis=1)
    assert 550 <= shared.min() and shared.max() <= 650, "about 600 shared points"
    for i in range(20):
        moved, target = _counterparts(b, i)
        # Two independent noises, each clipped to [-c, c] per coordinate of the shape's frame (the target's
        # noise is added before it moves, so rotate the difference back).
        residual = np.abs((moved - target) @ b["R"][i])
        assert residual.max() <= 2 * clip * 1.001 + 1e-5
        assert residual.max() > 0.5 * clip, "noise is there"
    if setting == "high_noise_partial":
        moved, target = _counterparts(b, 0)
        # N(0, 0.01^2) per cloud: the difference has std 0.01 * sqrt(2).
        assert np.std(moved - target) == pytest.approx(0.01 * np.sqrt(2), rel=0.1)


@pytest.mark.parametrize("setting", list(pairs.SETTINGS))
def test_angle_and_translation_ranges(modelnet_test, setting):
    _, b = _batch(modelnet_test, 400, setting=setting)
    angles, t = b["euler_zyx"], b["t"]
    assert angles.min() >= -45 and angles.max() <= 45
    assert angles.min() < -40 and angles.max() > 40, "the whole range is drawn"
    assert t.min() >= -0.5 and t.max() <= 0.5 and t.min() < -0.45 and t.max() > 0.45
    np.testing.assert_allclose(b["R"], pairs.euler_zyx_to_matrix(angles), atol=1e-6)


def test_euler_convention_is_rx_ry_rz():
    az, ay, ax = 30.0, -20.0, 10.0
    r = pairs.euler_zyx_to_matrix(np.array([az, ay, ax]))
    rz = pairs.euler_zyx_to_matrix(np.array([az, 0.0, 0.0]))
    ry = pairs.euler_zyx_to_matrix(np.array([0.0, ay, 0.0]))
    rx = pairs.euler_zyx_to_matrix(np.array([0.0, 0.0, ax]))
    np.testing.assert_allclose(r, rx @ ry @ rz, atol=1e-12)
    np.testing.assert_allclose(rz @ [1, 0, 0], [np.cos(np.radians(30)), np.sin(np.radians(30)), 0], atol=1e-12)


def test_unseen_split_keeps_categories_apart(modelnet_test, modelnet_train):
    test = pairs.PairDataset(modelnet_test, pairs.PairConfig(unseen=True))
    train = pairs.PairDataset(modelnet_train, pairs.PairConfig(unseen=True, train=True))
    assert set(np.unique(test.batch(np.arange(len(test)))["label"])) == set(range(20, 40))
    assert set(np.unique(train.batch(np.arange(len(train)))["label"])) == set(range(20))
    seen = pairs.PairDataset(modelnet_test, pairs.PairConfig())
    assert len(seen) == 2468


def _test_pair_digest(n):
    code = (
        "import hashlib, sys; from dit_jax.data import shapes, pairs;"
        f"s = shapes.load_shapes({str(MODELNET_DIR)!r}, 'test', data_dir=sys.argv[1]);"
        "p = pairs.PairDataset(s, pairs.PairConfig(setting='high_noise_partial'))[" + str(n) + "];"
        "print(hashlib.sha256(b''.join(p[k].tobytes() for k in sorted(p))).hexdigest())"
    )
    return code


def test_test_pair_is_bit_identical_across_runs(modelnet_test, prepared_dir):
    pair = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="high_noise_partial"))[17]
    digest = hashlib.sha256(b"".join(pair[k].tobytes() for k in sorted(pair))).hexdigest()
    other_run = subprocess.run(
        [sys.executable, "-c", _test_pair_digest(17), prepared_dir], capture_output=True, text=True, timeout=300
    )
    assert other_run.returncode == 0, other_run.stderr
    assert other_run.stdout.strip() == digest


def test_pair_n_is_the_same_alone_and_in_any_batch(modelnet_test):
    ds = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="low_noise_partial"))
    alone = ds[7]
    batched = ds.batch([3, 7, 11])
    for key in alone:
        np.testing.assert_array_equal(alone[key], batched[key][1])


def test_training_pairs_are_fresh_each_epoch_and_reproducible(modelnet_test):
    ds = pairs.PairDataset(modelnet_test, pairs.PairConfig(train=True, seed=3))
    e0, e1, e0_again = ds.batch([5], epoch=0), ds.batch([5], epoch=1), ds.batch([5], epoch=0)
    assert not np.allclose(e0["R"], e1["R"])
    np.testing.assert_array_equal(e0["tgt"], e0_again["tgt"])
    other_seed = pairs.PairDataset(modelnet_test, pairs.PairConfig(train=True, seed=4)).batch([5], epoch=0)
    assert not np.allclose(e0["R"], other_seed["R"])


def test_peers_variant(modelnet_test):
    _, b = _batch(modelnet_test, 200, setting="high_noise_partial", variant="peers")
    assert b["src"].shape == (200, 700, 3)
    assert b["euler_zyx"].min() >= 0 and b["euler_zyx"].max() <= 45 and b["euler_zyx"].max() > 40
    shared = (b["correspondence"] >= 0).sum(axis=1)
    assert 400 <= shared.min() and shared.max() <= 700 and 450 < shared.mean() < 600


def test_bad_configs_are_refused():
    with pytest.raises(ValueError, match="unknown setting 'noisy'"):
        pairs.PairConfig(setting="noisy")
    with pytest.raises(ValueError, match="unknown variant"):
        pairs.PairConfig(variant="dcp")


INDEPENDENT = [s for s, spec in pairs.SETTINGS.items() if spec.independent]


@pytest.mark.parametrize("setting", INDEPENDENT)
def test_independent_settings_share_no_point(modelnet_test, setting):
    """The clouds are disjoint samples of the shape: at the true pose no source point lands on a target point,
    yet most have a neighbour on the target nearby (the same surface)."""
    _, b = _batch(modelnet_test, 12, setting=setting, n_points=1000)
    spec = pairs.SETTINGS[setting]
    expected = {"none": 500, "authors": 400, "scan": 200}[spec.crop]  # of the 1000 points each shape holds
    assert b["src"].shape == (12, expected, 3) and b["tgt"].shape == (12, expected, 3)
    for i in range(12):
        moved = b["src"][i] @ b["R"][i].T + b["t"][i]
        gaps = np.linalg.norm(moved[:, None] - b["tgt"][i][None], axis=-1).min(axis=1)
        if spec.noise_clip == 0:
            assert gaps.min() > 1e-4, "no point is shared"
        assert np.median(gaps) < 0.12, "both clouds sample the same surface"
        has = b["correspondence"][i] >= 0
        assert 0.1 < has.mean() < 1.0
        # Counterparts are target rows within the radius on the noise-free shape (noise moves them a little).
        matched = np.linalg.norm(moved[has] - b["tgt"][i][b["correspondence"][i][has]], axis=-1)
        assert matched.max() < pairs.CORRESPONDENCE_RADIUS + 4 * max(spec.noise_clip, 1e-6) * np.sqrt(3)


def test_independent_pairs_are_deterministic_and_fresh_per_epoch(modelnet_test):
    test = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="scan_high_noise"))
    np.testing.assert_array_equal(test.batch([3, 4])["src"], test.batch([3, 4])["src"])
    np.testing.assert_array_equal(test[4]["tgt"], test.batch([3, 4])["tgt"][1])
    train = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="independent_clean", train=True))
    assert not np.array_equal(train.batch([0], epoch=0)["src"], train.batch([0], epoch=1)["src"])


def test_visible_points_of_a_sphere_face_the_camera():
    rng = np.random.default_rng(0)
    sphere = rng.normal(size=(2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    camera = np.array([0.0, 0.0, 3.0])
    seen = views.visible_points(sphere, camera)
    # A camera 3 radii away sees the cap with z > 1/3; hidden-point removal finds most of it and nothing behind
    # (a few points at the horizon are within sampling error of it).
    assert sphere[seen, 2].min() > 0.1 and (sphere[seen, 2] < 0.25).mean() < 0.01
    assert 0.7 < seen.sum() / (sphere[:, 2] > 1 / 3).sum() <= 1.1


@pytest.mark.parametrize("hidden", [50, 0])
def test_scan_views_stay_whole_and_disjoint_when_few_points_are_hidden(monkeypatch, hidden):
    """One camera sees 100 points, the other all but ``hidden``: too few hidden points to fill the first view
    (training stopped on such a pair with "could not broadcast (199,) into (205,)"). Both clouds still get k
    distinct points and share none."""
    shape = np.random.default_rng(1).normal(size=(1024, 3))
    masks = iter([np.arange(1024) < 100, np.arange(1024) < 1024 - hidden])
    monkeypatch.setattr(views, "visible_points", lambda points, camera: next(masks))
    src, tgt = views.scan_views(shape, 205, np.random.default_rng(0))
    assert len(src) == len(tgt) == 205
    assert len(np.unique(src)) == len(np.unique(tgt)) == 205 and not np.intersect1d(src, tgt).size


def test_scan_views_differ_by_at_most_sixty_degrees(modelnet_test):
    """The two views' clouds lie on the sides of the shape their cameras face: their mean directions from the
    shape's centre are less than about 90 degrees apart, where independent halves would be random."""
    ds = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="scan_low_noise"))
    b = ds.batch(np.arange(40))
    angles = []
    for i in range(40):
        centre = modelnet_test.points[ds.rows[i]].mean(axis=0)
        src_dir = (b["src"][i] - centre).mean(axis=0)
        tgt_dir = ((b["tgt"][i] - b["t"][i]) @ b["R"][i] - centre).mean(axis=0)
        cos = src_dir @ tgt_dir / np.linalg.norm(src_dir) / np.linalg.norm(tgt_dir)
        angles.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    assert np.median(angles) < 60


def test_mixed_pairs_draw_whole_batches_from_each_setting(modelnet_test):
    config = pairs.PairConfig(train=True, n_points=512)
    mix = mixed.MixedPairs(modelnet_test, config, ("clean", "independent_clean", "scan_high_noise"))
    seen = {}
    for first in range(30):
        indices = [first, first + 100]
        setting = mix.setting_of(indices, epoch=2)
        b = mix.batch(indices, epoch=2)
        expected = mix.datasets[setting].batch(indices, epoch=2)
        np.testing.assert_array_equal(b["src"], expected["src"])
        seen[setting] = seen.get(setting, 0) + 1
        assert mix.setting_of(indices, epoch=2) == setting, "deterministic"
    assert set(seen) == {"clean", "independent_clean", "scan_high_noise"}
    assert len(mix) == len(mix.datasets["clean"])


def test_pair_view_reads_a_stacked_batch_and_swaps_clouds(modelnet_test):
    ds = pairs.PairDataset(modelnet_test, pairs.PairConfig(setting="low_noise_partial"))
    stacked = ds.batch(np.arange(6))
    view, swapped = mixed.PairView(stacked), mixed.PairView(ds, swap=True)
    for key in ("src", "tgt", "R"):
        np.testing.assert_array_equal(view.batch([4, 1])[key], ds.batch([4, 1])[key])
        np.testing.assert_array_equal(view[3][key], ds[3][key])
    np.testing.assert_array_equal(swapped.batch([2])["src"], ds.batch([2])["tgt"])
    np.testing.assert_array_equal(swapped[2]["tgt"], ds[2]["src"])
    np.testing.assert_array_equal(mixed.PairView(stacked, swap=True)[5]["src"], stacked["tgt"][5])


def _thinned_clean_pairs(mix, n, size):
    """The mix's first ``n`` clean pairs, checked: clouds of ``size`` points, exact counterparts where both
    points stayed, the same on a second call."""
    batch = mix.setting_batch("clean", np.arange(n))
    assert batch["src"].shape == batch["tgt"].shape == (n, size, 3)
    for i in range(n):
        moved, target = _counterparts(batch, i)
        np.testing.assert_allclose(moved, target, atol=2e-6)
    np.testing.assert_array_equal(mix.setting_batch("clean", np.arange(n))["tgt"], batch["tgt"])
    return batch


def test_a_mix_of_one_size_thins_every_setting_to_its_smallest_clouds(modelnet_test):
    """``one_size``: every setting's clouds hold the mix's fewest points (here the partial setting's 800 of
    1000), and the thinned pairs keep exact counterparts where both points stayed, the same on every call."""
    config = pairs.PairConfig(n_points=1000)
    mix = mixed.MixedPairs(modelnet_test, config, ("clean", "low_noise_partial"), one_size=True)
    assert mix.cloud_points == 800
    clean = _thinned_clean_pairs(mix, 6, 800)
    for i in range(6):  # about 800 / 1000 of the kept source points kept their counterpart
        assert 0.7 < (clean["correspondence"][i] >= 0).mean() < 0.9
    partial = mix.setting_batch("low_noise_partial", np.arange(6))
    np.testing.assert_array_equal(partial["src"], mix.datasets["low_noise_partial"].batch(np.arange(6))["src"])
    assert mixed.MixedPairs(modelnet_test, config, ("clean", "low_noise_partial")).batch(np.arange(2))["src"].shape[
        1
    ] in (800, 1000)


def test_samplers_keep_distinct_patterns():
    """``uniform`` keeps points at random; ``density`` favours one side (the kept points' centroid moves),
    ``farthest`` spreads them (no two kept points close): what makes a varied mix vary."""
    cloud = np.random.default_rng(0).uniform(-1, 1, (3000, 3))
    from scipy.spatial import cKDTree

    def kept(sampler, seed):
        idx = views.sample_points(cloud, 600, np.random.default_rng(seed), sampler)
        assert len(np.unique(idx)) == 600 and np.all(np.diff(idx) > 0)
        return cloud[idx]

    shift = {s: [float(np.linalg.norm(kept(s, seed).mean(axis=0))) for seed in range(4)] for s in views.SAMPLERS}
    assert min(shift["density"]) > 2 * max(shift["uniform"]), shift
    closest = {
        s: min(float(cKDTree(c).query(c, k=2)[0][:, 1].min()) for c in [kept(s, 0)]) for s in ("uniform", "farthest")
    }
    assert closest["farthest"] > 5 * closest["uniform"], closest
    with pytest.raises(ValueError, match="unknown sampler"):
        views.sample_points(cloud, 10, np.random.default_rng(0), "voxel")


def test_a_varied_mix_thins_each_cloud_its_own_way_and_keeps_counterparts(modelnet_test):
    mix = mixed.MixedPairs(
        modelnet_test,
        pairs.PairConfig(n_points=1000),
        ("clean", "low_noise_partial"),
        one_size=True,
        points=300,
        sampling="varied",
    )
    assert mix.cloud_points == 300
    _thinned_clean_pairs(mix, 8, 300)
    with pytest.raises(ValueError, match="points"):
        mixed.MixedPairs(
            modelnet_test, pairs.PairConfig(n_points=1000), ("clean", "low_noise_partial"), one_size=True, points=900
        )
    # Without one size, points caps each setting: larger clouds are thinned, smaller ones keep their size.
    capped = mixed.MixedPairs(
        modelnet_test, pairs.PairConfig(n_points=1000), ("clean", "low_noise_partial"), points=900, sampling="varied"
    )
    assert capped.setting_batch("clean", np.arange(2))["src"].shape == (2, 900, 3)
    assert capped.setting_batch("low_noise_partial", np.arange(2))["src"].shape == (2, 800, 3)
