"""What each keypoint of a cloud's voxel grid looks like: the descriptors that local features match.

FPFH (Rusu et al., "Fast Point Feature Histograms (FPFH) for 3D Registration", ICRA 2009) describes a point by
three histograms of angles between its neighbours' normals, in 33 bins (11 a histogram). Matched as they
are, a few crowded bins decide the distance; square-rooted (the Hellinger distance between histograms) every
bin counts. One radius sees either detail or context; :func:`histograms` joins FPFH at several radii, each
block scaled to unit length so each radius weighs the same. The wide radii are computed on a coarser grid and
handed to each keypoint from its nearest coarse point: FPFH's cost grows with the neighbours inside its radius,
and a wide radius on the fine grid would cost several times the rest together (docs/features.md).

Every length is in voxels of the caller's grid, so the descriptors do not depend on the clouds' units.
"""

from __future__ import annotations

import os
from typing import NamedTuple

import numpy as np

#: What :func:`describe` computes: "fpfh" (FPFH at one radius, :data:`FPFH_RADIUS` voxels, as Open3D's recipes
#: match it; the pipeline's default), "histograms" (:func:`histograms`) or "learned" (the shipped network of
#: :mod:`dit_jax.features.network` over the histograms; a directory of a user's own weights is taken in its
#: place, :func:`is_descriptor`). Both of the last match more keypoints of rooms right than FPFH and need normals
#: that face a viewpoint; the histograms register no more rooms, the learned descriptor registers more, but the
#: verdict's bounds are FPFH's (docs/features.md).
DESCRIPTORS = ("fpfh", "histograms", "learned")
#: The radius of single-scale FPFH and its most neighbours, in voxels (Open3D's room recipe: 5 voxels, 100).
FPFH_RADIUS = 5.0
FPFH_NEIGHBOURS = 100


class Block(NamedTuple):
    """One radius of :func:`histograms`: FPFH within ``radius`` voxels on a grid of ``grid`` voxels, from at most
    ``neighbours`` neighbours."""

    radius: float
    grid: float
    neighbours: int


#: The joined histograms' radii: 2.5 and 5 voxels on the keypoints' own grid, 8 and 12 on a grid twice as
#: coarse (of the two radius sets run through the pipeline on every 3DMatch pair, the one that registered more;
#: docs/features.md).
BLOCKS = (Block(2.5, 1.0, 50), Block(5.0, 1.0, 100), Block(8.0, 2.0, 100), Block(12.0, 2.0, 200))


def _o3d():
    try:
        import open3d
    except ImportError as error:  # the wheel loads libusb, which slim Debian images lack
        raise ImportError(
            f"registration by local features needs Open3D ({error}); on Debian: apt-get install libusb-1.0-0"
        ) from None
    return open3d


def fpfh(cloud, radius: float, neighbours: int) -> np.ndarray:
    """FPFH of each point of ``cloud`` (an Open3D point cloud with normals) from at most ``neighbours`` of its
    neighbours within ``radius`` (the cloud's units): (N, 33) float32, each of the three histograms summing to
    200 as Open3D scales them (0 for a point with no neighbour)."""
    o3d = _o3d()
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=neighbours)
    found = o3d.pipelines.registration.compute_fpfh_feature(cloud, search)
    return np.ascontiguousarray(np.asarray(found.data, np.float32).T)


def _unit_rows(rows: np.ndarray) -> np.ndarray:
    """(N, D) rows scaled to unit length; a row of zeros stays zero."""
    return rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)


def _coarse(cloud, grid: float, viewpoint):
    """``cloud``'s points thinned on a grid of ``grid`` (its units), with normals estimated from them as the
    keypoints' are from theirs (not averaged from the keypoints': where those point either way, as they do
    without a viewpoint, an average is noise)."""
    o3d = _o3d()
    points = np.asarray(cloud.voxel_down_sample(grid).points)
    coarse = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    coarse.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * grid, max_nn=30))
    if viewpoint is not None:
        coarse.orient_normals_towards_camera_location(np.asarray(viewpoint, np.float64))
    return coarse


def histograms(cloud, voxel: float, viewpoint=None, blocks: tuple[Block, ...] = BLOCKS) -> np.ndarray:
    """Square-rooted FPFH at each of ``blocks``' radii, each block of unit length, joined: (N, 33 * len(blocks))
    float32 for the N points of ``cloud`` (an Open3D point cloud with normals: the keypoints, on a grid of
    ``voxel``). A block on a coarser grid is computed there (normals facing ``viewpoint``, as the keypoints'
    do; None: as estimated) and each keypoint takes its nearest coarse point's."""
    from scipy.spatial import cKDTree

    points = np.asarray(cloud.points)
    coarse = {}
    joined = []
    for block in blocks:
        if block.grid == 1.0:
            values = fpfh(cloud, block.radius * voxel, block.neighbours)
        else:
            if block.grid not in coarse:
                grid = _coarse(cloud, block.grid * voxel, viewpoint)
                coarse[block.grid] = (grid, cKDTree(np.asarray(grid.points)).query(points)[1])
            grid, nearest = coarse[block.grid]
            values = fpfh(grid, block.radius * voxel, block.neighbours)[nearest]
        joined.append(_unit_rows(np.sqrt(values)))
    return np.ascontiguousarray(np.concatenate(joined, axis=1), np.float32)


def describe(cloud, voxel: float, descriptor: str = "fpfh", viewpoint=None) -> np.ndarray:
    """The ``descriptor`` (one of :data:`DESCRIPTORS`) of each point of ``cloud`` (an Open3D point cloud with
    normals facing ``viewpoint``, or as estimated where None; on a grid of ``voxel``): (N, D) float32."""
    if descriptor == "histograms":
        return histograms(cloud, voxel, viewpoint)
    if descriptor == "fpfh":
        return fpfh(cloud, FPFH_RADIUS * voxel, FPFH_NEIGHBOURS)
    if is_descriptor(descriptor):
        from dit_jax.features import network  # JAX and Flax: only for the learned descriptor

        weights = network.from_path(None if descriptor == "learned" else descriptor)
        return network.embed(weights, histograms(cloud, voxel, viewpoint))
    raise ValueError(f"descriptor must be one of {DESCRIPTORS} or a learned descriptor's directory, got {descriptor!r}")


def is_descriptor(descriptor: str) -> bool:
    """Whether ``descriptor`` names one: one of :data:`DESCRIPTORS`, or a directory of learned descriptor
    weights (``python train.py --config configs/features.py`` writes one as ``WORKDIR/descriptor``)."""
    if descriptor in DESCRIPTORS:
        return True
    return os.path.isfile(os.path.join(os.fspath(descriptor), "config", "metadata"))
