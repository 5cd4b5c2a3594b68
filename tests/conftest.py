"""Shared fixtures: the paths of ../shared and small clouds."""

from __future__ import annotations

import ast
import functools
import os
import pathlib
import shutil
import tempfile

import numpy as np
import pytest

# Compilation dominates this suite's time on two CPU cores, so the session and every process it starts compile
# with less code-generation work: XLA's CPU backend at LLVM optimisation level 0, without LLVM's expensive
# passes, and with its older fusion emitters (LLVM IR written directly) instead of the MLIR-based ones. XLA's
# own passes are unchanged, so the programs are the same; only their machine code is generated with less work.
# The whole suite passes with and without the flags, faster with them (docs/benchmarks.md, "The test suite").
# Users run the defaults. A flag the environment already sets is left as it is.
FAST_COMPILE_FLAGS = {
    "xla_backend_optimization_level": "0",
    "xla_llvm_disable_expensive_passes": "true",
    "xla_cpu_use_fusion_emitters": "false",
}
for _flag, _value in FAST_COMPILE_FLAGS.items():
    if _flag not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --{_flag}={_value}".strip()

# The test session and the train.py / dit-register / evaluate.py processes it starts share one throwaway
# compilation cache (tests that build the same train step, a resumed run, a second CLI call reuse programs
# compiled before), never the user's own; it is removed when the session ends. tests/test_network_compile_cache.py
# gives its processes caches of their own.
# Under pytest-xdist the workers inherit the controller's variables, so they find its cache through
# DIT_JAX_TEST_XLA_CACHE and share it (the controller alone removes it).
_TEST_CACHE = None
if "DIT_JAX_COMPILE_CACHE" not in os.environ:
    _TEST_CACHE = tempfile.mkdtemp(prefix="dit-jax-test-xla-")
    os.environ["DIT_JAX_COMPILE_CACHE"] = os.environ["DIT_JAX_TEST_XLA_CACHE"] = _TEST_CACHE
if os.environ.get("DIT_JAX_TEST_XLA_CACHE") == os.environ["DIT_JAX_COMPILE_CACHE"]:
    from dit_jax.network import compile_cache

    compile_cache.enable(os.environ["DIT_JAX_COMPILE_CACHE"])


# Likewise one TFDS preparation folder for the session and its xdist workers: the first worker to need a
# split prepares it (under the preparation lock) and the other reads it, instead of each preparing its own.
_TEST_TFDS = None
if "DIT_JAX_TEST_TFDS" not in os.environ:
    _TEST_TFDS = tempfile.mkdtemp(prefix="dit-jax-test-tfds-")
    os.environ["DIT_JAX_TEST_TFDS"] = _TEST_TFDS


def pytest_sessionfinish(session, exitstatus):
    for folder in (_TEST_CACHE, _TEST_TFDS):
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


ROOT = pathlib.Path(__file__).resolve().parents[1]
SHARED = pathlib.Path(os.environ.get("DIT_SHARED", ROOT.parent / "shared"))
REFERENCE_FILE = SHARED / "reference" / "dit_reference_a.npz"
MODELNET_DIR = SHARED / "data" / "modelnet40_ply_hdf5_1024"
TEST_DATA = ROOT / "tests" / "data"
DRAGON_DIR = SHARED / "data" / "stanford_dragon_stand"
ROOMS_DIR = SHARED / "data" / "3dmatch"


@pytest.fixture(scope="session")
def reference_file() -> pathlib.Path:
    if not REFERENCE_FILE.exists():
        pytest.skip(f"the authors' reference file is not here ({REFERENCE_FILE}); it ships with ../shared")
    return REFERENCE_FILE


@pytest.fixture(scope="session")
def reference_data(reference_file) -> dict[str, np.ndarray]:
    with np.load(reference_file) as npz:
        return {k: npz[k] for k in npz.files}


@pytest.fixture(scope="session")
def modelnet_shapes() -> np.ndarray:
    """(S, 1024, 3) shapes from the first ModelNet40 test file."""
    h5py = pytest.importorskip("h5py", reason="reading ModelNet40 needs h5py (the test extra)")
    path = MODELNET_DIR / "ply_data_test0.h5"
    if not path.exists():
        pytest.skip(f"ModelNet40 is not here ({MODELNET_DIR}); it ships with ../shared")
    with h5py.File(path, "r") as f:
        return np.asarray(f["data"][:64], dtype=np.float32)


@pytest.fixture(scope="session")
def dragon_dir() -> pathlib.Path:
    if not (DRAGON_DIR / "dragonStandRight.conf").exists():
        pytest.skip(f"the Stanford Dragon scans are not here ({DRAGON_DIR}); they ship with ../shared")
    return DRAGON_DIR


@pytest.fixture(scope="session")
def rooms_dir() -> pathlib.Path:
    if not (ROOMS_DIR / "hotel3" / "cloud_bin_35.ply").exists():
        pytest.skip(f"the 3DMatch scenes are not here ({ROOMS_DIR}); they ship with ../shared")
    return ROOMS_DIR


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory) -> str:
    """An untrained tiny network's checkpoint whose verdict trusts everything: for tests of the command line
    and the file handling around the network, not of its accuracy."""
    import jax

    from dit_jax.network import checkpoint, configs, model

    config = configs.tiny()
    path = tmp_path_factory.mktemp("ckpt") / "tiny"
    return checkpoint.save(
        path,
        model.init(jax.random.PRNGKey(0), config),
        config,
        extra={
            "inference_settings": {
                "n_points": 128,
                "min_fitness": 0.0,
                "max_disagreement_network": 180.0,
                "max_disagreement_icp": 180.0,
            }
        },
    )


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random rotation (det +1) from the QR of a Gaussian matrix."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@pytest.fixture(scope="session")
def shipped():
    """(params, DITConfig) of the shipped weights, for tests that compare two compiled programs' registrations:
    trained weights on pairs they register keep GMCCE's inlier sets clear of its thresholds, where untrained
    ones keep one or two matches that the last bits of either program decide (1.5 apart in rotation)."""
    from dit_jax.network import checkpoint
    from dit_jax.pipeline import registration

    return checkpoint.restore(registration.shipped_weights())


def shared_point_pairs(seed: int, n: int, m: int, batch: int, turn_deg: float = 30.0):
    """Pairs the shipped network registers to a hundredth of a degree: ``src`` (batch, n, 3) points of a bumpy
    sphere, ``tgt`` (batch, m, 3) m of them turned by ``turn_deg`` about a random axis and moved, float32; and
    each pair's turn (batch, 3, 3) float64. GMCCE keeps half of the matches or more on them."""
    from dit_jax.geometry import rigid

    rng = np.random.default_rng(seed)
    src, tgt, turns = [], [], []
    for _ in range(batch):
        directions = rng.normal(size=(n, 3))
        directions /= np.linalg.norm(directions, axis=1, keepdims=True)
        points = directions * (1.0 + 0.2 * np.sin(3 * directions[:, :1]) * np.cos(2 * directions[:, 1:2]))
        turn = rigid.axis_angle_matrix(rng.normal(size=3), turn_deg)
        src.append(points)
        tgt.append(points[rng.permutation(n)[:m]] @ turn.T + 0.05)
        turns.append(turn)
    return np.stack(src).astype(np.float32), np.stack(tgt).astype(np.float32), np.stack(turns)


@pytest.fixture(scope="session")
def prepared_dir() -> str:
    """Where the tests' TFDS preparations go: fresh per session (so preparation itself is tested), shared by
    the session's workers."""
    return os.environ["DIT_JAX_TEST_TFDS"]


@pytest.fixture(scope="session")
def modelnet_test(prepared_dir):
    """The official test split of the shared ModelNet40 copy, prepared through TFDS."""
    if not MODELNET_DIR.exists():
        pytest.skip(f"ModelNet40 is not here ({MODELNET_DIR}); it ships with ../shared")
    from dit_jax.data import shapes

    return shapes.load_shapes(MODELNET_DIR, "test", n_points=1000, data_dir=prepared_dir)


@pytest.fixture(scope="session")
def modelnet_train(prepared_dir, modelnet_test):
    from dit_jax.data import shapes

    return shapes.load_shapes(MODELNET_DIR, "train", n_points=1000, data_dir=prepared_dir)


def write_3dmatch_scene(scene, world, rng, fragments=(0, 1, 3)):
    """A 3DMatch scene: fragment k is ``world`` seen from pose k; one 3DMatch list with every pair and its
    information matrix (``gt.info``). Returns the poses."""
    from dit_jax import io

    (scene / "3DMatch").mkdir(parents=True)
    poses = {k: np.vstack([np.c_[random_rotation(rng), rng.normal(size=3)], [0, 0, 0, 1]]) for k in fragments}
    for k, pose in poses.items():
        io.write(scene / f"cloud_bin_{k}.ply", (world - pose[:3, 3]) @ pose[:3, :3])
    log, info = "", ""
    for i in fragments:
        for j in fragments:
            if j > i:
                log += f"{i} {j} 60\n" + "".join(
                    " ".join(f"{v:.17g}" for v in row) + "\n" for row in np.linalg.inv(poses[i]) @ poses[j]
                )
                sigma = np.diag([60.0, 60.0, 60.0, 8.0, 9.0, 10.0])
                info += f"{i} {j} 60\n" + "".join(" ".join(f"{v:g}" for v in row) + "\n" for row in sigma)
    (scene / "3DMatch" / "gt.log").write_text(log)
    (scene / "3DMatch" / "gt.info").write_text(info)
    return poses


def write_scan_series(directory, poses, rng, n_points: int = 50):
    """A tiny turntable series: one random cloud seen in several frames, with a .conf of their poses."""
    cloud = rng.normal(size=(n_points, 3))
    lines = ["camera 0 0 0 0 0 0 1", "mesh not_a_scan 0 0 0 0 0 0 1"]
    for i, (rotation, t) in enumerate(poses):
        # pose: p_common = R^T p + t, so the scan holds p = R (p_common - t).
        local = (cloud - t) @ rotation.T
        np.savetxt(directory / f"s{i}.xyz", local)
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(rotation).as_quat()
        lines.append(f"bmesh s{i}.xyz {t[0]} {t[1]} {t[2]} {q[0]} {q[1]} {q[2]} {q[3]}")
    (directory / "series.conf").write_text("\n".join(lines) + "\n")
    return cloud


#: Test modules whose tests run minutes, not seconds (training, several processes): started first, so that
#: under pytest-xdist (the README's ``-n 2``) the quick tests fill the other worker while these run,
#: instead of the slow ones meeting at the end.
_SLOW_MODULES = ("test_training.py",)


#: Tests outside those modules that take 15 s or more on two loaded cores (`--durations`): started
#: next, longest first, so that neither worker is left with one of them while the other has nothing to do.
_LONG_TESTS = (
    "test_other_widths_depths_and_point_counts_are_checked",
    "test_remat_gives_the_same_gradients_with_dropout",
    "test_rotation_search_registers_pairs_far_beyond_the_training_range",
    "test_icp_refinement_improves_independently_sampled_pairs_and_updates_the_verdict",
    "test_agreement_verdict_trusts_a_moved_copy_and_flags_another_shape",
    "test_evaluate_cli_uses_the_shipped_weights_by_default",
    "test_refinement_never_makes_clean_pairs_worse_and_records_tuned_options",
    "test_refine_and_plot_on_the_readme_example_pair",
    "test_real_scans_network_alone_is_trusted_only_where_both_directions_agree_closely",
    "test_a_second_dit_register_reuses_the_first_ones_programs",
    "test_evaluate_end_to_end_writes_tables_json_and_plots",
    "test_register_under_jit_and_vmap_with_n_not_m",
    "test_command_line_exit_status",
    "test_angle_sweep_reports_every_angle",
)


#: Fixtures whose work the suite does once, and the group of tests that read each: pytest-xdist runs a
#: fixture once per worker process, so each group's tests go to one worker, and only there is it built
#: (the ModelNet40 preparation of the other worker would otherwise wait on this one's lock).
_SHARED_FIXTURES = {"tiny_run": "tiny_run", "modelnet_test": "modelnet", "modelnet_train": "modelnet"}


@functools.cache
def _fixture_groups(path: pathlib.Path) -> dict[str, str]:
    """{test function name: group} of a test module, from the fixtures its test functions take."""
    groups = {}
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef) and node.name.startswith("test_"):
            shared = [_SHARED_FIXTURES[a.arg] for a in node.args.args if a.arg in _SHARED_FIXTURES]
            if shared:
                groups[node.name] = shared[0]
    return groups


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, which the test extra installs
def pytest_xdist_make_scheduler(config, log):
    """pytest-xdist's scope scheduling with a scope per test, but one per group of :data:`_SHARED_FIXTURES`
    (its ``--dist loadgroup`` marks do not reach the scheduler under pytest 9.2: pytest-xdist issue #1386).
    Groups go first, then single tests in collection order, each worker holding two at a time."""
    if config.getvalue("dist") != "load":  # another --dist asked for by name
        return None
    from xdist.scheduler import LoadScopeScheduling

    class SharedFixtureScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            file, _, name = nodeid.partition("::")
            return _fixture_groups(ROOT / file).get(name.split("[")[0], nodeid)

    return SharedFixtureScheduling(config, log)


def pytest_collection_modifyitems(session, config, items):
    def order(item):
        if item.path.name in _SLOW_MODULES:
            return 0
        name = item.originalname
        return 1 + _LONG_TESTS.index(name) if name in _LONG_TESTS else 1 + len(_LONG_TESTS)

    items.sort(key=order)  # stable: order kept otherwise


def box_room(n: int, seed: int) -> np.ndarray:
    """Floor and four walls of a 4 x 4 x 2.5 room, sampled at random: a quarter turn about the floor's normal
    maps it onto itself."""
    rng = np.random.default_rng(seed)
    corner, up = np.array([-2.0, -2.0, 0.0]), np.array([0.0, 0.0, 2.5])
    sides = [(corner, [4.0, 0, 0], [0, 4.0, 0])]
    sides += [(corner, [4.0, 0, 0], up), (corner + [0, 4, 0], [4.0, 0, 0], up)]
    sides += [(corner, [0, 4.0, 0], up), (corner + [4, 0, 0], [0, 4.0, 0], up)]
    shares = rng.uniform(0, 1, (len(sides), n // len(sides), 2))
    points = [o + s[:, :1] * np.array(u) + s[:, 1:] * np.array(v) for (o, u, v), s in zip(sides, shares)]
    return np.concatenate(points)


def rendered_legend(path) -> list[str]:
    """The legend entries of an HTML page (dit_jax.pictures.view) as headless Chromium renders it, after its script ran;
    skips where no Chromium is installed (Debian: apt-get install chromium)."""
    import re
    import shutil
    import subprocess

    import pytest

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no Chromium to render the page (apt-get install chromium)")
    dom = subprocess.run(
        [browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=10000", "--dump-dom",
         pathlib.Path(path).resolve().as_uri()],
        capture_output=True, text=True, timeout=120,
    ).stdout  # fmt: skip
    assert "<canvas" in dom and 'class="gl-container"' in dom, "the 3D scene did not render"
    return re.findall(r'class="legendtext"[^>]*data-unformatted="([^"]*)"', dom)


def scan_set(clouds):
    """``clouds`` as a :class:`dit_jax.pipeline.stages.ScanSet` without features, as a stand-in registrar's
    ``prepare_scans`` returns them (a ScanSet is returned as it is)."""
    from dit_jax.geometry import neighbours
    from dit_jax.pipeline import stages

    if isinstance(clouds, stages.ScanSet):
        return clouds
    return stages.ScanSet(list(clouds), None, [-1] * len(clouds), [neighbours.point_spacing(c) for c in clouds])


def exact_result(motion: np.ndarray, level: str, fitness: float = 0.9):
    """A :class:`dit_jax.pipeline.result.Result` of ``motion`` (4, 4) at the verdict's ``level``, as a stand-in
    registrar returns it."""
    from dit_jax.pipeline.result import Result

    return Result(
        motion[:3, :3],
        motion[:3, 3],
        motion,
        np.arange(3),
        np.arange(3),
        np.ones(3),
        1.0,
        fitness,
        0.0,
        refinement=None,
        refine_seconds=0.0,
        verdict=level == "trusted",
        level=level,
        verdict_rule="agreement",
        threshold=1.0,
        agreement=0.5,
        direction="forward",
        start_turn=0.0,
        agreement_band=None,
    )
