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
