"""Would other evidence make DIT+ICP's verdict better than the agreement of its two directions alone?

On validation pairs of training shapes (never test pairs), per pair: the rotation error of the motion
``register(refine="icp")`` returns (best direction), the agreement between the two refined directions, how far
apart the two place the source points (in point spacings), the kept motion's fitness (share of source points
within two spacings of the target) and its trimmed fit (:func:`dit_jax.icp.trimmed_fit`, in squared spacings).
With ``--rerun``, two more registrations of each pair (network, then ICP, as ``register`` does) that a wrong
pose found twice might not survive: ``resample``, the degrees between the kept rotation and that of a
registration of independent random subsets (:data:`RESAMPLE_SHARE` of each cloud's points), and ``turned``,
the same for a registration whose source was first turned :data:`TURN_DEG` degrees about a random axis (the
turn taken back out of the estimate). Per agreement threshold, beside the agreement alone, the rule that also
bounds the other signals (a small grid each) and trusts the most even pairs with at least 95 % of them within
5 degrees; its figures on the odd pairs, not used to choose it, are in the last two columns.

    python scripts/check_verdict_signals.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen \
        --pairs 48 --save runs/verdict_signals.npz
    python scripts/check_verdict_signals.py --load runs/verdict_signals.npz     # the analysis again
    python scripts/check_verdict_signals.py --data-dir ../shared/data/modelnet40_ply_hdf5_1024 --unseen \
        --pairs 96 --independent-only --rerun --save runs/verdict_rerun.npz
"""

import argparse
import itertools

import numpy as np
from scipy.spatial import cKDTree

from dit_jax import checkpoint, evaluation, geometry, icp as icp_lib, registration, training
from dit_jax.data import pairs as pairs_lib

RIGHT_DEG = 5.0
PRECISION = 0.95
GRID = {"agreement": (0.5, 1, 1.5, 2, 3, 4, 5, 6, 8), "shift": (np.inf, 0.5, 1, 2, 3, 5),
        "trimmed_fit": (np.inf, 0.25, 0.5, 1, 2), "fitness": (0, 0.5, 0.6, 0.7, 0.8)}
#: Bounds tried on the ``--rerun`` signals (degrees).
RERUN_GRID = (np.inf, 10, 5, 3, 2, 1)
#: ``resample`` registers this share of each cloud's points, drawn independently.
RESAMPLE_SHARE = 0.75
#: ``turned`` turns the source by this many degrees about a random axis first.
TURN_DEG = 25.0


def _dit_icp(params, config, batch: dict, indices: np.ndarray) -> dict:
    """DIT+ICP forward on ``batch``, as ``register(refine="icp")`` gives it for one direction."""
    pairs = pairs_lib.PairView(batch)
    return evaluation.refine_dit(evaluation.predict_dit(params, config, pairs, indices), pairs, indices,
                                 truth_fit=False)


def rerun_signals(params, config, b: dict, kept: dict, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The ``resample`` and ``turned`` signals (P,) of :func:`gather` for one setting's batch ``b``, whose
    DIT+ICP motions are ``kept`` ({"R": (P, 3, 3)})."""
    indices = np.arange(len(b["src"]))
    n_src, n_tgt = (max(3, int(round(RESAMPLE_SHARE * b[k].shape[1]))) for k in ("src", "tgt"))
    subset = {"src": np.stack([s[rng.choice(len(s), n_src, replace=False)] for s in b["src"]]),
              "tgt": np.stack([t[rng.choice(len(t), n_tgt, replace=False)] for t in b["tgt"]])}
    resampled = _dit_icp(params, config, subset, indices)
    turns = np.stack([geometry.axis_angle_matrix(rng.normal(size=3), TURN_DEG) for _ in indices])
    turned_src = np.einsum("pij,pnj->pni", turns, b["src"]).astype(b["src"].dtype)
    turned = _dit_icp(params, config, {"src": turned_src, "tgt": b["tgt"]}, indices)
    return {"resample": np.array([geometry.rotation_angle_deg(r.T @ k) for r, k in zip(resampled["R"], kept["R"])]),
            "turned": np.array([geometry.rotation_angle_deg((r @ p).T @ k)
                                for r, p, k in zip(turned["R"], turns, kept["R"])])}


def gather(params, config, batches: dict, rerun: bool = False, seed: int = 0) -> dict[str, np.ndarray]:
    """Per-pair evidence (P,) over every setting of ``batches`` ({setting: validation batch}); with ``rerun``
    the :func:`rerun_signals` too."""
    rng = np.random.default_rng(seed)
    rows = {k: [] for k in ("setting", "error", "agreement", "shift", "fitness", "trimmed_fit")}
    if rerun:
        rows |= {"resample": [], "turned": []}
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
        if rerun:
            for key, values in rerun_signals(params, config, b, kept, rng).items():
                rows[key].extend(values)
        print(f"{setting}: gathered", flush=True)
    return {k: np.asarray(v) for k, v in rows.items()}


def score(trusted: np.ndarray, errors: np.ndarray) -> tuple[float, float, int]:
    """(share of trusted results right, share of failures flagged, results trusted), as evaluate.py counts."""
    v = evaluation.verdict_summary(errors, trusted, "", RIGHT_DEG)
    return v["passed_right"], v["failures_caught"], v["passed"]


def trust(d: dict, agreement: float, **bounds) -> np.ndarray:
    """Trusted (P,): agreement within ``agreement`` and every other signal within its bound (fitness at or
    above its bound, the rest at or below)."""
    trusted = d["agreement"] <= agreement
    for key, bound in bounds.items():
        trusted &= d[key] >= bound if key == "fitness" else d[key] <= bound
    return trusted


def _grid(key: str) -> tuple:
    return GRID.get(key, RERUN_GRID)


def report(d: dict) -> None:
    right = d["error"] <= RIGHT_DEG
    choose = np.arange(len(right)) % 2 == 0
    print(f"{len(right)} pairs, {int((~right).sum())} more than {RIGHT_DEG:g} deg off\n")
    print("| rule | trusted right (all) | failures flagged (all) | trusted (all) | trusted right (odd) | "
          "failures flagged (odd) |")
    print("|---|---|---|---|---|---|")
    families = [("shift", "trimmed_fit", "fitness")]
    if "resample" in d:
        families += [("resample", "turned"), ("resample",), ("turned",)]
    for a in GRID["agreement"]:
        rules = [{}]
        for keys in families:
            best = None
            for values in itertools.product(*(_grid(k) for k in keys)):
                bounds = dict(zip(keys, values))
                if all(v == _grid(k)[0] for k, v in bounds.items()):
                    continue  # the agreement alone, listed first
                p, c, n = score(trust(d, a, **bounds)[choose], d["error"][choose])
                if n and p >= PRECISION and (best is None or (n, c) > best[0]):
                    best = ((n, c), bounds)
            if best is not None:
                bounds = {k: v for k, v in best[1].items() if v != _grid(k)[0]}
                if bounds not in rules:
                    rules.append(bounds)
        for bounds in rules:
            t = trust(d, a, **bounds)
            p, c, n = score(t, d["error"])
            po, co, _ = score(t[~choose], d["error"][~choose])
            text = "".join(f", {k.replace('_', ' ')} {'>=' if k == 'fitness' else '<='} {v:g}" for k, v in bounds.items())
            print(f"| agreement <= {a:g}{text} | {p:.3f} | {c:.3f} | {n} | {po:.3f} | {co:.3f} |")
    independent = np.array([pairs_lib.SETTINGS[str(x)].independent for x in d["setting"]])
    print("\nThe largest agreement threshold with at least 95 % of the trusted results right, pooled over:")
    for name, pool in (("every setting", np.ones_like(independent)), ("the settings that share no point", independent)):
        fits = [a for a in GRID["agreement"] if score(d["agreement"][pool] <= a, d["error"][pool])[0] >= PRECISION]
        if fits:
            a = max(fits)
            p, c, n = score(d["agreement"][independent] <= a, d["error"][independent])
            print(f"- {name}: {a:g} deg; on the settings that share no point {p:.3f} of {n} trusted right, "
                  f"{c:.3f} of failures flagged")
    fooled = trust(d, 4) & ~right
    honest = trust(d, 4) & right
    print(f"\nTrimmed fit (squared spacings) at agreement <= 4: the {int(fooled.sum())} trusted failures median "
          f"{np.median(d['trimmed_fit'][fooled]):.2f}; the {int(honest.sum())} trusted right results median "
          f"{np.median(d['trimmed_fit'][honest]):.2f}, 90th percentile {np.percentile(d['trimmed_fit'][honest], 90):.2f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data-dir", default=None)
    parser.add_argument("--unseen", action="store_true", help="validation shapes of categories 0-19 only")
    parser.add_argument("--pairs", type=int, default=48, help="validation pairs per setting")
    parser.add_argument("--checkpoint", default=None, help="default: the shipped weights")
    parser.add_argument("--independent-only", action="store_true",
                        help="only the settings whose clouds share no point (the verdict's pool)")
    parser.add_argument("--rerun", action="store_true", help="gather the resample and turned signals too "
                        "(two more registrations per pair)")
    parser.add_argument("--save", default=None, help="write the per-pair evidence here (npz)")
    parser.add_argument("--load", default=None, help="analyse evidence saved earlier instead of gathering it")
    args = parser.parse_args()
    if args.load:
        d = dict(np.load(args.load))
    else:
        params, config = checkpoint.restore(args.checkpoint or registration.shipped_weights())
        settings = [s for s in pairs_lib.SETTINGS if pairs_lib.SETTINGS[s].independent or not args.independent_only]
        batches = training.validation_batches(args.data_dir, settings, count=args.pairs, unseen=args.unseen)
        d = gather(params, config, batches, rerun=args.rerun)
        if args.save:
            np.savez(args.save, **d)
    report(d)


if __name__ == "__main__":
    main()
