"""Plot the training curves of one or more runs into one PNG.

python tools/plot_training_curves.py OUT.png runs/a runs/b ... [--labels "seed 0" "seed 1" ...]
"""

import argparse

from dit_jax import training


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", help="PNG to write")
    parser.add_argument("workdirs", nargs="+", help="training workdirs (each with metrics.jsonl)")
    parser.add_argument("--labels", nargs="+", default=None, help="one per workdir (default: the workdirs)")
    parser.add_argument("--title", default=None)
    args = parser.parse_args(argv)
    labels = args.labels or args.workdirs
    if len(labels) != len(args.workdirs):
        parser.error(f"{len(labels)} labels for {len(args.workdirs)} workdirs")
    training.plot_curves(dict(zip(labels, args.workdirs)), args.out, args.title)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
