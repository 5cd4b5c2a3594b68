"""Rebuilds dit-jax's embedded dataset from Debian's ``sweethome3d-furniture`` package.

    apt-get install sweethome3d-furniture          # or: apt-get download sweethome3d-furniture
    python tools/build_embedded_dataset.py [--furniture-dir DIR | --deb FILE.deb] [--out DIR]

Every furniture model of the package's five catalogues (CC0 and CC-BY 3.0 CAD models) is read from its OBJ
mesh, turned z-up, sampled with 1024 points uniformly over its surface area (seeded by the model's id, so the
result is the same on every machine), centred on the points' mean and scaled into the unit sphere. A ModelNet40
category is given where the model's name says one (its rightmost word or phrase that names a category), else
-1. Writes ``dit_jax/data/embedded/sh3d_furniture_1024.npz`` (coordinates stored as int16 in units of 1/32767)
and ``ATTRIBUTION.md`` beside it, listing every model with its creator and licence.
"""

from __future__ import annotations

import argparse
import hashlib
import pathlib
import re
import subprocess
import sys
import tempfile
import zipfile

import numpy as np

from dit_jax import io

N_POINTS = 1024
QUANT = 32767  # stored coordinates are int16 in units of 1 / QUANT
OUT_DIR = pathlib.Path(__file__).resolve().parents[1] / "dit_jax" / "data" / "embedded"
DEFAULT_DIR = pathlib.Path("/usr/share/sweethome3d/furniture")

LICENCES = {  # from the package's debian/copyright
    "KatorLegaz": ("CC-BY-3.0-US", "Andrew Kator & Jennifer Legaz, 2003-2008"),
    "Reallusion": ("CC-BY-3.0-US", "Reallusion, 2008-2011"),
    "Scopia": ("CC-BY-3.0", "Scopia Visual Interfaces Systems, s.l., 2010-2012"),
    "BlendSwap-CC-BY": ("CC-BY-3.0", "The BlendSwap contributors"),
    "BlendSwap-CC-0": ("CC0", "Emmanuel Puybaret (eTeks) and other contributors, 2014"),
}

MODELNET40 = [
    "airplane",
    "bathtub",
    "bed",
    "bench",
    "bookshelf",
    "bottle",
    "bowl",
    "car",
    "chair",
    "cone",
    "cup",
    "curtain",
    "desk",
    "door",
    "dresser",
    "flower_pot",
    "glass_box",
    "guitar",
    "keyboard",
    "lamp",
    "laptop",
    "mantel",
    "monitor",
    "night_stand",
    "person",
    "piano",
    "plant",
    "radio",
    "range_hood",
    "sink",
    "sofa",
    "stairs",
    "stool",
    "table",
    "tent",
    "toilet",
    "tv_stand",
    "vase",
    "wardrobe",
    "xbox",
]

# Words and phrases of furniture names, to ModelNet40 categories. The rightmost match in a name wins, so
# "Piano bench" is a bench and "Bar chair" a chair; phrases are tried before their last word.
VOCABULARY = {
    "airplane": "airplane",
    "aeroplane": "airplane",
    "plane": "airplane",
    "aircraft": "airplane",
    "bathtub": "bathtub",
    "bath": "bathtub",
    "jacuzzi": "bathtub",
    "bed": "bed",
    "crib": "bed",
    "cot": "bed",
    "bunk": "bed",
    "bench": "bench",
    "bookcase": "bookshelf",
    "bookshelf": "bookshelf",
    "shelves": "bookshelf",
    "shelf": "bookshelf",
    "bottle": "bottle",
    "bowl": "bowl",
    "car": "car",
    "beetle": "car",
    "sedan": "car",
    "convertible": "car",
    "jeep": "car",
    "van": "car",
    "chair": "chair",
    "armchair": "chair",
    "cone": "cone",
    "cup": "cup",
    "mug": "cup",
    "curtain": "curtain",
    "curtains": "curtain",
    "desk": "desk",
    "door": "door",
    "dresser": "dresser",
    "chest of drawers": "dresser",
    "drawers": "dresser",
    "commode": "dresser",
    "flower pot": "flower_pot",
    "flowerpot": "flower_pot",
    "planter": "flower_pot",
    "guitar": "guitar",
    "keyboard": "keyboard",
    "lamp": "lamp",
    "laptop": "laptop",
    "fireplace": "mantel",
    "mantel": "mantel",
    "monitor": "monitor",
    "tv": "monitor",
    "television": "monitor",
    "screen": "monitor",
    "night stand": "night_stand",
    "nightstand": "night_stand",
    "bedside table": "night_stand",
    "male": "person",
    "female": "person",
    "man": "person",
    "woman": "person",
    "boy": "person",
    "girl": "person",
    "child": "person",
    "person": "person",
    "baby": "person",
    "piano": "piano",
    "plant": "plant",
    "tree": "plant",
    "bush": "plant",
    "bamboo": "plant",
    "palm": "plant",
    "cactus": "plant",
    "fern": "plant",
    "radio": "radio",
    "hood": "range_hood",
    "range hood": "range_hood",
    "sink": "sink",
    "washbasin": "sink",
    "basin": "sink",
    "lavatory": "sink",
    "sofa": "sofa",
    "couch": "sofa",
    "settee": "sofa",
    "loveseat": "sofa",
    "stairs": "stairs",
    "staircase": "stairs",
    "stair": "stairs",
    "stool": "stool",
    "table": "table",
    "tent": "tent",
    "toilet": "toilet",
    "wc": "toilet",
    "tv stand": "tv_stand",
    "tv cabinet": "tv_stand",
    "tv unit": "tv_stand",
    "vase": "vase",
    "wardrobe": "wardrobe",
    "closet": "wardrobe",
    "armoire": "wardrobe",
    "xbox": "xbox",
}
# Names whose last word qualifies what comes before ("Toilet paper dispenser" is no toilet).
STOP_WORDS = {"dispenser", "holder", "paper", "plug", "switch", "rack", "lid", "cover", "mat", "brush", "sign"}


def category_of(name: str) -> int:
    words = re.findall(r"[a-z0-9]+", name.lower())
    for end in range(len(words), 0, -1):
        if words[end - 1] in STOP_WORDS:
            return -1
        for length in (3, 2, 1):
            if end - length < 0:
                continue
            phrase = " ".join(words[end - length : end])
            if phrase in VOCABULARY:
                return MODELNET40.index(VOCABULARY[phrase])
    return -1


def read_properties(text: str) -> dict[int, dict[str, str]]:
    entries: dict[int, dict[str, str]] = {}
    for match in re.finditer(r"^(\w+)#(\d+)=(.*)$", text, re.M):
        value = match[3].strip().encode("latin-1", "replace").decode("unicode_escape", "replace")
        entries.setdefault(int(match[2]), {})[match[1]] = value
    return entries


def read_obj(text: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) and fan-triangulated faces (F, 3) of an OBJ file."""
    vertices, faces = [], []
    for line in text.splitlines():
        if line.startswith("v "):
            vertices.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("f "):
            idx = [int(tok.split("/")[0]) for tok in line.split()[1:]]
            faces.extend([idx[0], idx[i], idx[i + 1]] for i in range(1, len(idx) - 1))
    verts = np.asarray(vertices, np.float64).reshape(-1, 3)
    tris = np.asarray(faces, np.int64).reshape(-1, 3)
    tris = np.where(tris < 0, tris + len(verts), tris - 1)  # OBJ indices are 1-based, or negative = relative
    return verts, tris


def normalise(points: np.ndarray) -> np.ndarray:
    points = points - points.mean(axis=0)
    return points / np.max(np.linalg.norm(points, axis=1))


def build(furniture_dir: pathlib.Path, out_dir: pathlib.Path = OUT_DIR) -> None:
    records = []
    for catalogue in sorted(LICENCES):
        path = furniture_dir / f"{catalogue}.sh3f"
        if not path.exists():
            sys.exit(f"error: {path} not found; is sweethome3d-furniture installed or unpacked there?")
        with zipfile.ZipFile(path) as archive:
            entries = read_properties(archive.read("PluginFurnitureCatalog.properties").decode("latin-1"))
            for number in sorted(entries):
                entry = entries[number]
                model_id = f"{catalogue}/{entry['id'].split('#')[-1]}"
                verts, tris = read_obj(archive.read(entry["model"].lstrip("/")).decode("latin-1"))
                if "modelRotation" in entry:  # how Sweet Home 3D turns the model upright
                    verts = verts @ np.asarray(entry["modelRotation"].split(), np.float64).reshape(3, 3).T
                verts = verts[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y up -> z up (a rotation)
                seed = int.from_bytes(hashlib.sha256(model_id.encode()).digest()[:8], "little")
                try:
                    points = io.sample_surface(verts, tris, N_POINTS, seed=seed)
                except ValueError:  # no triangles, or none with an area
                    print(f"skipped {model_id}: no surface", file=sys.stderr)
                    continue
                records.append(
                    dict(
                        id=model_id,
                        name=entry["name"],
                        points=normalise(points),
                        label=category_of(entry["name"]),
                        creator=entry.get("creator", ""),
                        licence=LICENCES[catalogue][0],
                        catalogue=catalogue,
                    )
                )
                if len(records) % 50 == 0:
                    print(f"{len(records)} models", file=sys.stderr)
    points = np.stack([r["points"] for r in records])
    np.savez_compressed(
        out_dir / "sh3d_furniture_1024.npz",
        # Radius 0.9999 before rounding keeps every dequantised point inside the unit sphere.
        points=np.round(points * (0.9999 * QUANT)).astype(np.int16),
        label=np.asarray([r["label"] for r in records], np.int16),
        id=np.asarray([r["id"] for r in records]),
        name=np.asarray([r["name"] for r in records]),
        shape_names=np.asarray(MODELNET40),
    )
    lines = [
        "# Embedded dataset: attribution",
        "",
        f"`sh3d_furniture_1024.npz` holds {len(records)} point clouds of {N_POINTS} points, sampled by",
        "`python tools/build_embedded_dataset.py` from the 3D models of Debian's `sweethome3d-furniture` package",
        "(version 1.8-1; https://www.sweethome3d.com/importModels.jsp). The clouds are derived works of",
        "these models, shared under the same licences:",
        "",
    ]
    for catalogue, (licence, holder) in sorted(LICENCES.items()):
        count = sum(r["catalogue"] == catalogue for r in records)
        lines.append(f"- {catalogue} ({count} models): {licence}, (c) {holder}")
    lines += [
        "",
        "Licences: CC-BY-3.0 https://creativecommons.org/licenses/by/3.0/ ; CC-BY-3.0-US",
        "https://creativecommons.org/licenses/by/3.0/us/ ; CC0 https://creativecommons.org/publicdomain/zero/1.0/",
        "",
        "| id | name | creator | licence | ModelNet40 category |",
        "|---|---|---|---|---|",
    ]
    for r in records:
        label = MODELNET40[r["label"]] if r["label"] >= 0 else "-"
        lines.append(f"| {r['id']} | {r['name']} | {r['creator']} | {r['licence']} | {label} |")
    (out_dir / "ATTRIBUTION.md").write_text("\n".join(lines) + "\n")
    labelled = sum(r["label"] >= 0 for r in records)
    print(f"wrote {len(records)} models ({labelled} with a ModelNet40 category) to {out_dir}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--furniture-dir", type=pathlib.Path, default=DEFAULT_DIR)
    group.add_argument("--deb", type=pathlib.Path, help="the package file from `apt-get download`")
    parser.add_argument("--out", type=pathlib.Path, default=OUT_DIR, help="default: the package's embedded folder")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.deb:
        with tempfile.TemporaryDirectory() as tmp:
            subprocess.run(["dpkg", "-x", str(args.deb), tmp], check=True)
            build(pathlib.Path(tmp) / "usr/share/sweethome3d/furniture", args.out)
    else:
        build(args.furniture_dir, args.out)


if __name__ == "__main__":
    main()
