"""A real scan series into one frame: every scan of a Stanford .conf series registered onto the one before,
chained, and the loop closed (`dit_jax.scenes.series`), against the poses the .conf records.

    python benchmarks/register_series.py --scans ../shared/data/stanford_dragon_stand [--refine icp] [--plot F.png]

Prints a markdown table, per scan: its rotation error in the first scan's frame and how far its points land
from where the true pose puts them, chained and with the loop closed, and the link that reaches it, then one
JSON record of the medians.
"""

from __future__ import annotations

import argparse
import datetime
import json
import time

import numpy as np

from dit_jax.data import scans as scan_data
from dit_jax.geometry import rigid
from dit_jax.pipeline import registration
from dit_jax.scenes import series


def pose_errors(poses: np.ndarray, truth: np.ndarray, clouds) -> tuple[np.ndarray, np.ndarray]:
    """Rotation errors (degrees) of (K, 4, 4) poses against the truth, and how far each scan's points land
    from where the true pose puts them (mean distance): the merged cloud's error, which a pose's translation
    alone (at the scanner's origin, far from the object) does not measure."""
    rotation = np.array([rigid.rotation_angle_deg(p[:3, :3].T @ q[:3, :3]) for p, q in zip(poses, truth)])
    offsets = [
        np.linalg.norm(c @ (p[:3, :3] - q[:3, :3]).T + (p[:3, 3] - q[:3, 3]), axis=1).mean()
        for p, q, c in zip(poses, truth, clouds)
    ]
    return rotation, np.array(offsets)


def simulate(scans, trials: int, seed: int = 0) -> None:
    """The loop closed with and without the joint fit, on the series' true links each given a registration's
    kind of error (a turn of 0.4 degrees per axis, Gaussian, about the moved scan's centroid, and a shift of
    0.5 mm per axis): how far the points land from the truth, mean over scans, per trial."""
    from scipy.spatial.transform import Rotation

    truth = np.stack([np.linalg.inv(scans[0].pose) @ s.pose for s in scans])
    clouds = [s.points[::10] for s in scans]
    centres = np.stack([c.mean(axis=0) for c in clouds])
    scale = float(np.mean([np.sqrt(np.mean(np.sum((c - m) ** 2, axis=1))) for c, m in zip(clouds, centres)]))
    links = np.stack([np.linalg.inv(truth[k]) @ truth[(k + 1) % len(scans)] for k in range(len(scans))])
    rng = np.random.default_rng(seed)
    off = {"chained": [], "closed form": [], "closed and fitted": []}
    for _ in range(trials):
        noisy = links.copy()
        for k in range(len(scans)):
            centre = centres[(k + 1) % len(scans)]
            error = np.eye(4)
            error[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * np.radians(0.4)).as_matrix()
            error[:3, 3] = centre - error[:3, :3] @ centre + rng.normal(size=3) * 0.0005
            noisy[k] = noisy[k] @ error
        for name, poses in (
            ("chained", series.chain(noisy[:-1])),
            ("closed form", series.close_loop(noisy)[0]),
            ("closed and fitted", series.close_loop(noisy, centres, scale)[0]),
        ):
            off[name].append(pose_errors(poses, truth, clouds)[1].mean())
    for name, values in off.items():
        print(f"{name}: points off {1000 * np.mean(values):.3f} mm on average over {trials} trials")
    better = np.mean(np.array(off["closed and fitted"]) < np.array(off["closed form"]))
    print(f"the fit lands closer than the closed form in {100 * better:.0f} % of the trials")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scans", required=True, help="a directory of scans with a Stanford .conf")
    parser.add_argument("--refine", choices=("icp", "none"), default="icp")
    parser.add_argument("--plot", default=None, help="also plot each scan's errors, chained and closed, here (PNG)")
    parser.add_argument(
        "--simulate",
        type=int,
        default=0,
        metavar="TRIALS",
        help="instead: close loops of the true links given simulated errors, with and without the fit",
    )
    args = parser.parse_args()

    scans = scan_data.load_scans(args.scans)
    if args.simulate:
        return simulate(scans, args.simulate)
    truth = np.stack([np.linalg.inv(scans[0].pose) @ s.pose for s in scans])
    clouds = [s.points for s in scans]
    start = time.perf_counter()
    result = series.register_series(
        registration.load(),
        clouds,
        loop=True,
        refine=args.refine,
        progress=lambda done, total: print(f"link {done} of {total}", flush=True),
    )
    seconds = time.perf_counter() - start
    chained = series.chain(np.stack([link.matrix for link in result.links[:-1]]))
    extent = float(np.linalg.norm(np.ptp(clouds[0], axis=0)))
    rot_chain, shift_chain = pose_errors(chained, truth, clouds)
    rot_loop, shift_loop = pose_errors(result.poses, truth, clouds)

    print(
        f"\n{len(scans)} scans, {len(result.links)} links, {seconds:.0f} s; loop gap {result.loop_gap_deg:.3f} deg "
        f"and {result.loop_gap:.5f} ({result.loop_gap / extent:.4f} of the first scan's diagonal)\n"
    )
    link_truth = [np.linalg.inv(truth[target]) @ truth[source] for source, target in result.pairs]
    link_errors = [rigid.rotation_angle_deg(link.rotation.T @ t[:3, :3]) for link, t in zip(result.links, link_truth)]
    print(
        "| scan | link into it: verdict / its own error (deg) | chained: deg / points off | loop closed: deg / "
        "points off |\n|---|---|---|---|"
    )
    for k, scan in enumerate(scans):
        link = f"link from {scans[-1].name}: " if k == 0 else ""
        k_link = (k - 1) % len(scans)
        verdict = result.links[k_link].level
        print(
            f"| {scan.name} | {link}{verdict} / {link_errors[k_link]:.2f} | {rot_chain[k]:.2f} / "
            f"{shift_chain[k]:.5f} | {rot_loop[k]:.2f} / {shift_loop[k]:.5f} |"
        )
    for name, rot, shift in (("chained", rot_chain, shift_chain), ("loop closed", rot_loop, shift_loop)):
        print(
            f"{name}: rotation error median {np.median(rot):.2f}, max {rot.max():.2f} deg; points off by "
            f"median {np.median(shift):.5f}, max {shift.max():.5f} (diagonal {extent:.4f})"
        )
    print(f"suspect links: {result.suspect_links}")
    print(
        json.dumps(
            {
                "benchmark": "register_series",
                "date": datetime.date.today().isoformat(),
                "scans": args.scans,
                "refine": args.refine,
                "seconds": round(seconds, 1),
                "chained": {
                    "rotation_median_deg": float(np.median(rot_chain)),
                    "points_off_median": float(np.median(shift_chain)),
                },
                "loop_closed": {
                    "rotation_median_deg": float(np.median(rot_loop)),
                    "points_off_median": float(np.median(shift_loop)),
                },
                "loop_gap_deg": float(result.loop_gap_deg),
                "suspect_links": list(result.suspect_links),
            }
        )
    )

    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
        for ax, (what, chain_err, loop_err) in zip(
            axes,
            (("rotation error (deg)", rot_chain, rot_loop), ("points off (mean distance)", shift_chain, shift_loop)),
        ):
            ax.plot(chain_err, "o-", label="chained")
            ax.plot(loop_err, "s-", label=f"loop closed (gap {result.loop_gap_deg:.2f} deg)")
            for k in result.suspect_links:  # link k reaches scan k + 1 (the loop's own link, scan 0 again)
                ax.axvline((k + 1) % len(scans), color="0.8", zorder=0)
            ax.set_xlabel("scan (grey: reached by a suspect link)")
            ax.set_ylabel(what)
            ax.grid(alpha=0.3)
        axes[0].legend()
        fig.suptitle(
            f"{len(scans)} scans of {args.scans.rstrip('/').split('/')[-1]} in the first one's frame, "
            f"against the .conf's poses"
        )
        fig.savefig(args.plot, dpi=110, bbox_inches="tight")
        print(f"wrote {args.plot}")


if __name__ == "__main__":
    main()
