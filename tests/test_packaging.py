"""What pyproject.toml promises users who install on a GPU."""

import pathlib
import re
import tomllib

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_the_cuda_extra_brings_jax_with_cuda_12_at_the_projects_jax_version():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = next(d for d in project["dependencies"] if re.match(r"jax[<>=!~ ]", d))
    (cuda,) = project["optional-dependencies"]["cuda"]
    assert cuda.startswith("jax[cuda12]")
    assert cuda[len("jax[cuda12]") :] == base[len("jax") :]  # the same version bound: no second JAX
    assert "pip install -e '.[cuda]'" in (ROOT / "README.md").read_text()


def test_the_wheel_holds_the_package_alone_and_no_machine_path(tmp_path):
    """The built wheel carries what users run: the package (code, weights, embedded data), no release tool,
    benchmark or test, and no absolute path of the machine that built or trained it."""
    import shutil
    import subprocess
    import sys
    import zipfile

    source = tmp_path / "source"  # a copy, so that the build leaves nothing in the working tree
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    shutil.copytree(ROOT / "dit_jax", source / "dit_jax", ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(tmp_path), "."],
        cwd=source,
        check=True,
        capture_output=True,
        timeout=300,
    )
    (wheel,) = tmp_path.glob("*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = archive.namelist()
        assert {name.split("/")[0] for name in names} == {"dit_jax", "dit_jax-0.1.0.dist-info"}
        assert not [n for n in names if re.search(r"(^|/)(tools|release|benchmarks|tests)/", n)]
        assert "dit_jax/cli/register.py" in names and any(n.startswith("dit_jax/network/weights/") for n in names)
        for name in names:
            if name.endswith((".py", ".json", ".md", "metadata", "METADATA", ".txt")):
                text = archive.read(name).decode("utf-8", "replace")
                found = re.findall(r"(?<![\w.$])/(?:work|root|home|tmp|Users)/[\w./-]+", text)
                assert not found, f"{name}: {found[:3]}"
