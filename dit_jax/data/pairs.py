"""Registration pairs made from shapes as the authors make them (docs/network.md, section 12), with random access.

For shape X (its first P points, P = 1000 by default):

1. angles per axis uniform in [-45, 45] degrees, R = Rx(ax) Ry(ay) Rz(az) (scipy ``from_euler('zyx',
   [az, ay, ax])``); t uniform in [-0.5, 0.5]^3;
2. noisy settings: each cloud independently gets N(0, 0.01^2) per coordinate clipped to [-c, c]
   (c = 0.001 low noise, 0.05 high noise), before cropping and before the target moves;
3. partial settings: the source keeps its 800 points nearest to a random point near (1000, 1000, 1000), the
   target its 800 nearest to one near (-1000, -1000, -1000), both in the shape's frame (about 600 shared);
4. the target is moved, ``Y = R Y + t``, and its points are shuffled.

The authors' settings: ``clean``, ``low_noise_partial``, ``high_noise_partial``. In all three the source and
the target are made of the same points, which no pair of real scans is; a model can score 100 % on them by
matching identical points. Settings as real data has them (see :data:`SETTINGS`):

* ``independent_*``: the same three, but source and target are disjoint random halves of the shape's points
  (each cloud takes ``min(n_points, P // 2)`` of the P points the shape holds), so no point is shared;
* ``scan_low_noise`` / ``scan_high_noise``: scan-like partial views, sampled independently: each cloud is what
  a range scanner at a random viewpoint 2 radii from the centre sees (hidden-point removal, Katz et al. 2007,
  on all P points; about 45 % of a ModelNet40 shape), the target's viewpoint 0-60 degrees from the
  source's; points both views see go to one cloud or the other at random; each cloud keeps
  ``min(n_points, round(0.2 P))`` of its visible points at random (where a view has fewer, about one in
  ten, the hidden points nearest its camera fill it up). Noise (low: clip 0.001; high: clip 0.05) is added
  after the view is taken, as a sensor adds it.

``variant="peers"`` follows DCP / PRNet / RPM-Net instead: angles in [0, 45] degrees and RPM-Net's crop (each
cloud keeps the 70 % of its points on the far side of a plane through the centre with a random normal).

Splits: ``unseen=False`` uses the shapes as given (the official train/test split); ``unseen=True`` keeps
labels 0-19 for training and 20-39 for testing, the authors' default.

Determinism: test pair n is drawn from a generator seeded with n, the same on every run and machine; training
pair n of epoch e from one seeded with (seed, e, n), so every epoch brings fresh pairs and a resumed run sees
the same ones.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from dit_jax.data import shapes as shapes_lib
from dit_jax.data import views
from dit_jax.data.shapes import Shapes


class Setting(NamedTuple):
    """How one data setting makes its pairs."""

    noise_clip: float  # per-coordinate clip of N(0, 0.01^2) noise; 0: no noise
    crop: str  # "none", "authors" (nearest points to a far anchor; the peers' plane crop) or "scan"
    independent: bool  # source and target sampled from disjoint points of the shape


SETTINGS: Mapping[str, Setting] = {
    "clean": Setting(0.0, "none", False),
    "low_noise_partial": Setting(0.001, "authors", False),
    "high_noise_partial": Setting(0.05, "authors", False),
    "independent_clean": Setting(0.0, "none", True),
    "independent_low_noise_partial": Setting(0.001, "authors", True),
    "independent_high_noise_partial": Setting(0.05, "authors", True),
    "scan_low_noise": Setting(0.001, "scan", True),
    "scan_high_noise": Setting(0.05, "scan", True),
}


#: The settings of the paper (docs/network.md, section 12).
AUTHORS_SETTINGS = ("clean", "low_noise_partial", "high_noise_partial")


VARIANTS = ("authors", "peers")


NOISE_STD = 0.01


#: Distance under which a source point's true counterpart counts as matched (docs/network.md, section 11).
CORRESPONDENCE_RADIUS = 0.04


SCAN_KEEP = 0.2


@dataclasses.dataclass(frozen=True)
class PairConfig:
    """How pairs are made.

    Attributes:
      setting: one of :data:`SETTINGS`.
      train: training pairs (fresh each epoch) rather than fixed test pairs.
      unseen: split by category: labels 0-19 for training, 20-39 for testing.
      variant: "authors" (docs/network.md, section 12) or "peers" (angles in [0, 45], RPM-Net plane crop
        keeping 70 %).
      n_points: points taken from each shape (its first ones); with independent sampling, the most points
        each cloud takes (see the module docs).
      partial_points: points each cloud keeps in the authors' partial settings (default: 80 % of n_points,
        the authors' 800 of 1000).
      peers_keep: fraction each cloud keeps in the peers' crop.
      max_angle: degrees; angles are uniform in [-max, max] (authors) or [0, max] (peers).
      max_translation: t is uniform in [-max, max]^3.
      seed: seeds the training pairs.
    """

    setting: str = "clean"
    train: bool = False
    unseen: bool = False
    variant: str = "authors"
    n_points: int = 1000
    partial_points: int | None = None
    peers_keep: float = 0.7
    max_angle: float = 45.0
    max_translation: float = 0.5
    seed: int = 0

    def __post_init__(self):
        if self.setting not in SETTINGS:
            raise ValueError(f"unknown setting {self.setting!r}; choose one of {', '.join(SETTINGS)}")
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.partial_points is not None and not 0 < self.partial_points <= self.n_points:
            raise ValueError(f"partial_points ({self.partial_points}) must be in 1..n_points ({self.n_points})")

    @property
    def noise_clip(self) -> float:
        return SETTINGS[self.setting].noise_clip

    @property
    def partial(self) -> bool:
        return SETTINGS[self.setting].crop != "none"

    @property
    def independent(self) -> bool:
        return SETTINGS[self.setting].independent

    def cloud_points(self, shape_points: int) -> int:
        """Points in each cloud of a pair made from shapes of ``shape_points`` points."""
        if not self.independent:
            return self.points_per_cloud
        if SETTINGS[self.setting].crop == "scan":
            return min(self.n_points, int(round(SCAN_KEEP * shape_points)))
        half = min(self.n_points, shape_points // 2)
        if not self.partial:
            return half
        if self.variant == "peers":
            return int(round(self.peers_keep * half))
        return int(round(0.8 * half)) if self.partial_points is None else min(self.partial_points, half)

    @property
    def points_per_cloud(self) -> int:
        """Points in each cloud of the authors' (shared-point) settings."""
        if not self.partial:
            return self.n_points
        if self.variant == "peers":
            return int(round(self.peers_keep * self.n_points))
        return self.partial_points or int(round(0.8 * self.n_points))


def shape_points(source, n_points: int, settings) -> int:
    """Points to load per shape of ``source`` (see :func:`dit_jax.data.shapes.load_shapes`) for pairs of
    ``settings``: ``n_points``, or all the source holds where a setting samples its two clouds from disjoint
    points (they draw from the whole shape)."""
    if any(SETTINGS[s].independent for s in settings):
        return max(n_points, shapes_lib.source_points(source))
    return n_points


def euler_zyx_to_matrix(angles_deg: np.ndarray) -> np.ndarray:
    """R = Rz(az) applied first, then Ry, then Rx: ``Rx(ax) Ry(ay) Rz(az)`` for angles (..., 3) = (az, ay, ax).

    The same matrix as scipy's ``Rotation.from_euler('zyx', [az, ay, ax], degrees=True)``.
    """
    az, ay, ax = np.moveaxis(np.radians(np.asarray(angles_deg, np.float64)), -1, 0)
    cz, sz, cy, sy, cx, sx = np.cos(az), np.sin(az), np.cos(ay), np.sin(ay), np.cos(ax), np.sin(ax)
    one, zero = np.ones_like(az), np.zeros_like(az)
    rz = np.stack([np.stack([cz, -sz, zero], -1), np.stack([sz, cz, zero], -1), np.stack([zero, zero, one], -1)], -2)
    ry = np.stack([np.stack([cy, zero, sy], -1), np.stack([zero, one, zero], -1), np.stack([-sy, zero, cy], -1)], -2)
    rx = np.stack([np.stack([one, zero, zero], -1), np.stack([zero, cx, -sx], -1), np.stack([zero, sx, cx], -1)], -2)
    return rx @ ry @ rz


class PairDataset:
    """Registration pairs over a :class:`Shapes` split, random access by index.

    ``dataset[n]`` is one pair, ``dataset.batch(indices, epoch)`` a stacked batch; both give the same pair for
    the same (n, epoch). A pair is a dict of numpy arrays:

    * ``src`` (N, 3), ``tgt`` (M, 3) float32, ``tgt ~ src @ R.T + t`` on the shared part;
    * ``R`` (3, 3), ``t`` (3,) float32, the ground truth; ``euler_zyx`` (3,) its angles (az, ay, ax) in degrees;
    * ``correspondence`` (N,) int32: the row of ``tgt`` holding each source point's own counterpart, or -1
      where the crop removed it (the discrimination loss's labels);
    * ``tgt_clean`` (P, 3) float32: the whole noise-free shape in the target's frame (for RPM-Net's Chamfer
      distance);
    * ``label`` () int64 and ``index`` () int64: the shape's category and its row in the split.
    """

    def __init__(self, shapes: Shapes, config: PairConfig):
        if config.independent and shapes.points.shape[1] < 8:
            raise ValueError(f"shapes hold {shapes.points.shape[1]} points, too few to sample two clouds from")
        if not config.independent and shapes.points.shape[1] < config.n_points:
            raise ValueError(f"shapes hold {shapes.points.shape[1]} points, fewer than the {config.n_points} asked")
        rows = np.arange(len(shapes.labels))
        if config.unseen:
            # Shapes without a ModelNet40 category (label -1, embedded set only) belong to neither side.
            rows = rows[(shapes.labels >= 0) & (shapes.labels < 20)] if config.train else rows[shapes.labels >= 20]
        self.shapes = shapes
        self.config = config
        self.rows = rows  # pair n uses shape rows[n]

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, n: int) -> dict[str, np.ndarray]:
        return {k: v[0] for k, v in self.batch([n]).items()}

    def _rng(self, n: int, epoch: int, *stream: int) -> np.random.Generator:
        """Pair n's generator; ``stream`` names another one of the same pair (draws that must not move the
        pair's own)."""
        if self.config.train:
            return np.random.default_rng([self.config.seed, epoch, n, *stream])
        return np.random.default_rng([n, *stream] if stream else n)

    def batch(self, indices, epoch: int = 0) -> dict[str, np.ndarray]:
        """Pairs ``indices`` (of this dataset, not shape rows) stacked on a leading axis."""
        c = self.config
        indices = np.asarray(indices, np.int64).reshape(-1)
        if len(indices) and (indices.min() < -len(self) or indices.max() >= len(self)):
            raise IndexError(f"pair index out of range for {len(self)} pairs")
        indices = indices % max(len(self), 1)
        if c.independent:
            return self._independent_batch(indices, epoch)
        b, p = len(indices), c.n_points
        clouds = self.shapes.points[self.rows[indices], :p].astype(np.float64)  # (B, P, 3)

        # Every random draw of pair n comes from pair n's own generator, in a fixed order.
        angles = np.empty((b, 3))
        trans = np.empty((b, 3))
        noise = np.zeros((2, b, p, 3))
        crop_src, crop_tgt = np.empty((b, 3)), np.empty((b, 3))
        perms = np.empty((b, c.points_per_cloud), np.int64)
        for i, n in enumerate(indices):
            rng = self._rng(int(n), epoch)
            low = 0.0 if c.variant == "peers" else -c.max_angle
            angles[i] = rng.uniform(low, c.max_angle, 3)  # (az, ay, ax)
            trans[i] = rng.uniform(-c.max_translation, c.max_translation, 3)
            if c.noise_clip > 0:
                noise[:, i] = np.clip(rng.normal(0.0, NOISE_STD, (2, p, 3)), -c.noise_clip, c.noise_clip)
            if c.variant == "peers":
                crop_src[i], crop_tgt[i] = views.unit_vectors(rng, 2)
            else:
                crop_src[i] = rng.random(3) + 1000.0
                crop_tgt[i] = rng.random(3) - 1000.0
            perms[i] = rng.permutation(c.points_per_cloud)

        src_full = clouds + noise[0]
        tgt_full = clouds + noise[1]
        if c.partial:
            src_keep = self._crop(src_full, crop_src)
            tgt_keep = self._crop(tgt_full, crop_tgt)
        else:
            src_keep = tgt_keep = np.broadcast_to(np.arange(p), (b, p))
        tgt_keep = np.take_along_axis(tgt_keep, perms, axis=1)  # the shuffle of the target
        src = np.take_along_axis(src_full, src_keep[..., None], axis=1)
        tgt = np.take_along_axis(tgt_full, tgt_keep[..., None], axis=1)

        rot = euler_zyx_to_matrix(angles)
        tgt = np.einsum("bij,bnj->bni", rot, tgt) + trans[:, None, :]

        # Where each source point's own counterpart went in the target (-1: cropped away).
        where = np.full((b, p), -1, np.int64)
        np.put_along_axis(where, tgt_keep, np.broadcast_to(np.arange(tgt_keep.shape[1]), tgt_keep.shape), axis=1)
        correspondence = np.take_along_axis(where, src_keep, axis=1)

        shape_in_tgt_frame = np.einsum("bij,bnj->bni", rot, clouds) + trans[:, None, :]
        return {
            "src": src.astype(np.float32),
            "tgt": tgt.astype(np.float32),
            "R": rot.astype(np.float32),
            "t": trans.astype(np.float32),
            "euler_zyx": angles.astype(np.float32),
            "correspondence": correspondence.astype(np.int32),
            "tgt_clean": shape_in_tgt_frame.astype(np.float32),
            "label": self.shapes.labels[self.rows[indices]],
            "index": indices,
        }

    def _independent_batch(self, indices: np.ndarray, epoch: int) -> dict[str, np.ndarray]:
        """:meth:`batch` for the settings whose two clouds share no point (see the module docs)."""
        c = self.config
        shapes = self.shapes.points[self.rows[indices]].astype(np.float64)  # (B, P, 3): all of each shape
        b, p = shapes.shape[:2]
        k = c.cloud_points(p)
        src_idx, tgt_idx = np.empty((b, k), np.int64), np.empty((b, k), np.int64)
        angles, trans = np.empty((b, 3)), np.empty((b, 3))
        noise = np.zeros((2, b, k, 3))
        for i, n in enumerate(indices):
            rng = self._rng(int(n), epoch)
            low = 0.0 if c.variant == "peers" else -c.max_angle
            angles[i] = rng.uniform(low, c.max_angle, 3)
            trans[i] = rng.uniform(-c.max_translation, c.max_translation, 3)
            if SETTINGS[c.setting].crop == "scan":
                src_idx[i], tgt_idx[i] = views.scan_views(shapes[i], k, rng)
            else:
                order = rng.permutation(p)
                halves = order[: p // 2], order[p // 2 : 2 * (p // 2)]
                half = min(c.n_points, p // 2)
                picked = [h[:half] for h in halves]
                if c.partial:
                    picked = [
                        h[self._crop(shapes[i][h][None], anchor[None], k)[0]]
                        for h, anchor in zip(picked, self._crop_anchors(rng))
                    ]
                src_idx[i], tgt_idx[i] = picked[0], rng.permutation(picked[1])
            if c.noise_clip > 0:
                noise[:, i] = np.clip(rng.normal(0.0, NOISE_STD, (2, k, 3)), -c.noise_clip, c.noise_clip)
        src_clean = np.take_along_axis(shapes, src_idx[..., None], axis=1)
        tgt_clean = np.take_along_axis(shapes, tgt_idx[..., None], axis=1)
        # A source point's counterpart: the nearest target point on the noise-free shape, if near enough. A k-d
        # tree per pair: the dense (B, K, K, 3) differences took 2.5 GB and 17 s for 400 pairs of 512 points.
        from scipy.spatial import cKDTree

        gap, nearest = np.empty((b, k)), np.empty((b, k), np.int64)
        for i in range(b):
            gap[i], nearest[i] = cKDTree(tgt_clean[i]).query(src_clean[i])
        near = gap < CORRESPONDENCE_RADIUS
        rot = euler_zyx_to_matrix(angles)
        tgt = np.einsum("bij,bnj->bni", rot, tgt_clean + noise[1]) + trans[:, None, :]
        return {
            "src": (src_clean + noise[0]).astype(np.float32),
            "tgt": tgt.astype(np.float32),
            "R": rot.astype(np.float32),
            "t": trans.astype(np.float32),
            "euler_zyx": angles.astype(np.float32),
            "correspondence": np.where(near, nearest, -1).astype(np.int32),
            "tgt_clean": (np.einsum("bij,bnj->bni", rot, shapes) + trans[:, None, :]).astype(np.float32),
            "label": self.shapes.labels[self.rows[indices]],
            "index": indices,
        }

    def _crop_anchors(self, rng: np.random.Generator) -> np.ndarray:
        """(2, 3): where the source's and the target's crops are anchored (a direction for the peers)."""
        if self.config.variant == "peers":
            return views.unit_vectors(rng, 2)
        return np.stack([rng.random(3) + 1000.0, rng.random(3) - 1000.0])

    def _crop(self, clouds: np.ndarray, anchors: np.ndarray, k: int | None = None) -> np.ndarray:
        """Indices (B, K) of the points each cloud keeps, in their original order."""
        c = self.config
        if c.variant == "peers":
            # RPM-Net: keep the points farthest along a random direction from the centroid's plane.
            centred = clouds - clouds.mean(axis=1, keepdims=True)
            score = -np.einsum("bnj,bj->bn", centred, anchors)
        else:
            score = np.sum((clouds - anchors[:, None, :]) ** 2, axis=-1)
        k = k or c.points_per_cloud
        nearest = np.argpartition(score, k - 1, axis=1)[:, :k]
        return np.sort(nearest, axis=1)
