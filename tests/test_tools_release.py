"""The release tools in tools/ (outside the package), each run on a tiny input: what the README's example pair
is made from, the embedded dataset, the training curves, the README's and the results pages' tables."""

import io as stdio
import json
import zipfile
from contextlib import redirect_stdout

import build_embedded_dataset
import make_example_pair
import numpy as np
import plot_training_curves
import readme_tables
import results_page
from conftest import ROOT

from dit_jax import io


def test_the_example_pair_is_what_the_tool_makes(tmp_path):
    make_example_pair.main(["--out", str(tmp_path)])
    for name in ("chair_src.ply", "chair_tgt.pcd"):
        np.testing.assert_array_equal(io.read(tmp_path / name), io.read(ROOT / "examples" / name), err_msg=name)
    assert (tmp_path / "chair_truth.txt").read_text() == (ROOT / "examples" / "chair_truth.txt").read_text()


def _catalogue(path, models):
    """A Sweet Home 3D furniture catalogue holding ``models`` ({name: OBJ text})."""
    lines = []
    with zipfile.ZipFile(path, "w") as archive:
        for number, (name, obj) in enumerate(models.items(), 1):
            archive.writestr(f"{name}.obj", obj)
            lines += [f"id#{number}=test#{name}", f"name#{number}={name}", f"model#{number}=/{name}.obj"]
        archive.writestr("PluginFurnitureCatalog.properties", "\n".join(lines) + "\n")


_BOX = "\n".join(
    [f"v {x} {y} {z}" for x in (0, 1) for y in (0, 2) for z in (0, 3)]
    + ["f 1 2 4 3", "f 5 7 8 6", "f 1 5 6 2", "f 3 4 8 7", "f 1 3 7 5", "f 2 6 8 4"]
)


def test_the_embedded_dataset_builds_from_furniture_catalogues(tmp_path):
    furniture = tmp_path / "furniture"
    furniture.mkdir()
    for catalogue in build_embedded_dataset.LICENCES:
        _catalogue(furniture / f"{catalogue}.sh3f", {"Chair": _BOX, "Widget": _BOX + "\nf 1 1 1"})
    build_embedded_dataset.main(["--furniture-dir", str(furniture), "--out", str(tmp_path / "out")])
    data = np.load(tmp_path / "out" / "sh3d_furniture_1024.npz")
    assert data["points"].shape == (2 * len(build_embedded_dataset.LICENCES), 1024, 3)
    radii = np.linalg.norm(data["points"] / build_embedded_dataset.QUANT, axis=2)
    assert radii.max() <= 1.0 and radii.max() > 0.99  # scaled into the unit sphere
    chair = build_embedded_dataset.MODELNET40.index("chair")
    assert list(data["label"][:2]) == [chair, -1]
    assert "| KatorLegaz/Chair | Chair |" in (tmp_path / "out" / "ATTRIBUTION.md").read_text()


def test_training_curves_plot_from_workdirs(tmp_path):
    lines = [{"step": 5, "split": "train", "loss": 1.0}]
    lines += [
        {"step": s, "split": "val", "rotation_error": 1e-3, "network_rotation_error": 9.0 / (1 + s)} for s in (0, 5)
    ]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in lines))
    plot_training_curves.main([str(tmp_path / "curves.png"), str(tmp_path), "--labels", "run"])
    assert (tmp_path / "curves.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_readme_tables_and_the_results_pages_are_made_from_the_committed_results():
    printed = stdio.StringIO()
    with redirect_stdout(printed):
        readme_tables.main([str(ROOT / "docs" / "eval_modelnet40_unseen")])
    assert printed.getvalue().count("\n|") > 5
    assert results_page.main(["--check"]) == 0


def test_the_baselines_tune_and_compare_their_refinement_on_a_pair(tmp_path, capsys):
    """tune_baselines's three stages on one pair of one setting (writing its JSON and report where told,
    not over the shipped ones), and compare_baseline_refinement's table on one pair of every setting."""
    import compare_baseline_refinement
    import tune_baselines

    out = tmp_path / "tuned.json"
    tune_baselines.main(
        ["--pairs", "1", "--points", "128", "--settings", "clean", "--checkpoint", "none",
         "--out-json", str(out), "--report", str(tmp_path / "report")]
    )  # fmt: skip
    tuned = json.loads(out.read_text())
    assert {"fpfh_ransac", "fgr", "fpfh_ransac_icp", "fgr_icp"} <= set(tuned["choice"])
    assert (tmp_path / "report.md").exists()
    capsys.readouterr()
    compare_baseline_refinement.main(["--pairs", "1", "--points", "128"])
    printed = capsys.readouterr().out
    assert "| fgr_icp | scan_high_noise |" in printed and "DIT's refinement on" in printed


def test_calibration_chooses_agreement_thresholds_on_validation_pairs(tmp_path):
    import calibrate

    out = tmp_path / "choice.json"
    assert calibrate.main(
        [str(ROOT / "dit_jax" / "network" / "weights" / "dit-cpu-modelnet40"), "--pairs", "2", "--verdict-only",
         "--verdict-settings", "clean", "--out", str(out)]
    ) == 0  # fmt: skip
    choice = json.loads(out.read_text())
    assert choice["pairs_per_setting"] == 2 and set(choice["verdict_max_disagreement"]) >= {"none", "icp"}
