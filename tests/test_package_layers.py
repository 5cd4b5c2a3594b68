"""The package's folders are layers (docs/implementation.md, "The package map"): a module imports its own
subpackage and the layers below it, never a layer above or a sibling of its own layer."""

from __future__ import annotations

import ast
import pathlib

import dit_jax

ROOT = pathlib.Path(dit_jax.__file__).parent

#: Bottom to top; a subpackage may import only from the rows above it in this list (and from itself).
LAYERS = (
    ("geometry", "io"),
    ("network", "features", "pictures", "data"),
    ("pipeline",),
    ("scenes",),
    ("evaluators", "cli"),
    ("training",),
)
LAYER = {name: depth for depth, names in enumerate(LAYERS) for name in names}


def _imports(path: pathlib.Path) -> set[str]:
    """The dit_jax subpackages a module imports, at its top or inside its functions."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] if node.module != "dit_jax" else [f"dit_jax.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        found |= {name.split(".")[1] for name in names if name.startswith("dit_jax.")}
    return found


def test_every_subpackage_has_a_layer_and_says_what_it_holds():
    subpackages = {p.parent.name for p in ROOT.glob("*/__init__.py")}
    assert subpackages == set(LAYER), "a new subpackage needs a layer here and in docs/implementation.md"
    for name in subpackages:
        doc = ast.get_docstring(ast.parse((ROOT / name / "__init__.py").read_text()))
        assert doc and len(doc.split()) > 15, f"dit_jax/{name}/__init__.py: say what lives there"


def test_no_import_runs_up_the_layers_or_across_one():
    wrong = []
    for path in sorted(ROOT.rglob("*.py")):
        home = path.relative_to(ROOT).parts[0]
        if home not in LAYER:
            continue  # dit_jax/__init__.py: the public names, imported on first use
        for other in _imports(path) - {home}:
            if other not in LAYER or LAYER[other] >= LAYER[home]:
                wrong.append(f"{path.relative_to(ROOT.parent)} imports dit_jax.{other}")
    assert not wrong, "\n".join(wrong)


def test_the_package_top_holds_its_subpackages_and_nothing_else():
    entries = {p.name for p in ROOT.iterdir() if p.name != "__pycache__"}
    assert entries == {"__init__.py", *LAYER}, sorted(entries)
    assert len(entries) <= 12
