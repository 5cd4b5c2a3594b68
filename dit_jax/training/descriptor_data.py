"""The learned descriptor's data: keypoints of real room scans with the benchmark's truth, and the batches of
matching keypoints it trains on.

A folder of 3DMatch scenes (each with ``3DMatch/`` and ``3DLoMatch/`` lists of fragment pairs and their true
motions, :func:`dit_jax.data.scans.load_pair_sets`) gives, per scene, every fragment's keypoints on the grid
local features use (:func:`dit_jax.features.keypoints.prepare_scans`: the scene's voxel, normals facing the
sensor), their joined histograms (the network's input) and FPFH (measured beside it). A keypoint of a pair's
source and one of its target match where the true motion brings them within ``positive_voxels`` voxels.
"""

from __future__ import annotations

import pathlib
from typing import NamedTuple

import numpy as np


class Fragment(NamedTuple):
    """One scan's keypoints: ``points`` (N, 3), ``histograms`` (N, 132) and ``fpfh`` (N, 33), float32."""

    points: np.ndarray
    histograms: np.ndarray
    fpfh: np.ndarray


class KeypointPair(NamedTuple):
    """A benchmark pair of fragments of one scene: ``source``/``target`` index the scene's fragments;
    ``listed`` is its list ("3DMatch" or "3DLoMatch"); the truth is ``target ~ source @ rotation.T +
    translation``; ``matched`` (M, 2) int: the source and target keypoints that match (M may be 0)."""

    listed: str
    source: int
    target: int
    rotation: np.ndarray
    translation: np.ndarray
    matched: np.ndarray


class Scene(NamedTuple):
    """A scene's fragments and pairs, with the voxel of its keypoints (its units)."""

    name: str
    voxel: float
    fragments: tuple[Fragment, ...]
    pairs: tuple[KeypointPair, ...]


class Batch(NamedTuple):
    """One training step's keypoints, P pairs of A matching keypoints each.

    Attributes:
      source: (P, A, H) histograms of the source keypoints.
      target: (P, A + G, H) histograms of their matching target keypoints (the first A, in order), then G
        more keypoints of the same target drawn at random (negatives).
      near: (P, A, A + G) bool: target keypoints within ``false_negative_voxels`` of a source keypoint's true
        place other than its own match; the loss does not count them as wrong.
    """

    source: np.ndarray
    target: np.ndarray
    near: np.ndarray


def scene_names(folder: str | pathlib.Path) -> list[str]:
    """The scenes of a folder of 3DMatch scenes: its subfolders that hold a ``3DMatch`` list, sorted."""
    folder = pathlib.Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such folder of 3DMatch scenes")
    return sorted(p.name for p in folder.iterdir() if (p / "3DMatch").is_dir())


def load_scene(folder: pathlib.Path, positive_voxels: float, max_fragments: int = 0) -> Scene:
    """Keypoints of every fragment of the scene in ``folder`` and its benchmark pairs (only pairs between its
    first ``max_fragments`` fragments, by name, where that is above 0)."""
    from dit_jax.data import scans as scans_lib
    from dit_jax.features import descriptors, keypoints, network

    sets = scans_lib.load_pair_sets(folder)
    clouds, listed = {}, []
    for set_name, found in sets.items():
        for pair in found.pairs:
            source, target = pair.name.split("/")[-1].split("->")
            clouds[source], clouds[target] = pair.source, pair.target
            listed.append((set_name.split("/")[-1], source, target, pair.rotation, pair.translation))
    names = sorted(clouds)[: max_fragments or None]
    prepared = keypoints.prepare_scans([clouds[n] for n in names], descriptor="fpfh")
    fragments = []
    for scan in prepared.scans:
        if scan is None:  # too few voxels to describe: no keypoints
            fragments.append(Fragment(*(np.zeros((0, width), np.float32) for width in (3, network.HISTOGRAM_SIZE, 33))))
            continue
        thinned = scan.cloud.thinned
        fragments.append(
            Fragment(
                np.asarray(thinned.points, np.float32),
                descriptors.histograms(thinned, prepared.voxel, keypoints.VIEWPOINT),
                scan.cloud.features,
            )
        )
    index = {n: k for k, n in enumerate(names)}
    pairs = []
    for set_name, source, target, rotation, translation in listed:
        if source in index and target in index:
            s, t = index[source], index[target]
            matched = matching_keypoints(
                fragments[s], fragments[t], rotation, translation, positive_voxels * prepared.voxel
            )
            pairs.append(KeypointPair(set_name, s, t, rotation, translation, matched))
    return Scene(folder.name, prepared.voxel, tuple(fragments), tuple(pairs))


def matching_keypoints(source: Fragment, target: Fragment, rotation, translation, within: float) -> np.ndarray:
    """(M, 2) int: each source keypoint that the motion brings within ``within`` of a target keypoint, with
    the nearest such target keypoint."""
    from scipy.spatial import cKDTree

    if len(source.points) == 0 or len(target.points) == 0:
        return np.zeros((0, 2), np.int64)
    moved = source.points @ np.asarray(rotation, np.float32).T + np.asarray(translation, np.float32)
    distance, nearest = cKDTree(target.points).query(moved, distance_upper_bound=within)
    rows = np.nonzero(np.isfinite(distance))[0]
    return np.stack([rows, nearest[rows]], axis=1)


def draw_batch(
    scenes: list[Scene], rng: np.random.Generator, pairs: int, anchors: int, negatives: int, near_voxels: float
) -> Batch:
    """A :class:`Batch` of ``pairs`` pairs drawn at random among the scenes' pairs with at least ``anchors``
    matching keypoints (weighted by nothing: a low-overlap pair counts as much as a high one)."""
    usable = [(scene, pair) for scene in scenes for pair in scene.pairs if len(pair.matched) >= anchors]
    if len(usable) < pairs:
        raise ValueError(f"{len(usable)} pairs have {anchors} matching keypoints; {pairs} needed per step")
    sources, targets, nears = [], [], []
    for k in rng.choice(len(usable), pairs, replace=False):
        scene, pair = usable[k]
        source, target = scene.fragments[pair.source], scene.fragments[pair.target]
        chosen = pair.matched[rng.choice(len(pair.matched), anchors, replace=False)]
        drawn = np.concatenate([chosen[:, 1], rng.choice(len(target.points), negatives)])
        sources.append(source.histograms[chosen[:, 0]])
        targets.append(target.histograms[drawn])
        true_place = source.points[chosen[:, 0]] @ pair.rotation.T.astype(np.float32) + pair.translation.astype(
            np.float32
        )
        near = np.linalg.norm(true_place[:, None] - target.points[drawn][None], axis=-1) < near_voxels * scene.voxel
        near[np.arange(anchors), np.arange(anchors)] = False
        nears.append(near)
    return Batch(np.stack(sources), np.stack(targets), np.stack(nears))
