"""Would other evidence make DIT+ICP's verdict better than the agreement of its two directions alone?

On validation pairs of training shapes (never test pairs), per pair: the rotation error of the motion
``register(refine="icp")`` returns (best direction), the agreement between the two refined directions, how far
apart the two place the source points (in point spacings), the kept motion's fitness (share of source points
within two spacings of the target) and its trimmed fit (:func:`dit_jax.icp.trimmed_fit`, in squared spacings).
Per agreement threshold, beside the agreement alone, the rule that also bounds shift, trimmed fit or fitness
(a small grid) and trusts the most even pairs with at least 95 % of them within 5 degrees; its figures on the
odd pairs, not used to choose it, are in the last two columns.

    python scripts/check_verdict_signals.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen \
        --pairs 48 --save runs/verdict_signals.npz
    python scripts/check_verdict_signals.py --load runs/verdict_signals.npz     # the analysis again
"""

import argparse
import itertools

import numpy as np
from scipy.spatial import cKDTree

from dit_jax import checkpoint, evaluation, geometry, icp as icp_lib, registration, training
from dit_jax.data import pairs as pairs_lib

RIGHT_DEG = 5.0
PRECISION = 0.95
GRID = {"agreement": (1, 1.5, 2, 3, 4, 5, 6, 8), "shift": (np.inf, 0.5, 1, 2, 3, 5),
        "trimmed_fit": (np.inf, 0.25, 0.5, 1, 2), "fitness": (0, 0.5, 0.6, 0.7, 0.8)}


def gather(params, config, batches: dict) -> dict[str, np.ndarray]:
    """Per-pair evidence (P,) over every setting of ``batches`` ({setting: validation batch})."""
    rows = {k: [] for k in ("setting", "error", "agreement", "shift", "fitness", "trimmed_fit")}
    for setting, b in batches.items():
        pairs, indices = pairs_lib.PairView(b), np.arange(len(b["src"]))
        forward = evaluation.predict_dit(params, config, pairs, indices)
        refined = evaluation.refine_dit(forward, pairs, indices, truth_fit=False)
        both = evaluation.backward_agreement(params, config, pairs, indices, forward, refined)
        back = both[evaluation.METHOD_DIT_ICP]
        kept = evaluation.choose_direction(refined, back, pairs, indices)
        for i in indices:
            src, tgt = b["src"][i].astype(np.float64), b["tgt"][i].astype(np.float64)
            spacing = float(np.median(cKDTree(src).query(src, k=2)[0][:, 1]))
            tree = cKDTree(tgt)
            rotation, translation = kept["R"][i], kept["t"][i]
            inverse = (back["R"][i].T, -back["R"][i].T @ back["t"][i])
            rows["setting"].append(setting)
            rows["error"].append(geometry.rotation_angle_deg(rotation.T @ b["R"][i]))
            rows["agreement"].append(back["agreement"][i])
            rows["shift"].append(icp_lib.mean_shift(src, refined["R"][i], refined["t"][i], *inverse) / spacing)
            rows["fitness"].append(float(np.mean(tree.query(src @ rotation.T + translation)[0] <= 2 * spacing)))
            rows["trimmed_fit"].append(icp_lib.trimmed_fit(src, tree, rotation, translation) / spacing ** 2)
        print(f"{setting}: gathered", flush=True)
    return {k: np.asarray(v) for k, v in rows.items()}


def score(trusted: np.ndarray, errors: np.ndarray) -> tuple[float, float, int]:
    """(share of trusted results right, share of failures flagged, results trusted), as evaluate.py counts."""
    v = evaluation.verdict_summary(errors, trusted, "", RIGHT_DEG)
    return v["passed_right"], v["failures_caught"], v["passed"]


def trust(d: dict, agreement, shift, trimmed_fit, fitness) -> np.ndarray:
    return ((d["agreement"] <= agreement) & (d["shift"] <= shift) & (d["trimmed_fit"] <= trimmed_fit)
            & (d["fitness"] >= fitness))


def report(d: dict) -> None:
    right = d["error"] <= RIGHT_DEG
    choose = np.arange(len(right)) % 2 == 0
    print(f"{len(right)} pairs, {int((~right).sum())} more than {RIGHT_DEG:g} deg off\n")
    print("| rule | trusted right (all) | failures flagged (all) | trusted (all) | trusted right (odd) | "
          "failures flagged (odd) |")
    print("|---|---|---|---|---|---|")
    trivial = (np.inf, np.inf, 0)
    best = {}
    for a in GRID["agreement"]:
        for rest in itertools.product(*(GRID[k] for k in ("shift", "trimmed_fit", "fitness"))):
            p, c, n = score(trust(d, a, *rest)[choose], d["error"][choose])
            if rest != trivial and n and p >= PRECISION and (a not in best or (n, c) > best[a][0]):
                best[a] = ((n, c), rest)
    for a in GRID["agreement"]:
        for rest in [trivial] + ([best[a][1]] if a in best else []):
            t = trust(d, a, *rest)
            p, c, n = score(t, d["error"])
            po, co, _ = score(t[~choose], d["error"][~choose])
            bounds = "" if rest == trivial else ", shift <= {:g}, trimmed fit <= {:g}, fitness >= {:g}".format(*rest)
            print(f"| agreement <= {a:g}{bounds} | {p:.3f} | {c:.3f} | {n} | {po:.3f} | {co:.3f} |")
    independent = np.array([pairs_lib.SETTINGS[str(x)].independent for x in d["setting"]])
    print("\nThe largest agreement threshold with at least 95 % of the trusted results right, pooled over:")
    for name, pool in (("every setting", np.ones_like(independent)), ("the settings that share no point", independent)):
        fits = [a for a in GRID["agreement"] if score(d["agreement"][pool] <= a, d["error"][pool])[0] >= PRECISION]
        if fits:
            a = max(fits)
            p, c, n = score(d["agreement"][independent] <= a, d["error"][independent])
            print(f"- {name}: {a:g} deg; on the settings that share no point {p:.3f} of {n} trusted right, "
                  f"{c:.3f} of failures flagged")
    fooled = trust(d, 4, np.inf, np.inf, 0) & ~right
    honest = trust(d, 4, np.inf, np.inf, 0) & right
    print(f"\nTrimmed fit (squared spacings) at agreement <= 4: the {int(fooled.sum())} trusted failures median "
          f"{np.median(d['trimmed_fit'][fooled]):.2f}; the {int(honest.sum())} trusted right results median "
          f"{np.median(d['trimmed_fit'][honest]):.2f}, 90th percentile {np.percentile(d['trimmed_fit'][honest], 90):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=48, help="validation pairs per setting")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--save", default=None, help="write the per-pair evidence here (npz)")
    parser.add_argument("--load", default=None, help="analyse evidence saved earlier instead of gathering it")
    args = parser.parse_args()
    if args.load:
        d = dict(np.load(args.load))
    else:
        params, config = checkpoint.restore(args.checkpoint or registration.shipped_weights())
        batches = training.validation_batches(args.data_dir, list(pairs_lib.SETTINGS), count=args.pairs,
                                              unseen=args.unseen)
        d = gather(params, config, batches)
        if args.save:
            np.savez(args.save, **d)
    report(d)


if __name__ == "__main__":
    main()
