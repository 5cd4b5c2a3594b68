"""A series of scans into one frame: each scan registered onto the one before, the motions chained, and, where
the series closes on itself (a turntable, a walk around an object), the loop's gap spread over its links.

    from dit_jax import io, registration, series
    scans = [io.read(p) for p in paths]                     # in the order they were taken
    result = series.register_series(registration.load(), scans, loop=True)
    result.poses          # (K, 4, 4): scan k's points into scan 0's frame
    result.merged(scans)  # one cloud

Pairwise registration errors add up along a chain; a closed loop measures their sum (``loop_gap_deg``: the
rotation of the chained motions around the loop, which would be the identity without error) and
:func:`close_loop` takes it back out, a share per link, then fits all the links at once (least squares, the
misfit measured at the scans' centroids).
A link the verdict does not confirm is reported (``suspect_links``), not dropped: the chain needs every link.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np

from dit_jax.geometry import rigid


@dataclasses.dataclass(frozen=True)
class SeriesResult:
    """Scans of a series in one frame.

    Attributes:
      poses: (K, 4, 4) float64: scan k's points into scan 0's frame (``x0 = R_k x_k + t_k``; poses[0] = I),
        after loop closure where the series was registered as a loop.
      links: the registrations, one :class:`dit_jax.pipeline.result.Result` per link: scan k + 1 onto scan k for
        k = 0..K-2, then (loop) scan 0 onto scan K-1.
      loop_gap_deg: the rotation (degrees) left after going once around the loop on the links' motions; 0
        for a perfect loop, NaN without one. Each link's share of the correction is this over the link count.
      loop_gap: the translation left after going once around the loop, its rotation taken out, in the
        input's units; NaN without a loop.
    """

    poses: np.ndarray
    links: tuple
    loop_gap_deg: float = float("nan")
    loop_gap: float = float("nan")

    @property
    def pairs(self) -> list[tuple[int, int]]:
        """(source, target) indices of each link, in the order of ``links`` (see :func:`link_pairs`)."""
        return link_pairs(len(self.poses), loop=len(self.links) == len(self.poses))

    @property
    def suspect_links(self) -> list[int]:
        """Indices (into ``links``) of the links the verdict does not trust (unconfirmed or probably wrong)."""
        return [k for k, link in enumerate(self.links) if not link.verdict]

    @property
    def wrong_links(self) -> list[int]:
        """Indices (into ``links``) of the links the verdict finds probably wrong."""
        return [k for k, link in enumerate(self.links) if link.level == "probably wrong"]

    def apply(self, clouds: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Each (N_k, 3) cloud moved into scan 0's frame."""
        if len(clouds) != len(self.poses):
            raise ValueError(f"{len(clouds)} clouds for a series of {len(self.poses)}")
        return [np.asarray(c, np.float64) @ pose[:3, :3].T + pose[:3, 3] for c, pose in zip(clouds, self.poses)]

    def merged(self, clouds: Sequence[np.ndarray]) -> np.ndarray:
        """(sum N_k, 3): every cloud moved into scan 0's frame, in order."""
        return np.concatenate(self.apply(clouds))

    def plot(
        self, path, clouds: Sequence[np.ndarray], names: Sequence[str] | None = None, title: str | None = None
    ) -> str:
        """Writes a PNG of the clouds moved into scan 0's frame, each in its own colour, from two sides,
        beside each link's agreement and verdict (:func:`dit_jax.pictures.plotting.plot_series`); returns the path."""
        from dit_jax.pictures import plotting

        names = [f"{k}: {name}" for k, name in enumerate(names)] if names is not None else None
        links = [
            (f"{a} onto {b}", link.agreement, link.threshold, bool(link.verdict))
            for (a, b), link in zip(self.pairs, self.links)
        ]
        if not np.isnan(self.loop_gap_deg):
            line = f"{len(self.poses)} scans, loop closed (gap {self.loop_gap_deg:.2f} deg before closing)"
        else:
            line = f"{len(self.poses)} scans, chained"
        return plotting.plot_series(
            path, self.apply(clouds), names=names, links=links, title=f"{title}\n{line}" if title else line
        )


def link_pairs(n_clouds: int, loop: bool) -> list[tuple[int, int]]:
    """(source, target) of each link of a series of ``n_clouds``: cloud k + 1 onto cloud k, then (``loop``)
    cloud 0 onto the last."""
    return [(k + 1, k) for k in range(n_clouds - 1)] + ([(0, n_clouds - 1)] if loop else [])


def chain(motions: np.ndarray) -> np.ndarray:
    """Poses from consecutive motions: (K-1, 4, 4) motions, motion k moving scan k + 1 onto scan k, give
    (K, 4, 4) poses of every scan in scan 0's frame (pose 0 = I, pose k+1 = pose k @ motion k)."""
    motions = np.asarray(motions, np.float64)
    poses = [np.eye(4)]
    for motion in motions:
        poses.append(poses[-1] @ motion)
    return np.stack(poses)


def close_loop(
    motions: np.ndarray, centres: np.ndarray | None = None, scale: float = 1.0
) -> tuple[np.ndarray, float, float]:
    """Poses of a closed series: K motions around the loop (motion k moves scan k + 1 onto scan k, the last
    scan 0 onto scan K-1), whose product would be the identity without error.

    The chained poses miss the start by the loop's gap. Rotations: pose k is turned back by k / K of the gap's
    rotation (its axis-angle vector), so every link takes the same share. Translations: given those rotations,
    each link's translation constrains two poses linearly; over one cycle with equal weights the least-squares
    solution subtracts k / K of the summed translation residual from pose k.

    With ``centres`` the poses then go on to the least-squares fit of all links at once, each link's misfit
    measured where the scans are rather than at their frames' origins (a scanner's origin lies far from what
    it scans, so a small turn there is a large shift on the object): its rotation's angle times ``scale`` and
    how far it moves the centre of the scan it moves (:func:`link_misfit`). On real scan series that brings
    the points closer to the truth (docs/benchmarks.md).

    Args:
      motions: (K, 4, 4).
      centres: (K, 3) where scan k lies in its own frame (its centroid), or None for the closed form alone.
      scale: the length that weighs rotation against translation (the scans' RMS radius).

    Returns:
      poses: (K, 4, 4), pose 0 the identity.
      gap_deg: the loop's rotation gap in degrees before closure.
      gap: its translation gap (the norm of the summed residual, rotation taken out), in the motions' units.
    """
    from scipy.spatial.transform import Rotation

    motions = np.asarray(motions, np.float64)
    k_links = len(motions)
    around = chain(motions)  # K + 1 poses; the last is scan 0 again, off by the gap
    gap_rotation = around[-1, :3, :3]
    gap_deg = rigid.rotation_angle_deg(gap_rotation)
    turn_back = Rotation.from_matrix(gap_rotation).as_rotvec()
    poses = np.tile(np.eye(4), (k_links, 1, 1))
    for k in range(k_links):
        share = Rotation.from_rotvec(-turn_back * k / k_links).as_matrix()
        poses[k, :3, :3] = share @ around[k, :3, :3]
    # Link k says t_{k+1} = t_k + R_k tau_k (with t_K = t_0 = 0): the steps below, re-turned, sum to the gap.
    steps = np.stack([poses[k, :3, :3] @ motions[k, :3, 3] for k in range(k_links)])
    residual = steps.sum(axis=0)
    for k in range(1, k_links):
        poses[k, :3, 3] = steps[:k].sum(axis=0) - residual * k / k_links
    if centres is not None:
        poses = _fit_links(motions, poses, np.asarray(centres, np.float64), float(scale))
    return poses, gap_deg, float(np.linalg.norm(residual))


def link_misfit(poses: np.ndarray, motions: np.ndarray, centres: np.ndarray, scale: float) -> np.ndarray:
    """How far (K, 4, 4) poses are from agreeing with the loop's K links: (K, 6), per link k (pose k @ motion k
    should be pose k+1) the angle-axis vector of the disagreement times ``scale``, then how far it moves the
    centre of scan k+1 (``centres``: (K, 3), each scan's centroid in its own frame)."""
    from scipy.spatial.transform import Rotation

    k_links = len(motions)
    following = (np.arange(k_links) + 1) % k_links
    errors = np.linalg.inv(motions) @ np.linalg.inv(poses) @ poses[following]
    turn = Rotation.from_matrix(errors[:, :3, :3]).as_rotvec() * scale
    moved = centres[following]
    shift = np.einsum("kij,kj->ki", errors[:, :3, :3], moved) + errors[:, :3, 3] - moved
    return np.concatenate([turn, shift], axis=1)


def _fit_links(motions: np.ndarray, poses: np.ndarray, centres: np.ndarray, scale: float) -> np.ndarray:
    """Poses 1..K-1 (pose 0 fixed) that minimise :func:`link_misfit`'s sum of squares, from ``poses``."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    def unpack(x):
        out = np.tile(np.eye(4), (len(motions), 1, 1))
        out[1:, :3, :3] = Rotation.from_rotvec(x.reshape(-1, 6)[:, :3]).as_matrix()
        out[1:, :3, 3] = x.reshape(-1, 6)[:, 3:]
        return out

    start = np.concatenate([Rotation.from_matrix(poses[1:, :3, :3]).as_rotvec(), poses[1:, :3, 3]], axis=1)
    fit = least_squares(lambda x: link_misfit(unpack(x), motions, centres, scale).ravel(), start.ravel(), method="lm")
    return unpack(fit.x)


def register_series(
    registrar,
    clouds: Sequence[np.ndarray],
    *,
    loop: bool = False,
    refine: str | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SeriesResult:
    """Registers each cloud onto the one before it and puts them all in the first one's frame.

    Args:
      registrar: a :class:`dit_jax.pipeline.registration.Registrar` (``registration.load()``).
      clouds: K >= 2 (N_k, 3) clouds in the order they were taken, so that neighbours overlap.
      loop: the last also overlaps the first (a turntable's full turn): register it onto the last as well
        and close the loop (:func:`close_loop`). Needs K >= 3.
      refine: passed to ``registrar.register`` (None: its settings' own).
      progress: called as ``progress(done, total)`` after each link.

    Returns :class:`SeriesResult`.
    """
    if len(clouds) < 2 or (loop and len(clouds) < 3):
        raise ValueError(
            f"a series needs at least {3 if loop else 2} clouds{' for a loop' if loop else ''}, got {len(clouds)}"
        )
    pairs = link_pairs(len(clouds), loop)
    links = []
    for done, (source, target) in enumerate(pairs, 1):
        links.append(registrar.register(clouds[source], clouds[target], refine=refine))
        if progress is not None:
            progress(done, len(pairs))
    motions = np.stack([link.matrix for link in links])
    if loop:
        centres = np.stack([np.asarray(c, np.float64).mean(axis=0) for c in clouds])
        scale = float(
            np.mean(
                [
                    np.sqrt(np.mean(np.sum((np.asarray(c, np.float64) - centre) ** 2, axis=1)))
                    for c, centre in zip(clouds, centres)
                ]
            )
        )
        poses, gap_deg, gap = close_loop(motions, centres, scale)
        return SeriesResult(poses, tuple(links), gap_deg, gap)
    return SeriesResult(chain(motions), tuple(links))
