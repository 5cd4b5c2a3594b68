"""What makes a release: calibrating a checkpoint's inference settings (:mod:`.calibrate`), shipping weights
(:mod:`.ship_weights`), tuning the baselines (:mod:`.tune_baselines`, :mod:`.compare_baseline_refinement`),
the embedded data and example pair (:mod:`.build_embedded_dataset`, :mod:`.make_example_pair`) and the
README's tables (:mod:`.readme_tables`).
Each runs as ``python -m dit_jax.release.NAME`` from the repository root; the first three have console
entry points too."""
