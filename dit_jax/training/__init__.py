"""Training DIT (optax, orbax checkpoints, data parallelism over a device mesh, resumable), and the learned
descriptor of room scans.

The package's modules, one job each: :mod:`~dit_jax.training.config` (the recipe), :mod:`~dit_jax.training.step`
(optimiser, loss and gradients, the device mesh), :mod:`~dit_jax.training.precision` (the step's precision
on this machine, for ``train_precision="auto"``), :mod:`~dit_jax.training.validation` (the run's pairs and
their validation), :mod:`~dit_jax.training.checkpoints` (orbax checkpoints and the exported model),
:mod:`~dit_jax.training.curves` (logged metrics and plots) and :mod:`~dit_jax.training.loop` (:func:`train`).
Everything is importable from ``dit_jax.training`` itself. The learned descriptor of room scans trains apart:
:mod:`~dit_jax.training.descriptor` (its recipe, loss and loop) and :mod:`~dit_jax.training.descriptor_data`
(keypoints of real rooms with the benchmark's truth, and its batches).

:func:`train` is the whole job behind ``python train.py``. Its pieces are usable on their own:
:func:`make_optimizer`, :func:`init_state`, :func:`make_train_step` (a jitted, sharded step that skips
non-finite updates) and :func:`validate`.
"""

from dit_jax.training.checkpoints import (  # noqa: F401
    TrainCheckpointError,
    export_params,
)
from dit_jax.training.config import (  # noqa: F401
    TrainConfig,
    load_config,
    recipe_from_config_dict,
    recipe_from_json,
)
from dit_jax.training.curves import (  # noqa: F401
    plot_curves,
    read_metrics,
)
from dit_jax.training.loop import (  # noqa: F401
    train,
)
from dit_jax.training.step import (  # noqa: F401
    TrainState,
    batch_loss_and_grads,
    init_state,
    initialize_distributed,
    is_primary,
    lr_schedule,
    make_mesh,
    make_optimizer,
    make_train_step,
    replicate,
    shard_batch,
)
from dit_jax.training.validation import (  # noqa: F401
    make_datasets,
    split_validation,
    validate,
    validation_batches,
)
