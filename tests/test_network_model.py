import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import shared_point_pairs

from dit_jax.evaluators import metrics
from dit_jax.network import configs, convert, model

CONFIG = configs.tiny()
# model.features as a caller would jit it: one compiled program, where op-by-op dispatch would compile every
# operation of the network.
_features = jax.jit(model.features, static_argnames=("config",))


@pytest.fixture(scope="module")
def params():
    return model.init(jax.random.key(0), CONFIG)


def _pair(seed, n=48, m=40, batch=2):
    rng = np.random.default_rng(seed)
    src = rng.uniform(-1, 1, size=(batch, n, 3)).astype(np.float32)
    tgt = rng.uniform(-1, 1, size=(batch, m, 3)).astype(np.float32)
    return jnp.asarray(src), jnp.asarray(tgt)


def _assert_proper_rotations(rot):
    rot = np.asarray(rot)
    assert np.isfinite(rot).all()
    np.testing.assert_allclose(rot @ np.swapaxes(rot, -1, -2), np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0, atol=1e-5)


def test_register_under_jit_and_vmap_with_n_not_m(shipped):
    """Batched, alone, or vmapped by the caller: the same registration, to float32 rounding.

    Three compiled programs: on pairs the shipped weights register, their rotations and translations were
    measured at most 1.2e-6 apart (16 pairs, this comparison and the iterations' below; AVX2 and AVX-512 code
    paths); the bound is eight times that. Untrained weights would not do (see ``conftest.shipped``)."""
    params, config = shipped
    src, tgt, turns = (jnp.asarray(a) for a in shared_point_pairs(0, n=48, m=40, batch=2))
    rot, trans, extras = jax.jit(model.register, static_argnames="config")(params, src, tgt, config)
    assert rot.shape == (2, 3, 3) and trans.shape == (2, 3)
    assert extras["correspondences"].shape == (2, 48) and int(extras["correspondences"].max()) < 40
    assert extras["step_rotation"].shape == (2, config.n_iters, 3, 3)
    _assert_proper_rotations(rot)
    assert float(jnp.max(metrics.rotation_error_deg(rot, turns))) < 0.1  # registered: GMCCE's sets are clear
    # Batching changes nothing: each pair alone gives the same answer.
    for b in range(2):
        rot_b, trans_b, _ = model.register(params, src[b : b + 1], tgt[b : b + 1], config)
        np.testing.assert_allclose(np.asarray(rot_b[0]), np.asarray(rot[b]), atol=1e-5)
        np.testing.assert_allclose(np.asarray(trans_b[0]), np.asarray(trans[b]), atol=1e-5)
    # vmap over an extra axis of pairs works on the user's side too.
    outer = jax.vmap(lambda s, t: model.register(params, s, t, config)[0])(src[:, None], tgt[:, None])
    np.testing.assert_allclose(np.asarray(outer[:, 0]), np.asarray(rot), atol=1e-5)


def test_register_composes_the_iterations(params):
    src, tgt = _pair(1, batch=1)
    rot, trans, extras = model.register(params, src, tgt, CONFIG)
    total_r, total_t = np.eye(3), np.zeros(3)
    for r_i, t_i in zip(np.asarray(extras["step_rotation"][0]), np.asarray(extras["step_translation"][0])):
        total_r, total_t = r_i @ total_r, r_i @ total_t + t_i
    np.testing.assert_allclose(np.asarray(rot[0]), total_r, atol=1e-5)
    np.testing.assert_allclose(np.asarray(trans[0]), total_t, atol=1e-5)


@pytest.mark.parametrize("case", ["identical_points", "collinear", "repeated_points", "coplanar"])
def test_register_never_nan_on_degenerate_clouds(params, case):
    rng = np.random.default_rng(2)
    n = 40
    if case == "identical_points":
        src = np.full((n, 3), 0.25, np.float32)
    elif case == "collinear":
        src = np.outer(np.linspace(-1, 1, n), [0.3, -0.2, 0.9]).astype(np.float32)
    elif case == "repeated_points":
        src = np.repeat(rng.normal(size=(4, 3)), n // 4, axis=0).astype(np.float32)
    else:
        src = rng.normal(size=(n, 3)).astype(np.float32)
        src[:, 2] = 0
    tgt = src[rng.permutation(n)][: n - 5] + 0.1
    rot, trans, extras = model.register(params, jnp.asarray(src[None]), jnp.asarray(tgt[None]), CONFIG)
    _assert_proper_rotations(rot)
    assert np.isfinite(np.asarray(trans)).all()
    assert np.isfinite(np.asarray(extras["weights"])).all()


def test_gmcce_rejecting_everything_falls_back_to_soft_weights(params):
    config = CONFIG.replace(gmcce_threshold=1.0)  # confidence never exceeds 1: every match rejected
    src, tgt = _pair(3, batch=1)
    rot, trans, extras = model.register(params, src, tgt, config)
    fallback = np.asarray(extras["gmcce_fallback"][0])
    assert not fallback[0] and fallback[1:].all(), "soft mode needs no fallback; every GMCCE step does"
    assert np.asarray(extras["weights"]).min() > 0, "the fallback uses the positive soft weights"
    _assert_proper_rotations(rot)


def test_register_rejects_bad_shapes_in_one_line(params):
    src, tgt = _pair(4)
    with pytest.raises(ValueError, match=r"src must have shape \(B, N, 3\)"):
        model.register(params, src[0], tgt, CONFIG)
    with pytest.raises(ValueError, match="tgt has 5 points; this config needs at least 11"):
        model.register(params, src, tgt[:, :5], CONFIG)
    with pytest.raises(ValueError, match="batch sizes differ"):
        model.register(params, src, tgt[:1], CONFIG)


def test_features_are_permutation_equivariant(params):
    # Point order carries no meaning: permuting the source permutes its features and nothing else.
    src, tgt = _pair(5, batch=1)
    perm = np.random.default_rng(5).permutation(src.shape[1])
    _, feats = _features(params, src[0], tgt[0], CONFIG)
    _, feats_p = _features(params, src[0][perm], tgt[0], CONFIG)
    np.testing.assert_allclose(np.asarray(feats_p.phi_src), np.asarray(feats.phi_src)[perm], atol=1e-4)
    np.testing.assert_allclose(np.asarray(feats_p.phi_tgt), np.asarray(feats.phi_tgt), atol=1e-4)


def test_reference_weights_register_their_pair_with_part_of_the_target(reference_data):
    # The authors' small (partly trained) network registers its own pair exactly; dropping 16 target points
    # (N = 256, M = 240) must not change that.
    config = configs.from_authors(str(reference_data["config"]), gmcce_threshold=0.99)
    sd = {k[len("param/") :]: v for k, v in reference_data.items() if k.startswith("param/")}
    params = convert.from_torch_state_dict(sd, config)
    keep = np.random.default_rng(0).permutation(len(reference_data["tgt"]))[:240]
    src, tgt = reference_data["src"][None], reference_data["tgt"][keep][None]
    rot, trans, extras = model.register(params, jnp.asarray(src), jnp.asarray(tgt), config)
    np.testing.assert_allclose(np.asarray(rot[0]), reference_data["R_gt"], atol=1e-5)
    np.testing.assert_allclose(np.asarray(trans[0]), reference_data["t_gt"], atol=1e-5)
    assert 0 < float(extras["inlier_ratio"][0]) < 1


def test_cached_embeddings_give_the_uncached_iterations(shipped):
    """register reuses the target's embedding and memory and the source's kNN graph; recomputing all of
    them every iteration, as the authors do, gives the same registration, iteration by iteration (two
    compiled programs: within the float32 bound of the test above, on a pair the shipped weights register)."""
    params, config = shipped
    src, tgt, _ = (jnp.asarray(a) for a in shared_point_pairs(5, n=48, m=40, batch=1))
    rot, trans, extras = model.register(params, src, tgt, config)
    forward = jax.jit(model.forward, static_argnames=("config", "use_gmcce"))
    moved, total_r, total_t = src[0], jnp.eye(3), jnp.zeros(3)
    for i in range(config.n_iters):
        feats, out = forward(params, moved, tgt[0], config, use_gmcce=i >= 1)
        total_r, total_t = out.rotation @ total_r, out.rotation @ total_t + out.translation
        moved = moved @ out.rotation.T + out.translation
        np.testing.assert_allclose(np.asarray(out.rotation), np.asarray(extras["step_rotation"][0, i]), atol=1e-5)
        np.testing.assert_allclose(np.asarray(out.translation), np.asarray(extras["step_translation"][0, i]), atol=1e-5)
        # Each iteration's matches are recorded: the first's are the network's own (training's validation).
        # Each source point's best score leads its second by far more than float32 rounding here, so the
        # argmax is the same in both programs.
        best_two = jnp.sort(feats.scores, axis=-1)[:, -2:]
        assert float(jnp.min(best_two[:, 1] - best_two[:, 0])) > 1e-3
        np.testing.assert_array_equal(np.asarray(out.correspondences), np.asarray(extras["step_correspondences"][0, i]))
    np.testing.assert_allclose(np.asarray(rot[0]), np.asarray(total_r), atol=1e-5)
    np.testing.assert_allclose(np.asarray(trans[0]), np.asarray(total_t), atol=1e-5)


def test_attention_in_blocks_changes_nothing(params):
    """Blocked attention (memory linear in N) computes the features of the whole (gradients: test_layers)."""
    src, tgt = _pair(6, n=80, m=40, batch=1)
    whole = CONFIG.replace(attention_chunk=0)
    blocked = CONFIG.replace(attention_chunk=32)  # 80 source rows: blocks of 32, 32 and 16 padded
    _, f_whole = _features(params, src[0], tgt[0], whole)
    _, f_blocked = _features(params, src[0], tgt[0], blocked)
    np.testing.assert_allclose(np.asarray(f_blocked.scores), np.asarray(f_whole.scores), atol=1e-5)


def test_configs_that_hold_the_same_parameters_initialise_alike_from_one_program(params):
    """Fields that change only what the network computes leave the initial parameters bit for bit, and do not
    compile init again; a field that shapes them does."""
    before = model._init._cache_size()
    computing = CONFIG.replace(
        n_iters=1,
        gmcce_k=5,
        gmcce_threshold=0.5,
        guard_iterations=True,
        temp_factor=50.0,
        dropout=0.0,
        attention_chunk=16,
        compute_dtype="bfloat16",
        precision="tf32",
        remat=True,
    )
    jax.tree.map(np.testing.assert_array_equal, model.init(jax.random.key(0), computing), params)
    assert model._init._cache_size() == before
    wider = jax.eval_shape(lambda: model.init(jax.random.key(0), CONFIG.replace(k=CONFIG.k + 1)))
    assert jax.tree.map(lambda a: a.shape, wider) != jax.tree.map(lambda a: a.shape, params)


def test_remat_gives_the_same_gradients_with_dropout(params):
    """Rematerialised blocks (``remat=True``) recompute the same forward pass, dropout masks included, so the
    training gradients are those of the stored activations; the parameter tree is the same too. (One
    iteration, since gradients do not cross iterations, and the tree from ``jax.eval_shape``: 32 -> 21 s.)"""
    src, tgt = _pair(7, n=40, m=40, batch=1)
    key = jax.random.key(3)

    def loss(p, config):
        its = model.unroll(p, src[0], tgt[0], config, 1, differentiable=True, dropout_key=key)
        return jnp.sum(its.rotation**2) + jnp.sum(its.soft_weights)

    plain = CONFIG.replace(dropout=0.2)
    remat = plain.replace(remat=True)
    assert jax.tree.structure(jax.eval_shape(lambda: model.init(jax.random.key(0), remat))) == jax.tree.structure(
        params
    )
    value_and_grad = jax.jit(jax.value_and_grad(loss), static_argnums=1)  # under jit, as training runs it
    value, grads = value_and_grad(params, plain)
    value_r, grads_r = value_and_grad(params, remat)
    np.testing.assert_allclose(float(value_r), float(value), rtol=1e-6)
    for g, g_r in zip(jax.tree.leaves(grads), jax.tree.leaves(grads_r)):
        # Equal up to float32 reassociation, measured against each leaf's largest entry. The softmax and the
        # Procrustes derivative magnify rounding to about 1e-5 of that scale, more on CPUs with wider vector
        # units (XLA sums in another order there); another dropout mask moves a leaf by a tenth of it or more.
        scale = max(1.0, float(np.abs(np.asarray(g)).max()))
        np.testing.assert_allclose(np.asarray(g_r), np.asarray(g), rtol=1e-4, atol=1e-4 * scale)


def test_guarded_iterations_never_lower_the_fitness(params):
    """With ``guard_iterations`` an iteration's update is kept only where it brings the source no farther from
    the target; the final alignment cost is then at most the first iteration's, and refused updates are
    reported."""
    from dit_jax.geometry import rigid

    src, tgt = _pair(5, n=64, m=64, batch=4)
    guarded = CONFIG.replace(guard_iterations=True, n_iters=3)
    rot, trans, extras = model.register(params, src, tgt, guarded)
    first_r, first_t, _ = model.register(params, src, tgt, CONFIG.replace(n_iters=1))

    def cost(r, t, b):
        moved = rigid.apply_transform(r[b], t[b], src[b])
        return float(rigid.alignment_cost(moved, tgt[b], CONFIG.fitness_radius * rigid.spacing(tgt[b])))

    for b in range(4):
        assert cost(rot, trans, b) <= cost(first_r, first_t, b) + 1e-6
    accepted = np.asarray(extras["accepted"])
    assert accepted.shape == (4, 3) and accepted[:, 0].all()
    # The estimate is the composition of the accepted steps only.
    for b in range(4):
        total_r, total_t = np.eye(3), np.zeros(3)
        for ok, r_i, t_i in zip(
            accepted[b], np.asarray(extras["step_rotation"][b]), np.asarray(extras["step_translation"][b])
        ):
            if ok:
                total_r, total_t = r_i @ total_r, r_i @ total_t + t_i
        np.testing.assert_allclose(np.asarray(rot[b]), total_r, atol=1e-5)
        np.testing.assert_allclose(np.asarray(trans[b]), total_t, atol=1e-5)


def test_fitness_measures_how_much_of_the_source_lands_on_the_target():
    from dit_jax.geometry import rigid

    src, _ = _pair(6, n=200, batch=1)
    src = src[0]
    radius = 2 * rigid.spacing(src)
    assert float(rigid.fitness(src, src, radius)) == 1.0
    assert float(rigid.fitness(src, src + 100.0, radius)) == 0.0
    assert float(rigid.alignment_cost(src, src, radius)) == 0.0
    assert float(rigid.alignment_cost(src, src + 100.0, radius)) == pytest.approx(1.0, abs=1e-6)
    nearer = float(rigid.alignment_cost(src, src + 0.1 * radius, radius))
    assert 0.0 < nearer < float(rigid.alignment_cost(src, src + 0.5 * radius, radius)) < 1.0
    half = src[src[:, 0] > 0]
    assert 0.35 < float(rigid.fitness(src, half, radius)) < 0.75, "half the source has a target nearby"
