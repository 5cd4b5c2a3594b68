"""Training throughput of a recipe's train step on this machine: pairs per second, the work per step, and the
share of the machine's matmul peak it reaches; with ``--compare REV``, the same step of another commit
measured in the same run.

    python benchmarks/train_throughput.py                                   # configs/cpu.py and configs/paper.py
    python benchmarks/train_throughput.py --config configs/cpu.py --compare HEAD~1
    python benchmarks/train_throughput.py --config configs/paper.py --remat on
    python benchmarks/train_throughput.py --config configs/cpu.py --mix        # a mix of every setting
    python benchmarks/train_throughput.py --config configs/cpu.py --precision highest --precision bfloat16 --by-part

Random clouds of the recipe's point count; each step is compiled first, then timed (median of --steps).
The work per step is counted on the step's jaxpr, loops times their trip counts: GFLOP (matrix products at
2 FLOP per multiply-add, plus one per element of every other arithmetic operation) and the bytes its
operations read and write if none were fused (an upper bound of the memory traffic: XLA fuses, and its own
cost analysis counts a loop's body once). The probe is the best GFLOP/s of a float32 2048 x 2048 matmul;
``probe_share`` is the step's GFLOP/s over it. ``--compare REV`` checks REV out in a temporary git worktree
and times its step in a child process with the same arguments, alternating with this tree's, and prints
the ratio of pairs per second. Peak memory: the process's peak resident set (VmHWM, compilation included)
and, on an accelerator, the device's peak bytes in use. Prints one JSON record per recipe.

``--precision P`` times the step with the network's products at P (``TrainConfig.train_precision``); given
more than once, each precision is timed in turn in the same run, and each record after the first gives
``pairs_per_s_ratio``, its pairs per second over the first's; ``auto`` (the ``cpu`` and ``paper`` recipes'
own) times both as ``train.py`` does when a run starts (or reads its cached choice) and adds
``auto_precision``, the choice and the two steps' seconds. ``--by-part`` adds ``by_part_ms``: a profile of
two steps (``jax.profiler``), each compiled operation's time added to the part of the network it comes from
(its ``op_name``: PSE, PFT's attention and feed-forward layers, the positional encoding, the head, ...), forward
and backward apart, in milliseconds per step summed over the threads; and ``by_kind_ms``, the same time by kind of
operation: products (XLA's dots and the fusions that hold one), elementwise work and
reductions (the softmax, the norms), fusions holding a conversion between float32 and bfloat16, copies and
transposes, and the rest.

``--mix`` trains on real pairs of a mix instead (the recipe's ``settings``, else every setting of
:data:`dit_jax.data.pairs.SETTINGS`, from the embedded shapes), one batch of each setting in turn: it reports
the train-step programs compiled for the whole mix, the compile and first step, and each setting's step.
"""

import argparse
import contextlib
import dataclasses
import datetime
import json
import os
import pathlib
import re
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT_CONFIGS = ("configs/cpu.py", "configs/paper.py")

#: Primitives that move or relabel data without arithmetic: no FLOPs (their bytes still count).
_NO_ARITHMETIC = {
    "reshape",
    "broadcast_in_dim",
    "transpose",
    "squeeze",
    "expand_dims",
    "convert_element_type",
    "slice",
    "dynamic_slice",
    "dynamic_update_slice",
    "concatenate",
    "pad",
    "gather",
    "scatter",
    "scatter-add",
    "scatter_add",
    "select_n",
    "iota",
    "copy",
    "copy_p",
    "rev",
    "sort",
    "stop_gradient",
    "device_put",
    "sharding_constraint",
    "argmax",
    "argmin",
    "top_k",
}


def count_work(jaxpr) -> tuple[float, float]:
    """(FLOPs, bytes read and written unfused) of a closed jaxpr, loops times their trip counts."""
    from jax.extend import core

    flops = nbytes = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        subs = [v for v in eqn.params.values() if isinstance(v, (core.ClosedJaxpr, core.Jaxpr))]
        if name == "scan":
            f, b = count_work(eqn.params["jaxpr"].jaxpr)
            flops, nbytes = flops + eqn.params["length"] * f, nbytes + eqn.params["length"] * b
            continue
        if name == "cond":
            costs = [count_work(branch.jaxpr) for branch in eqn.params["branches"]]
            flops, nbytes = flops + max(c[0] for c in costs), nbytes + max(c[1] for c in costs)
            continue
        if subs:  # pjit, remat, custom_jvp/vjp calls, while (its body once: no trip count is known)
            for sub in subs:
                f, b = count_work(sub.jaxpr if isinstance(sub, core.ClosedJaxpr) else sub)
                flops, nbytes = flops + f, nbytes + b
            continue
        sizes = [float(np.prod(v.aval.shape)) for v in (*eqn.invars, *eqn.outvars) if hasattr(v.aval, "shape")]
        nbytes += sum(
            float(np.prod(v.aval.shape)) * v.aval.dtype.itemsize
            for v in (*eqn.invars, *eqn.outvars)
            if hasattr(v.aval, "dtype")
        )
        if name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            flops += 2.0 * float(np.prod(eqn.outvars[0].aval.shape)) * float(np.prod([lhs[d] for d in contract]))
        elif name not in _NO_ARITHMETIC and sizes:
            flops += float(np.prod(eqn.outvars[0].aval.shape)) if eqn.outvars else 0.0
    return flops, nbytes


def measure(
    config_path: str,
    steps: int,
    n_points: int | None,
    remat: str,
    count: bool,
    precision: str = "preset",
    by_part: bool = False,
) -> dict:
    """Compiles and times the recipe's train step; counts its work where ``count``, profiles it by part
    where ``by_part``."""
    import jax

    from dit_jax import training

    config = training.load_config(config_path)
    if precision != "preset":
        config = dataclasses.replace(config, train_precision=precision)
    if n_points:
        config = dataclasses.replace(config, n_points=n_points)
    if remat != "preset":
        config = dataclasses.replace(config, model=config.model.replace(remat=remat == "on"))
    optimizer = training.make_optimizer(config, 1000)
    mesh = training.make_mesh()
    rng = np.random.default_rng(0)
    b, n = config.batch_size, config.n_points
    src = rng.uniform(-1, 1, (b, n, 3)).astype(np.float32)
    host_batch = {
        "src": src,
        "tgt": src[:, ::-1] + 0.1,
        "R": np.tile(np.eye(3, dtype=np.float32), (b, 1, 1)),
        "t": np.full((b, 3), 0.1, np.float32),
    }
    auto = None
    # A tree older than the precision setting (--compare REV) has neither the field nor the step's own config.
    if getattr(config, "train_precision", None) == "auto":  # as train.py chooses it on this machine
        auto = training.precision.choose(config, optimizer, mesh, host_batch)
        config = dataclasses.replace(config, train_precision=auto.precision)
    state = training.replicate(training.init_state(config, optimizer), mesh)
    step = training.make_train_step(config, optimizer, mesh)
    batch = training.shard_batch(host_batch, mesh)
    record = {
        "config": config_path,
        "n_points": n,
        "batch_size": b,
        "train_iters": config.train_iters,
        "remat": config.model_config().remat,
        "precision": getattr(config, "train_model_config", config.model_config)().precision,
    }
    record["auto_precision"] = None if auto is None else dataclasses.asdict(auto) | {"speedup": auto.speedup}
    if count:
        flops, nbytes = count_work(jax.make_jaxpr(step)(state, batch).jaxpr)
        record.update(gflop_per_step=flops / 1e9, unfused_gbytes_per_step=nbytes / 1e9, flop_per_byte=flops / nbytes)
    t0 = time.perf_counter()
    state, out = step(state, batch)
    out["loss"].block_until_ready()
    record["compile_and_first_step_s"] = time.perf_counter() - t0
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        state, out = step(state, batch)
        out["loss"].block_until_ready()
        times.append(time.perf_counter() - t0)
    record["step_s"] = float(np.median(times))
    record["pairs_per_s"] = b / record["step_s"]
    if by_part:
        record["by_part_ms"], record["by_kind_ms"] = profile_by_part(step, state, batch)
    return record


#: Parts of the network, found in a compiled operation's op_name (the Flax module path), first match wins.
_PARTS = (
    ("pse.attention", ("pse/attention", "TokenTransformer")),
    ("pft.self_attn", ("self_attn",)),
    ("pft.src_attn", ("src_attn",)),
    ("pft.feed_forward", ("feed_forward",)),
    ("positional_encoding", ("positional_encoding",)),
    ("squeeze_excitation", ("/se/",)),
    ("temperature_net", ("/temp_net/",)),
    ("pse.other", ("/pse/", "DIT.embed")),
    ("pft.other", ("pft", "DIT.interact")),
)


def _computations_with_products(hlo_text: str) -> set[str]:
    """The names of the computations of compiled HLO text that hold a matrix product."""
    holding, current = set(), None
    for line in hlo_text.splitlines():
        header = re.match(r"%?([\w.\-]+) \(", line)
        if header:
            current = header.group(1)
        elif current and re.search(r" (dot|convolution)\(", line):
            holding.add(current)
    return holding


def _operation_kind(name: str, line: str, with_products: set[str]) -> str:
    """The kind of a compiled operation, from its name and its line of HLO text."""
    called = re.search(r"calls=%?([\w.\-]+)", line)
    if re.search(r" (dot|convolution)\(", line) or (called and called.group(1) in with_products):
        return "products (fusions included)"
    if " fusion(" in line:  # XLA names a fusion after what it holds: a conversion of precision, or arithmetic
        return "conversions (fusions holding one)" if "convert" in name else "elementwise and reductions"
    if re.search(r" (copy|transpose)\(", line):
        return "copies and transposes"
    return "other (sorting, top-k, SVD, loops' control)"


def profile_by_part(step, state, batch, repeats: int = 2) -> tuple[dict, dict]:
    """Milliseconds per step of the compiled operations of ``step``, by part and pass, and by kind of
    operation (see ``--by-part``)."""
    import collections
    import gzip

    import jax

    operation_names, kinds = {}, {}
    hlo_text = step.lower(state, batch).compile().as_text()
    with_products = _computations_with_products(hlo_text)
    for line in hlo_text.splitlines():
        instruction = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = ", line)
        if instruction:  # XLA's own copies have no op_name: they count by kind only
            kinds[instruction.group(1)] = _operation_kind(instruction.group(1), line, with_products)
        found = re.match(r'\s*(?:ROOT )?%?([\w.\-]+) = .*?op_name="([^"]+)"', line)
        if found:
            operation_names[found.group(1)] = found.group(2)
    with tempfile.TemporaryDirectory() as directory:
        with jax.profiler.trace(directory):
            for _ in range(repeats):
                state, out = step(state, batch)
                out["loss"].block_until_ready()
        trace = next(pathlib.Path(directory).rglob("*.trace.json.gz"))
        events = json.load(gzip.open(trace))["traceEvents"]
    by_part, by_kind = collections.Counter(), collections.Counter()
    for event in events:
        if event.get("ph") != "X" or event.get("name") not in kinds:
            continue
        by_kind[kinds[event["name"]]] += event["dur"] / 1e3 / repeats
        op_name = operation_names.get(event["name"])
        if op_name is None:
            continue
        part = next((name for name, keys in _PARTS if any(key in op_name for key in keys)), "head, losses, other")
        direction = "backward" if "transpose(" in op_name else "forward"
        by_part[f"{part} {direction}"] += event["dur"] / 1e3 / repeats
    rounded = lambda counter: {name: round(ms, 1) for name, ms in counter.most_common()}
    return rounded(by_part), rounded(by_kind)


def measure_mix(config_path: str, steps: int, n_points: int | None) -> dict:
    """Compiles the recipe's train step for a mix of settings and times a batch of each setting in turn."""
    from dit_jax import training
    from dit_jax.data import pairs

    config = training.load_config(config_path)
    config = dataclasses.replace(
        config, settings=config.settings or tuple(pairs.SETTINGS), data_dir=None, n_points=n_points or config.n_points
    )
    optimizer = training.make_optimizer(config, 1000)
    mesh = training.make_mesh()
    state = training.replicate(training.init_state(config, optimizer), mesh)
    step = training.make_train_step(config, optimizer, mesh)
    train_ds, _ = training.make_datasets(config)
    b = config.batch_size
    batches = {s: train_ds.setting_batch(s, np.arange(b)) for s in dict.fromkeys(config.settings)}
    record = {
        "config": config_path,
        "mix": list(batches),
        "mix_one_size": config.mix_one_size,
        "cloud_points": sorted({v["src"].shape[1] for v in batches.values()}),
        "batch_size": b,
    }
    t0 = time.perf_counter()
    state, out = step(state, training.shard_batch(next(iter(batches.values())), mesh))
    out["loss"].block_until_ready()
    record["compile_and_first_step_s"] = time.perf_counter() - t0
    per_setting = {}
    for _ in range(steps):
        for setting, batch in batches.items():
            t0 = time.perf_counter()
            state, out = step(state, training.shard_batch(batch, mesh))
            out["loss"].block_until_ready()
            per_setting.setdefault(setting, []).append(time.perf_counter() - t0)
    record["first_step_of_each_setting_s"] = {s: t[0] for s, t in per_setting.items()}
    record["step_s"] = float(np.median([t for ts in per_setting.values() for t in ts[1:] or ts]))
    record["compiled_train_steps"] = step._cache_size()
    return record


@contextlib.contextmanager
def worktree(rev: str):
    """A temporary checkout of ``rev`` (a git worktree, removed afterwards)."""
    directory = tempfile.mkdtemp(prefix="dit-jax-compare-")
    subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", "-f", directory, rev], check=True, capture_output=True
    )
    try:
        yield pathlib.Path(directory)
    finally:
        subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", directory], capture_output=True)


def child_measure(tree: pathlib.Path, config_path: str, args, precision: str) -> dict:
    """``measure`` in a fresh process importing ``dit_jax`` from ``tree``, the recipe read from there too."""
    command = [
        sys.executable,
        str(pathlib.Path(__file__).resolve()),
        "--child",
        "--config",
        config_path,
        "--steps",
        str(args.steps),
        "--remat",
        args.remat,
    ]
    if precision != "preset":  # older trees know no --precision
        command += ["--precision", precision]
    if args.n_points:
        command += ["--n-points", str(args.n_points)]
    env = dict(os.environ, PYTHONPATH=str(tree), DIT_JAX_COMPILE_CACHE="off")
    done = subprocess.run(command, cwd=str(tree), env=env, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"error: the step of {tree} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", action="append", help="a recipe file (repeatable; default: cpu and paper)")
    parser.add_argument("--steps", type=int, default=3, help="timed steps after the first (median)")
    parser.add_argument("--n-points", type=int, default=None)
    parser.add_argument(
        "--remat",
        choices=("preset", "on", "off"),
        default="preset",
        help="rematerialised blocks (DITConfig.remat): the recipe's choice, or on / off",
    )
    parser.add_argument(
        "--precision",
        action="append",
        choices=("preset", "auto", "highest", "tf32", "bfloat16"),
        help="the train step's products (TrainConfig.train_precision; repeatable: each in turn; default: the "
        "recipe's; auto: as train.py chooses it on this machine)",
    )
    parser.add_argument("--by-part", action="store_true", help="profile the step by part of the network (see above)")
    parser.add_argument("--compare", metavar="REV", help="also time the step of this git revision")
    parser.add_argument("--mix", action="store_true", help="real pairs of a mix of settings (see above)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    configs = args.config or list(DEFAULT_CONFIGS)
    precisions = args.precision or ["preset"]
    if args.mix:
        import jax

        for config_path in configs:
            record = {
                "date": datetime.date.today().isoformat(),
                "device": jax.devices()[0].device_kind,
                **measure_mix(config_path, args.steps, args.n_points),
            }
            print(json.dumps(record, indent=2), flush=True)
        return

    if args.child:  # one recipe, timed only: the other tree's library may not count work the same way
        print(json.dumps(measure(configs[0], args.steps, args.n_points, args.remat, False, precisions[0])))
        return

    import jax
    from inference import matmul_peak, peak_memory  # benchmarks/inference.py, beside this script

    probe = matmul_peak()
    with worktree(args.compare) if args.compare else contextlib.nullcontext() as other:
        for config_path in configs:
            first = None
            for precision in precisions:
                record = {
                    "date": datetime.date.today().isoformat(),
                    "device": jax.devices()[0].device_kind,
                    **measure(config_path, args.steps, args.n_points, args.remat, True, precision, args.by_part),
                    "probe_gflop_s": probe,
                }
                record["probe_share"] = record["gflop_per_step"] / record["step_s"] / probe
                first = first or record
                if record is not first:
                    record["pairs_per_s_ratio"] = record["pairs_per_s"] / first["pairs_per_s"]
                if other is not None:
                    # This tree's step again in a fresh process beside the other's, so both ran alike.
                    ours = child_measure(ROOT, config_path, args, precision)
                    theirs = child_measure(other, config_path, args, precision)
                    record["compare"] = {
                        "rev": args.compare,
                        "step_s": theirs["step_s"],
                        "compile_and_first_step_s": theirs["compile_and_first_step_s"],
                        "this_tree_step_s": ours["step_s"],
                        "ratio": theirs["step_s"] / ours["step_s"],
                    }
                print(json.dumps({**record, **peak_memory()}, indent=2), flush=True)


if __name__ == "__main__":
    main()
