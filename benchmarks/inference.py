"""Inference speed, FLOPs and memory of `register` for a config, against this machine's matmul peak.

    python benchmarks/inference.py                         # paper config, batches 1, 8, 32, "highest"
    python benchmarks/inference.py --sizes 512 1024 --skip-batches
    python benchmarks/inference.py --precision tf32 --sizes   # an opt-in precision, no scaling sweep
    python benchmarks/inference.py --dtype bfloat16

One run measures, in order, on the default device (printed: a GPU where JAX has one, else the CPU):
1. a matmul-peak probe: jitted (S x S) @ (S x S) float32 products at the chosen precision, best of 5;
2. at --n-points (1000) for each of --iters (2 and 3) and --batches (1, 8 and 32), each in a fresh process:
   seconds per pair and pairs per second of the compiled `model.register` (warm: compiled and run once first;
   median of --repeats), the peak memory of that process (device bytes on an accelerator, resident memory
   on a CPU), XLA's FLOP count (cost analysis of its parts, see `register_flops`) and the achieved GFLOP/s;
   for the paper config at 1000 points, the authors' PyTorch figures on one H100 (issue 18) beside them;
3. for each of --sizes (512 ... 8192 points, batch 1, the largest --iters): time per pair and the peak
   memory of a fresh process doing only that (compile included), plus XLA's own buffer estimate.

Every product of the network runs at --precision (DITConfig.precision, default "highest": float32 whatever
JAX's global default says). Weights are random (speed does not depend on them). Prints a markdown report and
writes --json.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

import numpy as np


def _setup_jax():
    import jax

    return jax


#: The authors' PyTorch implementation on one H100, float32 with TF32 off, 1000 points (issue 18): seconds per
#: pair by (iterations, batch), and peak GPU memory at batch 1. The batch-32 figure's iteration count is not
#: stated there; it is listed with 2.
AUTHORS_H100_S_PER_PAIR = {(2, 1): 0.212, (2, 8): 0.0385, (3, 8): 0.0678, (2, 32): 0.0363}
AUTHORS_H100_PEAK_GB_BATCH_1 = 18.8


def matmul_peak(size: int = 2048, repeats: int = 5, precision: str = "highest") -> float:
    """Best GFLOP/s of a jitted float32 (size x size) matmul at ``precision``."""
    jax = _setup_jax()
    import jax.numpy as jnp

    from dit_jax.network.layers import dot_precision

    a = jax.random.normal(jax.random.PRNGKey(0), (size, size), jnp.float32)
    b = jax.random.normal(jax.random.PRNGKey(1), (size, size), jnp.float32)
    f = jax.jit(lambda x, y: jnp.matmul(x, y, precision=dot_precision(precision)))
    f(a, b).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        f(a, b).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return 2 * size**3 / best / 1e9


def _inputs(batch: int, n_points: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(batch, n_points, 3)).astype(np.float32)
    shape /= np.linalg.norm(shape, axis=-1, keepdims=True)  # points on a sphere ...
    shape *= rng.uniform(0.5, 1.0, size=(batch, n_points, 1)).astype(np.float32)  # ... filled in
    angle = np.radians(30.0)
    rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]], np.float32)
    tgt = (shape @ rot.T + 0.1)[:, rng.permutation(n_points)]
    return shape, tgt


def _flops(fn, *args) -> float:
    import jax

    cost = jax.jit(fn).lower(*args).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, (list, tuple)) else cost
    return float(cost.get("flops", float("nan"))) if cost else float("nan")


def register_flops(params, config, src, tgt) -> float:
    """FLOPs of one pair's registration, summed over its parts as `register` runs them.

    XLA's cost analysis counts a loop body once whatever its trip count, and `register` runs its GMCCE
    iterations in a `lax.scan`; so this adds the target's embedding and memory, the source's kNN graph,
    and n_iters network passes with the soft head once and the GMCCE head n_iters - 1 times.
    """
    from dit_jax.geometry import rigid
    from dit_jax.network import model
    from dit_jax.network.head import head

    # Blocked attention is a loop too (same products, counted once): count the unblocked program.
    config = config.replace(attention_chunk=0)

    emb = model.embed(params, tgt, config, encode=True)
    knn = rigid.knn(src, config.k)
    feats = model.features(params, src, tgt, config, tgt_embedding=emb, src_knn=knn)[1]
    total = _flops(lambda p, y: model.embed(p, y, config, encode=True), params, tgt)
    total += _flops(lambda x: rigid.knn(x, config.k), src)
    total += config.n_iters * _flops(
        lambda p, x, e, kn: model.features(p, x, tgt, config, tgt_embedding=e, src_knn=kn)[1].scores,
        params,
        src,
        emb,
        knn,
    )
    for use_gmcce, times in ((False, 1), (True, config.n_iters - 1)):
        if times:
            total += times * _flops(
                lambda s_, t_: head(src, tgt, s_, t_, config, use_gmcce).rotation, feats.scores, feats.temperature
            )
    return total


def time_register(config, batch: int, n_points: int, repeats: int, count_flops: bool = True) -> dict:
    """Compiles `register` for (batch, n_points), runs it once, then times ``repeats`` calls."""
    jax = _setup_jax()
    from dit_jax.network import model

    params = model.init(jax.random.PRNGKey(0), config)
    src, tgt = _inputs(batch, n_points)
    src, tgt = jax.device_put(src), jax.device_put(tgt)
    t0 = time.perf_counter()
    lowered = model.register.lower(params, src, tgt, config)
    compiled = lowered.compile()
    compile_s = time.perf_counter() - t0
    memory = compiled.memory_analysis()
    jax.block_until_ready(compiled(params, src, tgt))  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(params, src, tgt))
        times.append(time.perf_counter() - t0)
    seconds = statistics.median(times)
    flops = batch * register_flops(params, config, src[0], tgt[0]) if count_flops else float("nan")
    return {
        "batch": batch,
        "n_points": n_points,
        "n_iters": config.n_iters,
        "compile_s": compile_s,
        "times_s": times,
        "seconds_per_call": seconds,
        "seconds_per_pair": seconds / batch,
        "pairs_per_s": batch / seconds,
        "flops_per_call": flops,
        "gflops_per_s": flops / seconds / 1e9,
        "xla_temp_bytes": getattr(memory, "temp_size_in_bytes", None),
        "xla_argument_bytes": getattr(memory, "argument_size_in_bytes", None),
    }


def _peak_rss_bytes() -> int:
    """This process's peak resident memory. VmHWM belongs to the process's own address space; ru_maxrss
    would also carry the parent's peak at fork time into a child started with fork + exec."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def peak_memory() -> dict:
    """This process's peak memory: the device's peak bytes in use on an accelerator, and the resident set."""
    jax = _setup_jax()
    device = jax.devices()[0]
    stats = device.memory_stats() if device.platform != "cpu" else None
    return {"peak_rss_bytes": _peak_rss_bytes(), "peak_device_bytes": stats and stats.get("peak_bytes_in_use")}


def _config(args, n_iters: int):
    from dit_jax.network import configs

    config = configs.get(args.config, "clean").replace(n_iters=n_iters, precision=args.precision)
    if args.dtype != "float32":
        config = config.replace(compute_dtype=args.dtype)
    return config


def _child(args) -> None:
    """Runs one (points, iterations, batch) in this (fresh) process and prints its record with its peak
    memory. FLOPs only for batch 1 (the parent scales them)."""
    record = time_register(
        _config(args, args.child_iters),
        args.child_batch,
        args.child,
        repeats=args.repeats,
        count_flops=args.child_flops,
    )
    record.update(peak_memory())
    print("RECORD " + json.dumps(record))


def _run_child(args, n_points: int, n_iters: int, batch: int = 1, flops: bool = False, repeats: int = 1) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--child",
        str(n_points),
        "--child-iters",
        str(n_iters),
        "--child-batch",
        str(batch),
        "--config",
        args.config,
        "--dtype",
        args.dtype,
        "--precision",
        args.precision,
        "--repeats",
        str(repeats),
    ] + (["--child-flops"] if flops else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    for line in proc.stdout.splitlines():
        if line.startswith("RECORD "):
            return json.loads(line[len("RECORD ") :])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"n_points": n_points, "n_iters": n_iters, "batch": batch, "error": " / ".join(tail)}


def _peak_gb(record: dict) -> float | None:
    value = record.get("peak_device_bytes") or record.get("peak_rss_bytes")
    return None if value is None else value / 2**30


def _gb(n: float | None) -> str:
    return "-" if n is None else f"{n / 2**30:.2f}"


def main() -> None:
    from dit_jax.network.configs import PRECISIONS

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="paper")
    parser.add_argument("--n-points", type=int, default=1000)
    parser.add_argument("--iters", type=int, nargs="+", default=[2, 3])
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="*", default=[512, 1024, 2048, 4096, 8192])
    parser.add_argument("--skip-batches", action="store_true", help="only the scaling sweep")
    parser.add_argument("--dtype", default="float32", choices=["float32", "bfloat16"])
    parser.add_argument("--precision", default="highest", choices=PRECISIONS)
    parser.add_argument("--json", default=None, help="also write the records here")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-iters", type=int, default=3, help=argparse.SUPPRESS)
    parser.add_argument("--child-batch", type=int, default=1, help=argparse.SUPPRESS)
    parser.add_argument("--child-flops", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        _child(args)
        return

    jax = _setup_jax()
    device = jax.devices()[0]
    report = {
        "date": datetime.date.today().isoformat(),
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "jax": jax.__version__,
        "device": device.device_kind,
        "platform": device.platform,
        "config": args.config,
        "dtype": args.dtype,
        "precision": args.precision,
    }
    report["matmul_peak_gflops"] = max(
        matmul_peak(2048, precision=args.precision), matmul_peak(4096, repeats=3, precision=args.precision)
    )
    print(
        f"{device.device_kind}: matmul peak {report['matmul_peak_gflops']:.0f} GFLOP/s ({args.precision})", flush=True
    )
    report["runs"] = []
    if not args.skip_batches:
        for n_iters in args.iters:
            per_pair_flops = None
            for batch in sorted(args.batches):
                record = _run_child(
                    args, args.n_points, n_iters, batch, flops=per_pair_flops is None, repeats=args.repeats
                )
                if "error" not in record:
                    if per_pair_flops is None:
                        per_pair_flops = record["flops_per_call"] / batch
                    record["flops_per_call"] = per_pair_flops * batch
                    record["gflops_per_s"] = record["flops_per_call"] / record["seconds_per_call"] / 1e9
                report["runs"].append(record)
                print(json.dumps({k: v for k, v in record.items() if k != "times_s"}), flush=True)
    report["scaling"] = []
    for n_points in args.sizes:
        record = _run_child(args, n_points, max(args.iters))
        report["scaling"].append(record)
        print(json.dumps({k: v for k, v in record.items() if k != "times_s"}), flush=True)

    peak = report["matmul_peak_gflops"]
    authors = args.config == "paper" and args.n_points == 1000
    lines = [
        f"Date {report['date']}; {report['device']} ({report['platform']}, {report['cpus']} CPUs); JAX "
        f'{report["jax"]}; config `{args.config}`, {args.dtype}, precision "{args.precision}". Matmul peak '
        f"probe: {peak:.0f} GFLOP/s.",
        "",
    ]
    if report["runs"]:
        header = "| points | iterations | batch | s / pair | pairs / s | peak memory GB | GFLOP / call | GFLOP/s | % of peak |"
        rule = "|---|---|---|---|---|---|---|---|---|"
        if authors:
            header += " authors' H100 s / pair |"
            rule += "---|"
        lines += [header, rule]
        for r in report["runs"]:
            if "error" in r:
                lines.append(f"| {r['n_points']} | {r['n_iters']} | {r['batch']} | failed: {r['error'][:80]} |")
                continue
            row = (
                f"| {r['n_points']} | {r['n_iters']} | {r['batch']} | {r['seconds_per_pair']:.4f} | "
                f"{r['pairs_per_s']:.2f} | {_peak_gb(r):.2f} | {r['flops_per_call'] / 1e9:.1f} | "
                f"{r['gflops_per_s']:.0f} | {100 * r['gflops_per_s'] / peak:.0f} % |"
            )
            if authors:
                theirs = AUTHORS_H100_S_PER_PAIR.get((r["n_iters"], r["batch"]))
                row += f" {theirs if theirs is not None else '-'} |"
            lines.append(row)
        if authors:
            lines.append(f"\nThe authors' peak memory at batch 1: {AUTHORS_H100_PEAK_GB_BATCH_1} GB (H100).")
        lines.append("")
    if report["scaling"]:
        lines += [
            "| points | iterations | s / pair | compile s | peak memory GB | XLA temp buffers GB |",
            "|---|---|---|---|---|---|",
        ]
        for r in report["scaling"]:
            if "error" in r:
                lines.append(f"| {r['n_points']} | {r['n_iters']} | failed: {r['error'][:80]} | | | |")
            else:
                lines.append(
                    f"| {r['n_points']} | {r['n_iters']} | {r['seconds_per_pair']:.2f} | "
                    f"{r['compile_s']:.1f} | {_peak_gb(r):.2f} | {_gb(r['xla_temp_bytes'])} |"
                )
    print("\n".join(lines))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report, f, indent=2)


if __name__ == "__main__":
    main()
