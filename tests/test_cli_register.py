"""`dit-register`: prints the transform, writes the moved source, and refuses bad input with exit status 2."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest

from dit_jax import io
from dit_jax.cli import register
from dit_jax.data.pairs import euler_zyx_to_matrix
from dit_jax.network import checkpoint, configs, model
from dit_jax.pipeline import network_stage


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A smooth surface (a bumpy sphere) and the same surface moved, shuffled, as two files."""
    rng = np.random.default_rng(0)
    d = rng.normal(size=(600, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    src = d * (1 + 0.2 * np.sin(3 * d[:, :1]) * np.cos(2 * d[:, 1:2])) * 20.0 + 300.0
    rotation = euler_zyx_to_matrix([20.0, -10.0, 15.0])
    tgt = (src @ rotation.T + [2.0, -1.0, 3.0])[rng.permutation(600)]
    folder = tmp_path_factory.mktemp("pair")
    io.write(folder / "src.ply", src)
    io.write(folder / "tgt.pcd", tgt)
    return folder, src, tgt


def run(capsys, *argv):
    code = register.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_prints_matrix_and_writes_moved_source(capsys, tiny_checkpoint, pair):
    folder, src, _ = pair
    code, out, err = run(
        capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--out", folder / "moved.xyz"
    )
    assert code == 0, err
    rows = [line for line in out.splitlines() if line.strip().startswith("[")]
    assert len(rows) == 4 and "inlier ratio" in out and "128 of 600 source points" in out
    matrix = np.array([[float(v) for v in row.replace("[", " ").replace("]", " ").split()] for row in rows])
    moved = io.read(folder / "moved.xyz")
    np.testing.assert_allclose(moved, src @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-5)


def test_json_output_and_icp_by_default(capsys, tiny_checkpoint, pair):
    """The default refines by ICP (the better result on every setting measured); --refine none does not."""
    folder, _, _ = pair
    code, out, _ = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--json")
    report = json.loads(out)
    assert code == 0 and np.shape(report["matrix"]) == (4, 4) and report["points_used"] == 128
    assert report["matrix"][3] == [0.0, 0.0, 0.0, 1.0] and 0.0 <= report["inlier_ratio"] <= 1.0
    assert report["refinement"] == "icp" and report["refine_seconds"] > 0
    code, out, _ = run(
        capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--json", "--refine", "none"
    )
    assert code == 0 and json.loads(out)["refinement"] is None and json.loads(out)["refine_seconds"] == 0
    # --help names where --best-direction's default lives: the checkpoint's inference settings.
    option_help = " ".join(register._parser().format_help().split()).split("--best-direction")[-1]
    assert "(default: the checkpoint's)" in option_help.split("--no-verdict-status")[0]


def test_any_rotation_searches_the_turned_starts_and_says_which_it_kept(capsys, tiny_checkpoint, pair, monkeypatch):
    """--any-rotation runs the network from the 24 turns of the source (one batch per direction) and prints
    the turn it went on from; the JSON report carries it too."""
    folder, _, _ = pair
    batches = []
    original = network_stage._register

    def counting(params, src, tgt, config):
        batches.append(src.shape[0])
        return original(params, src, tgt, config)

    monkeypatch.setattr(network_stage, "_register", counting)
    code, out, err = run(
        capsys,
        folder / "src.ply",
        folder / "tgt.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--any-rotation",
    )
    assert code == 0, err
    assert batches == [24, 24] and "rotation search: went on from a start turned" in out
    code, out, _ = run(
        capsys,
        folder / "src.ply",
        folder / "tgt.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--any-rotation",
        "--json",
    )
    assert code == 0 and json.loads(out)["start_turn_deg"] in {0.0, 90.0, 120.0, 180.0}
    batches.clear()
    run(capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--refine", "none")
    assert batches == [1, 1]


def _bad_inputs(folder):
    """(name, src path, expected fragment) for every kind of bad input the issue lists."""
    rng = np.random.default_rng(1)
    cases = []
    cases.append(("missing", folder / "nope.ply", "no such file"))
    (folder / "garbage.ply").write_bytes(b"\x00" * 64)
    cases.append(("unreadable", folder / "garbage.ply", "not a PLY file"))
    (folder / "cloud.e57").write_text("ASTM-E57")
    cases.append(("unknown format", folder / "cloud.e57", "unknown format"))
    nan = rng.normal(size=(300, 3))
    nan[5, 0] = np.nan
    io.write(folder / "nan.npy", nan)
    cases.append(("nan", folder / "nan.npy", "NaN or Inf"))
    inf = rng.normal(size=(300, 3))
    inf[9, 2] = np.inf
    io.write(folder / "inf.ply", inf)
    cases.append(("inf", folder / "inf.ply", "NaN or Inf"))
    io.write(folder / "few.xyz", rng.normal(size=(5, 3)))
    cases.append(("too few points", folder / "few.xyz", "needs at least"))
    np.save(folder / "two.npy", rng.normal(size=(300, 2)))
    cases.append(("not three coordinates", folder / "two.npy", "not three coordinates"))
    io.write(folder / "same.pcd", np.tile([[1.0, 2.0, 3.0]], (300, 1)))
    cases.append(("identical points", folder / "same.pcd", "same point"))
    io.write(folder / "line.xyz", np.linspace(0, 1, 300)[:, None] * [1.0, 2.0, 3.0])
    cases.append(("a line", folder / "line.xyz", "lie on one line"))
    return cases


@pytest.mark.parametrize("case", range(9))
def test_bad_input_exits_2_with_one_line_and_no_output(capsys, tmp_path, tiny_checkpoint, pair, case):
    folder, _, _ = pair
    name, bad, fragment = _bad_inputs(tmp_path)[case]
    out_file = tmp_path / "out.ply"
    for argv in ((bad, folder / "tgt.pcd"), (folder / "src.ply", bad)):
        code, out, err = run(capsys, *argv, "--checkpoint", tiny_checkpoint, "--out", out_file)
        assert code == 2, (name, out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"dit-register: error: {bad}:"), (name, err)
        assert fragment in lines[0] and "Traceback" not in err
        assert not out_file.exists() and not [p for p in os.listdir(tmp_path) if p.startswith(".tmp")]


def test_bad_checkpoint_and_output_path(capsys, tmp_path, pair):
    folder, _, _ = pair
    code, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tmp_path / "none")
    assert code == 2 and err.count("\n") == 1 and "none" in err
    code, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--out", tmp_path / "a.e57")
    assert code == 2 and "unknown output format" in err
    code, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--out", tmp_path / "a.stl")
    assert code == 2 and "a .stl file is written only as SRC moved" in err  # a cloud SRC has no mesh to move
    code, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--out", tmp_path / "no" / "a.ply")
    assert code == 2 and "folder does not exist" in err


def test_large_clouds_are_downsampled_unless_refused(capsys, tmp_path, tiny_checkpoint, pair):
    folder, _, _ = pair
    code, out, err = run(
        capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--max-points", 400
    )
    assert code == 0 and "600 points, above --max-points; using a random 400" in err
    assert "128 of 400 source points" in out
    code, _, err = run(
        capsys,
        folder / "src.ply",
        folder / "tgt.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--max-points",
        400,
        "--no-downsample",
    )
    assert code == 2 and "above the limit of 400" in err and err.count("\n") == 1


def test_nonfinite_points_refused_unless_left_out(capsys, tmp_path, tiny_checkpoint, pair):
    """A target with NaN rows, as an organized PCD file marks pixels without a return: refused with the flag
    named, or registered without them after one note that says how many were left out."""
    folder, _, tgt = pair
    holes = np.concatenate([tgt, np.full((200, 3), np.nan)])[np.random.default_rng(0).permutation(800)]
    io.write(tmp_path / "holes.pcd", holes)
    code, _, err = run(capsys, folder / "src.ply", tmp_path / "holes.pcd", "--checkpoint", tiny_checkpoint)
    assert code == 2 and "200 of 800 points have NaN or Inf" in err and "--drop-nonfinite" in err
    code, out, err = run(
        capsys,
        folder / "src.ply",
        tmp_path / "holes.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--drop-nonfinite",
        "--max-points",
        500,
    )
    assert code == 0 and "rotation" in out, err
    assert err.splitlines() == [
        f"dit-register: note: {folder / 'src.ply'}: 600 points, above --max-points; using a random 500",
        f"dit-register: note: {tmp_path / 'holes.pcd'}: left out 200 of 800 points with NaN or Inf coordinates",
        f"dit-register: note: {tmp_path / 'holes.pcd'}: 600 points, above --max-points; using a random 500",
    ]
    code, out, err = run(
        capsys,
        tmp_path / "holes.pcd",
        folder / "src.ply",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--drop-nonfinite",
        "--out",
        tmp_path / "moved.pcd",
    )
    rows = [line for line in out.splitlines() if line.strip().startswith("[")]
    matrix = np.array([[float(v) for v in row.replace("[", " ").replace("]", " ").split()] for row in rows])
    with pytest.warns(io.NonFiniteWarning):  # written whole, the holes where they were
        moved = io.read(tmp_path / "moved.pcd", drop_nonfinite=True)
    kept = np.isfinite(holes).all(axis=1)
    assert code in (0, 3) and b"\nPOINTS 800\n" in (tmp_path / "moved.pcd").read_bytes()
    np.testing.assert_allclose(moved, holes[kept] @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-4)


def test_a_mesh_registers_as_points_sampled_over_its_surface(capsys, tmp_path, tiny_checkpoint, pair):
    """An OBJ mesh (a bumpy sphere as a latitude-longitude grid) as SRC: sampled at io.MESH_POINTS (capped by
    --max-points), registered, and --out writes the samples moved; a mesh cannot be an output."""
    folder, _, _ = pair
    theta, phi = np.meshgrid(
        np.linspace(0.1, np.pi - 0.1, 20), np.linspace(0, 2 * np.pi, 40, endpoint=False), indexing="ij"
    )
    d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    vertices = d * (1 + 0.2 * np.sin(3 * d[:, :1]) * np.cos(2 * d[:, 1:2])) * 20.0 + 300.0
    index = np.arange(20 * 40).reshape(20, 40)
    quads = np.stack([index[:-1], np.roll(index, -1, 1)[:-1], np.roll(index, -1, 1)[1:], index[1:]], -1)
    faces = "".join(f"f {' '.join(str(i + 1) for i in q)}\n" for q in quads.reshape(-1, 4))
    (tmp_path / "mesh.obj").write_text("".join(f"v {x} {y} {z}\n" for x, y, z in vertices.tolist()) + faces)
    code, out, err = run(
        capsys,
        tmp_path / "mesh.obj",
        folder / "tgt.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--max-points",
        3000,
        "--out",
        tmp_path / "moved.ply",
    )
    assert code == 0 and "128 of 3000 source points" in out and err == "", err
    rows = [line for line in out.splitlines() if line.strip().startswith("[")]
    matrix = np.array([[float(v) for v in row.replace("[", " ").replace("]", " ").split()] for row in rows])
    samples = io.read(tmp_path / "mesh.obj", max_points=3000)  # the same seed: the same samples
    np.testing.assert_allclose(io.read(tmp_path / "moved.ply"), samples @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-4)
    code, out, err = run(
        capsys,
        tmp_path / "mesh.obj",
        folder / "tgt.pcd",
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--max-points",
        3000,
        "--out",
        tmp_path / "moved.obj",
    )
    assert code == 0 and f"wrote {tmp_path / 'moved.obj'}" in out, err
    moved_vertices, _ = io.read_mesh(tmp_path / "moved.obj")  # the same registration: the same matrix
    np.testing.assert_allclose(moved_vertices, vertices @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-4)
    for other, fragment in (
        ("moved.stl", "a .stl file is written only as SRC moved, where SRC is a .stl"),
        ("moved.las", "a .las file is written only as SRC moved"),
        ("moved.e57", "unknown output format"),
    ):
        code, _, err = run(
            capsys,
            tmp_path / "mesh.obj",
            folder / "tgt.pcd",
            "--checkpoint",
            tiny_checkpoint,
            "--out",
            tmp_path / other,
        )
        assert code == 2 and err.count("\n") == 1 and fragment in err, err


def test_a_ply_source_is_written_whole(capsys, tmp_path, tiny_checkpoint, pair):
    """--out with SRC's own extension: a PLY cloud read as a random subset (--max-points) is still written
    with every point and its colours, moved by the printed matrix; another extension gets the points read."""
    folder, src, _ = pair
    colours = np.arange(len(src)) % 256
    vertex = np.zeros(len(src), [("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("red", "u1")])
    vertex["x"], vertex["y"], vertex["z"], vertex["red"] = *src.T, colours
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(src)}\nproperty double x\n"
        "property double y\nproperty double z\nproperty uchar red\nend_header\n"
    )
    (tmp_path / "coloured.ply").write_bytes(header.encode() + vertex.tobytes())
    for out_name in ("moved.ply", "moved.npy"):
        code, out, err = run(
            capsys,
            tmp_path / "coloured.ply",
            folder / "tgt.pcd",
            "--checkpoint",
            tiny_checkpoint,
            "--refine",
            "none",
            "--max-points",
            400,
            "--out",
            tmp_path / out_name,
        )
        assert code in (0, 3) and "using a random 400" in err
        rows = [line for line in out.splitlines() if line.strip().startswith("[")]
        matrix = np.array([[float(v) for v in row.replace("[", " ").replace("]", " ").split()] for row in rows])
        moved = io.read(tmp_path / out_name)
        if out_name == "moved.ply":
            np.testing.assert_allclose(moved, src @ matrix[:3, :3].T + matrix[:3, 3], atol=1e-6)
            back = np.frombuffer((tmp_path / out_name).read_bytes()[len(header) :], vertex.dtype)
            assert back["red"].tolist() == colours.tolist()
        else:
            assert moved.shape == (400, 3)


def test_clouds_of_different_units_warn_but_still_register(capsys, tmp_path, tiny_checkpoint, pair):
    """A target in millimetres against a source in metres (1000 times the size): one warning line naming both
    files; the transform is still printed and the status is the verdict's. Same-size clouds give none."""
    folder, _, tgt = pair
    io.write(tmp_path / "tgt_mm.pcd", tgt * 1000.0)
    code, out, err = run(
        capsys, folder / "src.ply", tmp_path / "tgt_mm.pcd", "--checkpoint", tiny_checkpoint, "--refine", "none"
    )
    assert code == 0 and "rotation" in out
    (line,) = [line for line in err.splitlines() if "same units" in line]
    assert line.startswith(
        f"dit-register: warning: {tmp_path / 'tgt_mm.pcd'} is 1,000 times the size of {folder / 'src.ply'}"
    )
    _, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", tiny_checkpoint, "--refine", "none")
    assert "same units" not in err


def test_console_script_exit_status(tmp_path):
    """The installed entry point, as a user runs it: no traceback, status 2."""
    proc = subprocess.run(
        [sys.executable, "-m", "dit_jax.cli.register", str(tmp_path / "a.ply"), str(tmp_path / "b.ply")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"dit-register: error: {tmp_path / 'a.ply'}: no such file"


@pytest.mark.parametrize(
    "rule,threshold,expected",
    [("agreement", -1.0, 3), ("agreement", 180.0, 0), ("fitness", 1.01, 3), ("fitness", 0.0, 0)],
)
def test_a_probably_wrong_result_warns_and_exits_3_but_is_still_written(
    capsys, tmp_path, pair, rule, threshold, expected
):
    """The verdict's thresholds come with the checkpoint (agreement, the default, or --verdict fitness); a
    result they do not trust, with no validation band to say it is mostly right (this checkpoint records
    none), is "probably wrong": still printed and written, one warning line goes to stderr and the status is 3
    (0 with --no-verdict-status)."""
    config = configs.tiny()
    ckpt = checkpoint.save(
        tmp_path / "m",
        model.init(jax.random.PRNGKey(0), config),
        config,
        extra={
            "inference_settings": {
                "n_points": 128,
                "min_fitness": threshold,
                "max_disagreement_network": threshold,
                "max_disagreement_icp": threshold,
            }
        },
    )
    folder, _, _ = pair
    code, out, err = run(
        capsys,
        folder / "src.ply",
        folder / "tgt.pcd",
        "--checkpoint",
        ckpt,
        "--out",
        tmp_path / "moved.ply",
        "--json",
        "--verdict",
        rule,
    )
    report = json.loads(out)
    assert code == expected and report["level"] == ("probably wrong" if expected else "trusted")
    assert report["verdict_rule"] == rule and 0.0 <= report["fitness"] <= 1.0
    if rule == "agreement":
        assert report["threshold"] == threshold and 0.0 <= report["agreement_deg"] <= 180.0
    else:
        assert report["threshold"] == threshold and report["agreement_deg"] is None
    assert (tmp_path / "moved.ply").exists()
    if expected:
        assert err.count("\n") == 1 and err.startswith("dit-register: warning: the result is probably wrong")
        code, _, _ = run(
            capsys,
            folder / "src.ply",
            folder / "tgt.pcd",
            "--checkpoint",
            ckpt,
            "--no-verdict-status",
            "--verdict",
            rule,
        )
        assert code == 0
    else:
        assert err == ""


@pytest.mark.parametrize("right,level,expected", [(19, "unconfirmed", 0), (2, "probably wrong", 3)])
def test_an_untrusted_result_is_unconfirmed_where_its_band_was_mostly_right(
    capsys, tmp_path, pair, right, level, expected
):
    """Beyond the threshold, the agreement band the checkpoint records decides: a band where 19 of 20
    validation results were right makes the result "unconfirmed" (status 0, one note line quoting the band's
    rate); one where 2 of 20 were makes it "probably wrong" (status 3, one warning line)."""
    config = configs.tiny()
    bands = [[None, 20, right]]  # every agreement falls in this one band
    ckpt = checkpoint.save(
        tmp_path / "m",
        model.init(jax.random.PRNGKey(0), config),
        config,
        extra={
            "inference_settings": {
                "n_points": 128,
                "max_disagreement_network": -1.0,
                "max_disagreement_icp": -1.0,
                "agreement_bands_network": bands,
                "agreement_bands_icp": bands,
            }
        },
    )
    folder, _, _ = pair
    code, out, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", ckpt, "--refine", "none")
    assert code == expected and f"\n{level}: registering the target onto the source" in out
    rate = f"of the 20 validation results that disagreed by more than 0 deg, {5 * right} % were within 5 deg"
    assert err.count("\n") == 1 and rate in err, err
    assert err.startswith(
        "dit-register: note: the result is not confirmed"
        if expected == 0
        else "dit-register: warning: the result is probably wrong"
    )


def test_max_disagreement_overrides_the_checkpoints_threshold(capsys, tmp_path, pair):
    """--max-disagreement DEG replaces the agreement threshold the checkpoint carries, for either refinement:
    a checkpoint that trusts nothing (-1) trusts the same result at 180 (status 0, the threshold reported).
    A value outside 0-180, or beside --verdict fitness, is refused with status 2 before any work."""
    config = configs.tiny()
    ckpt = checkpoint.save(
        tmp_path / "m",
        model.init(jax.random.PRNGKey(0), config),
        config,
        extra={"inference_settings": {"n_points": 128, "max_disagreement_network": -1.0, "max_disagreement_icp": -1.0}},
    )
    folder, _, _ = pair
    for refine in ("none", "icp"):
        code, out, err = run(
            capsys,
            folder / "src.ply",
            folder / "tgt.pcd",
            "--checkpoint",
            ckpt,
            "--json",
            "--refine",
            refine,
            "--max-disagreement",
            180,
        )
        report = json.loads(out)
        assert code == 0 and err == "" and report["level"] == "trusted" and report["threshold"] == 180
    for argv, fragment in (
        (("--max-disagreement", -0.5), "between 0 and 180"),
        (("--max-disagreement", 181), "between 0 and 180"),
        (("--max-disagreement", 1, "--verdict", "fitness"), "cannot go with --verdict fitness"),
    ):
        code, out, err = run(
            capsys, folder / "src.ply", folder / "tgt.pcd", "--checkpoint", ckpt, "--out", tmp_path / "x.ply", *argv
        )
        assert code == 2 and fragment in err and err.count("\n") == 1 and out == ""
        assert not (tmp_path / "x.ply").exists()


def test_real_scans_network_alone_is_trusted_only_where_both_directions_agree_closely(capsys, dragon_dir):
    """The shipped network alone (--refine none) on two pairs of real Stanford Dragon scans 24 degrees apart:
    48 -> 72 is wrong (more than 5 degrees off, the two directions far apart), and the verdict says so with
    status 3 (the transform is still printed). 312 -> 336 is right (within 5 degrees), and its two directions
    agree to about the network alone's threshold: so close that only the consistency of verdict, agreement and
    exit status is asserted for it (trusted or unconfirmed and status 0, or probably wrong and status 3). With
    ICP, the default, 0 -> 24 is trusted: the test below."""
    from dit_jax.data import scans

    series = {s.name: s for s in scans.load_scans(dragon_dir)}
    for source, target, right in (
        ("dragonStandRight_312", "dragonStandRight_336", True),
        ("dragonStandRight_48", "dragonStandRight_72", False),
    ):
        code, out, err = run(
            capsys, dragon_dir / f"{source}.ply", dragon_dir / f"{target}.ply", "--json", "--refine", "none"
        )
        report = json.loads(out)
        truth, _ = scans.relative_motion(series[source], series[target])
        rotation = np.asarray(report["matrix"])[:3, :3]
        error = np.degrees(np.arccos(np.clip((np.trace(rotation.T @ truth) - 1) / 2, -1, 1)))
        assert (error < 5) == right, (source, error)
        trusted = report["agreement_deg"] <= report["threshold"]
        level = report["level"]
        assert (level == "trusted") == trusted, report
        assert code == (3 if level == "probably wrong" else 0), (source, code, err)
        assert ("probably wrong" in err) == (level == "probably wrong"), err
        if not right:
            assert level == "probably wrong", (source, error, report["agreement_deg"])


def test_refine_and_plot_on_the_readme_example_pair(capsys, tmp_path):
    """The README's example (two scan-like views of a chair sampled independently, true motion in
    examples/chair_truth.txt): --refine icp lands closer to the truth than the network alone, within 1.5
    degrees, and --plot writes a PNG. The network alone (a few degrees off) is not trusted: its directions agree
    less closely than its threshold, in a band with too few validation results to vouch for it, so it is
    "probably wrong" (status 3); DIT+ICP's two directions agree within the shipped threshold, so it is
    "trusted" (status 0), as the README shows. These 400-point clouds get no second candidate."""
    from dit_jax.geometry.rigid import rotation_angle_deg

    examples = os.path.join(os.path.dirname(__file__), "..", "examples")
    truth = np.loadtxt(os.path.join(examples, "chair_truth.txt"))
    errors = {}
    for refine, status in (("none", 3), ("icp", 0)):
        code, out, err = run(
            capsys,
            os.path.join(examples, "chair_src.ply"),
            os.path.join(examples, "chair_tgt.pcd"),
            "--refine",
            refine,
            "--plot",
            tmp_path / f"{refine}.png",
            "--json",
        )
        assert code == status, err
        report = json.loads(out)
        errors[refine] = rotation_angle_deg(np.asarray(report["matrix"])[:3, :3].T @ truth[:3, :3])
        assert report["refinement"] == (None if refine == "none" else "icp")
        if refine == "icp":
            assert report["level"] == "trusted"
        assert (tmp_path / f"{refine}.png").read_bytes()[:4] == b"\x89PNG"
    assert errors["icp"] < errors["none"] - 1.0 and errors["icp"] < 1.5, errors


def test_bad_plot_path_exits_2_before_any_work(capsys, tmp_path, pair):
    folder, _, _ = pair
    for bad, fragment in ((tmp_path / "x.jpg", "expected a .png"), (tmp_path / "no" / "x.png", "does not exist")):
        code, _, err = run(capsys, folder / "src.ply", folder / "tgt.pcd", "--plot", bad)
        assert code == 2 and fragment in err and not os.path.exists(bad)


def test_real_scans_refined_by_default_land_within_a_few_degrees(capsys, dragon_dir):
    """The default refinement (GICP on scans this dense) on dragon pairs 24 degrees apart
    (docs/eval_stanford_dragon): 0 -> 24 ends within half a degree; where the network is far off (48 -> 72),
    the pipeline still ends within a few degrees. The first pair with the default verdict: trusted, status 0
    (both directions agree); the other with the one-direction fitness verdict, which is all this accuracy
    check needs."""
    from dit_jax.data import scans
    from dit_jax.geometry.rigid import rotation_angle_deg

    series = {s.name: s for s in scans.load_scans(dragon_dir)}
    for source, target, bound in (
        ("dragonStandRight_0", "dragonStandRight_24", 0.5),
        ("dragonStandRight_48", "dragonStandRight_72", 3.0),
    ):
        first = source == "dragonStandRight_0"
        code, out, err = run(
            capsys,
            dragon_dir / f"{source}.ply",
            dragon_dir / f"{target}.ply",
            "--json",
            "--verdict",
            "agreement" if first else "fitness",
        )
        truth, _ = scans.relative_motion(series[source], series[target])
        error = rotation_angle_deg(np.asarray(json.loads(out)["matrix"])[:3, :3].T @ truth)
        assert error < bound and json.loads(out)["refinement"] in ("icp", "gicp"), (source, error)
        if first:
            assert code == 0 and err == "" and json.loads(out)["level"] == "trusted", err


def test_a_list_of_pairs_in_shards_resumes_and_records_every_pair(capsys, tmp_path, tiny_checkpoint, pair):
    """--pairs LIST registers each 'SRC TGT' line through one loaded model, one JSON line per pair (an unreadable
    file gets a line with its error and status 2, the others still run); --shard I/N takes every N-th pair, so
    the shards together cover the list once; --results appends and a second run skips what is recorded, and
    errors are tried again on every run, and a last line cut short by a kill stays where it is."""
    folder, _, _ = pair
    listing = tmp_path / "pairs.txt"
    listing.write_text(
        f"# source target\n{folder / 'src.ply'} {folder / 'tgt.pcd'}\n\n"
        f"{folder / 'tgt.pcd'} {folder / 'src.ply'}  # the other way\n"
        f"{folder / 'src.ply'} missing.ply\n"
    )
    results = tmp_path / "results.jsonl"
    common = [
        "--pairs",
        listing,
        "--results",
        results,
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--no-progress",
        "--no-verdict-status",
    ]
    code, out, err = run(capsys, *common, "--shard", "1/2")
    assert code == 0 and out == "", err
    records = [json.loads(line) for line in results.read_text().splitlines()]
    assert [r["index"] for r in records] == [1] and len(np.asarray(records[0]["matrix"])) == 4
    code, out, err = run(capsys, *common, "--shard", "0/2")
    records = [json.loads(line) for line in results.read_text().splitlines()]
    assert code == 2 and "1 of 2 pairs could not be registered" in err
    assert sorted(r["index"] for r in records) == [0, 1, 2]
    assert "missing.ply" in next(r for r in records if r["index"] == 2)["error"]
    # Resume: the two results are kept, the error is tried again (a line of its own, status 2 again).
    code, _, err = run(capsys, *common)
    assert code == 2 and len(results.read_text().splitlines()) == 4, err
    # A last line cut short by a kill is kept as it is, reported, and its pair registered again.
    text = results.read_text()
    results.write_text(text + text.splitlines()[0][:30])
    code, _, err = run(capsys, *common)
    lines = results.read_text().splitlines()
    assert code == 2 and "last line is cut short" in err and len(lines) == 6
    assert lines[4] == text.splitlines()[0][:30] and lines[:4] == text.splitlines()
    # Without --results the lines go to stdout; bad combinations are refused before any work.
    code, out, _ = run(
        capsys,
        "--pairs",
        listing,
        "--checkpoint",
        tiny_checkpoint,
        "--refine",
        "none",
        "--no-progress",
        "--shard",
        "0/3",
    )
    assert code == 0 and [json.loads(line)["index"] for line in out.splitlines()] == [0]
    for argv, fragment in (
        ((folder / "src.ply", "--pairs", listing), "cannot go with SRC TGT"),
        (("--pairs", listing, "--shard", "2/2"), "expected I/N"),
        (("--pairs", tmp_path / "none.txt"), "none.txt"),
        ((folder / "src.ply", folder / "tgt.pcd", "--shard", "0/2"), "go with --pairs"),
    ):
        code, out, err = run(capsys, *argv)
        assert code == 2 and fragment in err and out == "", err


def _pair_list(tmp_path, pair, count: int, name: str = "pairs.txt"):
    """A list of ``count`` distinct pairs (copies of the pair's source file, one target), and its path."""
    folder, _, _ = pair
    lines = []
    for k in range(count):
        copy = tmp_path / f"src_{k}.ply"
        if not copy.exists():
            copy.write_bytes((folder / "src.ply").read_bytes())
        lines.append(f"{copy} {folder / 'tgt.pcd'}")
    listing = tmp_path / name
    listing.write_text("\n".join(lines) + "\n")
    return listing


def _list_args(listing, results, checkpoint):
    return ["--pairs", listing, "--results", results, "--checkpoint", checkpoint, "--refine", "none", "--no-progress"]


def test_resume_keeps_every_record_around_a_blank_line_and_matches_pairs_not_positions(
    capsys, tmp_path, tiny_checkpoint, pair
):
    """A finished 10-pair file with a blank line after record 3: resuming deletes nothing, registers nothing
    and says nothing of it. A different 5-pair list on that file is refused with one line (its records are of
    another list), and runs beside them with --reuse-results, registering its own pairs."""
    listing = _pair_list(tmp_path, pair, 10)
    results = tmp_path / "results.jsonl"
    code, _, err = run(capsys, *_list_args(listing, results, tiny_checkpoint), "--no-verdict-status")
    assert code == 0, err
    lines = results.read_text().splitlines()
    assert len(lines) == 10
    results.write_text("\n".join(lines[:3] + [""] + lines[3:]) + "\n")
    before = results.read_text()
    code, _, err = run(capsys, *_list_args(listing, results, tiny_checkpoint), "--no-verdict-status")
    assert code == 0 and results.read_text() == before, err
    other = tmp_path / "other"
    other.mkdir()
    five = _pair_list(other, pair, 5)
    code, out, err = run(capsys, *_list_args(five, results, tiny_checkpoint))
    assert code == 2 and err.count("\n") == 1 and "other pairs or other settings" in err and out == ""
    assert results.read_text() == before
    code, _, err = run(capsys, *_list_args(five, results, tiny_checkpoint), "--reuse-results", "--no-verdict-status")
    assert code == 0, err
    assert results.read_text().startswith(before) and len(results.read_text().splitlines()) == 11 + 5


def test_failed_pairs_are_retried_and_a_probably_wrong_list_still_exits_3(capsys, tmp_path, tiny_checkpoint, pair):
    """Pairs that failed (an unreadable file) are tried again on the next run, and succeed once the file is
    there; a list whose results are probably wrong exits 3 on a resumed run too, registering nothing again."""
    listing = _pair_list(tmp_path, pair, 3)
    missing = tmp_path / "src_1.ply"
    kept = missing.read_bytes()
    missing.unlink()
    results = tmp_path / "results.jsonl"
    code, _, err = run(capsys, *_list_args(listing, results, tiny_checkpoint), "--max-disagreement", "0")
    assert code == 2 and "1 of 3 pairs could not be registered" in err
    missing.write_bytes(kept)
    code, _, err = run(capsys, *_list_args(listing, results, tiny_checkpoint), "--max-disagreement", "0")
    records = [json.loads(line) for line in results.read_text().splitlines()]
    assert len(records) == 4 and "error" in records[1] and records[3]["index"] == 1 and "level" in records[3]
    wrong = sum(r.get("level") == "probably wrong" for r in records)
    assert (code == 3) == (wrong > 0) and (code == 0) == (wrong == 0), err
    if wrong:
        code, _, err = run(capsys, *_list_args(listing, results, tiny_checkpoint), "--max-disagreement", "0")
        assert code == 3 and "probably wrong" in err and len(results.read_text().splitlines()) == 4


def test_two_processes_on_one_results_file_register_each_pair_once(tmp_path, tiny_checkpoint, pair):
    """Two shards and a duplicate of one of them, at once, on one file: every pair has exactly one record."""
    listing = _pair_list(tmp_path, pair, 8)
    results = tmp_path / "results.jsonl"
    base = [sys.executable, "-m", "dit_jax.cli.register", *map(str, _list_args(listing, results, tiny_checkpoint))]
    runs = [
        subprocess.Popen([*base, "--shard", shard, "--no-verdict-status"], stderr=subprocess.PIPE, text=True)
        for shard in ("0/2", "1/2", "0/2")
    ]
    for process in runs:
        assert process.wait(timeout=300) == 0, process.stderr.read()
    records = [json.loads(line) for line in results.read_text().splitlines()]
    assert sorted(r["index"] for r in records) == list(range(8))


def test_out_never_replaces_an_input_and_is_checked_before_any_work(capsys, tmp_path, tiny_checkpoint, pair):
    """--out naming the source or the target (or a link to one), or a folder: one line, status 2, the inputs
    untouched, before the model loads."""
    folder, _, _ = pair
    src, tgt = tmp_path / "x.ply", tmp_path / "t.pcd"
    src.write_bytes((folder / "src.ply").read_bytes())
    tgt.write_bytes((folder / "tgt.pcd").read_bytes())
    link = tmp_path / "link.ply"
    link.symlink_to(src)
    before = src.read_bytes(), tgt.read_bytes()
    for out, fragment in (
        (src, "never replaces an input"),
        (tgt, "never replaces an input"),
        (link, "never replaces an input"),
    ):
        code, stdout, err = run(capsys, src, tgt, "--checkpoint", "no_such_checkpoint", "--out", out)
        assert code == 2 and fragment in err and err.count("\n") == 1 and stdout == "", err
    folder_out = tmp_path / "adir.ply"
    folder_out.mkdir()
    code, _, err = run(capsys, src, tgt, "--checkpoint", "no_such_checkpoint", "--out", folder_out)
    assert code == 2 and "is a folder" in err
    assert (src.read_bytes(), tgt.read_bytes()) == before


def test_list_errors_name_the_files_and_a_missing_list_reads_as_one_line(capsys, tmp_path, tiny_checkpoint, pair):
    """In a list, a cloud the model cannot take is named by its path (not "source"/"target"); a list that does
    not exist ends in one line naming it."""
    folder, _, _ = pair
    one = tmp_path / "one.xyz"
    one.write_text("1 2 3\n")
    listing = tmp_path / "pairs.txt"
    listing.write_text(f"{folder / 'src.ply'} {one}\n")
    code, out, _ = run(capsys, "--pairs", listing, "--checkpoint", tiny_checkpoint, "--refine", "none", "--no-progress")
    record = json.loads(out)
    assert code == 2 and record["error"].startswith(f"{one}: 1 point;")
    code, out, err = run(capsys, "--pairs", tmp_path / "none.txt")
    assert code == 2 and "none.txt" in err and err.count("\n") == 1 and "Errno" not in err
