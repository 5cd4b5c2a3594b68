"""Model configurations as plain, typed, immutable values.

A :class:`DITConfig` fully determines the network's shapes and the inference procedure. It is hashable, so it
can be passed to ``jax.jit`` as a static argument. Presets:

* :func:`paper` -- the configuration of the paper and the authors' released model.
* :func:`cpu` -- a narrower, shallower network that trains in reasonable time on a laptop CPU.
* :func:`tiny` -- the smallest sensible network, for tests.

GMCCE thresholds per data setting (docs/network.md, section 9) are in :data:`GMCCE_THRESHOLDS`.
"""

from __future__ import annotations

import ast
import dataclasses
from collections.abc import Mapping
from typing import Any

#: The authors' evaluation thresholds tau of GMCCE for each data setting.
GMCCE_THRESHOLDS: Mapping[str, float] = {
    "clean": 0.99,
    "low_noise_partial": 0.9,
    "high_noise_partial": 0.6,
    # Settings whose clouds share no point (dit_jax.data.pairs): triangles keep their side lengths only
    # roughly there, so the loosest of the authors' thresholds.
    "independent_clean": 0.6,
    "independent_low_noise_partial": 0.6,
    "independent_high_noise_partial": 0.6,
    "scan_low_noise": 0.6,
    "scan_high_noise": 0.6,
}

#: The settings of :attr:`DITConfig.precision`, the network's matrix products
#: (:func:`dit_jax.network.layers.dot_precision` turns one into what ``jax.lax.dot_general`` takes).
PRECISIONS = ("highest", "tf32", "bfloat16")

#: Number of token-transformer layers in PSE; the embedding width is this many tokens wide.
PSE_LAYERS = 8


class Record:
    """What the frozen settings dataclasses share: copies with changes, and a JSON-able dict both ways."""

    def replace(self, **changes: Any):
        """Returns a copy with ``changes`` applied (and validated)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]):
        """The record from :meth:`to_dict`'s output; an unknown field is an error."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown {cls.__name__} fields: {', '.join(unknown)}")
        return cls(**values)


@dataclasses.dataclass(frozen=True)
class DITConfig(Record):
    """Everything that shapes DIT and its iterative inference.

    Attributes:
      emb_dims: E, the feature width. Must equal ``PSE_LAYERS * token_dim`` (8 T).
      token_dim: T, the width of each PSE token.
      n_blocks: encoder layers and decoder layers of PFT (each).
      ff_dims: hidden width of PFT's feed-forward layers.
      n_heads: attention heads in PFT (PSE always uses 4).
      k: neighbours of the LFI graph in PSE.
      n_iters: registration iterations at inference; GMCCE from the second on.
      gmcce_k: k_s, neighbours forming GMCCE's triangles.
      gmcce_sharpness: lambda of GMCCE's confidence 2 sigmoid(-lambda E).
      gmcce_threshold: tau; a correspondence is an inlier iff its confidence exceeds it.
      gmcce_min_dist2: squared distance below which a point is no GMCCE triangle vertex of another.
      gmcce_min_keep: GMCCE also keeps this share of the matches, the most confident ones, whatever the
        threshold (0: the authors' rule; see :func:`dit_jax.network.gmcce.weights`).
      guard_iterations: an iteration after the first keeps its update only if the update brings the source no
        farther from the target (:func:`dit_jax.geometry.rigid.alignment_cost` within ``fitness_radius``);
        otherwise the estimate stays as it was. False: the authors' iterations.
      fitness_radius: the radius of the fitness (:func:`dit_jax.geometry.rigid.fitness`, which the verdict uses)
        and of the guard's cost, in units of the target's median nearest-neighbour spacing.
      temp_factor: the temperature is clamped to [1 / temp_factor, temp_factor].
      pse_heads: attention heads of the PSE token transformers.
      se_reduction: channel reduction of the squeeze-and-excitation block.
      temp_hidden: hidden width of the temperature net.
      pe_expansion: the positional encoding's hidden width is ``pe_expansion * emb_dims``.
      dropout: dropout after PFT's feed-forward activation in training (the authors use 0.2).
      attention_chunk: attention over more query points than this runs in blocks of this many rows (same
        result, memory linear in N; see :func:`dit_jax.network.layers.attention`); 0 never splits.
      compute_dtype: "float32" (the default, the authors' numbers) or "bfloat16": PFT's matrix products in
        bfloat16 with float32 parameters, logits, softmax, norms and residuals (accuracy: docs/benchmarks.md).
      precision: how every matrix product of the network (PSE, PFT, SE, temperature net, similarity) is
        computed, in inference and training alike, whatever JAX's global ``jax_default_matmul_precision``
        says: "highest" (the default: float32 products on every backend, the numbers reference_check
        verifies), or the explicit opt-ins "tf32" (``lax.Precision.HIGH``: TensorFloat-32 on NVIDIA GPUs,
        three bfloat16 passes on TPUs) and "bfloat16" (bfloat16 operands with float32 accumulation; products
        with a vector operand, the squeeze-and-excitation gate's and the temperature net's, stay float32). JAX's
        own default on NVIDIA GPUs is TF32, which moves the reference check's scores (docs/benchmarks.md).
        The geometry (Procrustes, transforms, soft targets, losses and metrics) always multiplies at "highest".
      remat: rematerialise every PSE layer and PFT block in the backward pass (``jax.checkpoint``): training
        keeps only each block's input and recomputes the rest, with the same gradients. Inference is
        unaffected. Off by default: on a CPU it saves no peak memory and costs time (docs/benchmarks.md); it
        is for accelerators short of memory.
    """

    emb_dims: int = 512
    token_dim: int = 64
    n_blocks: int = 12
    ff_dims: int = 1024
    n_heads: int = 4
    k: int = 20
    n_iters: int = 3
    gmcce_k: int = 10
    gmcce_sharpness: float = 30.0
    gmcce_threshold: float = 0.99
    gmcce_min_dist2: float = 0.1
    gmcce_min_keep: float = 0.0
    fitness_radius: float = 2.0
    temp_factor: float = 100.0
    pse_heads: int = 4
    se_reduction: int = 16
    temp_hidden: int = 128
    pe_expansion: int = 8
    dropout: float = 0.2
    attention_chunk: int = 512
    guard_iterations: bool = False
    compute_dtype: str = "float32"
    precision: str = "highest"
    remat: bool = False

    def __post_init__(self):
        problems = []
        if self.emb_dims != PSE_LAYERS * self.token_dim:
            problems.append(f"emb_dims ({self.emb_dims}) must be {PSE_LAYERS} * token_dim ({self.token_dim})")
        if self.emb_dims % self.n_heads:
            problems.append(f"emb_dims ({self.emb_dims}) must be divisible by n_heads ({self.n_heads})")
        if self.token_dim % self.pse_heads:
            problems.append(f"token_dim ({self.token_dim}) must be divisible by pse_heads ({self.pse_heads})")
        if self.emb_dims < self.se_reduction:
            problems.append(f"emb_dims ({self.emb_dims}) must be at least se_reduction ({self.se_reduction})")
        for name in ("n_blocks", "ff_dims", "k", "n_iters", "gmcce_k", "temp_hidden"):
            if getattr(self, name) < 1:
                problems.append(f"{name} must be positive, got {getattr(self, name)}")
        if self.gmcce_k < 2:
            problems.append("gmcce_k must be at least 2 (a triangle needs two neighbours)")
        if not self.temp_factor >= 1.0:
            problems.append(f"temp_factor must be >= 1, got {self.temp_factor}")
        if self.compute_dtype not in ("float32", "bfloat16"):
            problems.append(f"compute_dtype must be 'float32' or 'bfloat16', got {self.compute_dtype!r}")
        if self.precision not in PRECISIONS:
            problems.append(f"precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        if not 0.0 <= self.gmcce_min_keep <= 1.0:
            problems.append(f"gmcce_min_keep must be in [0, 1], got {self.gmcce_min_keep}")
        if not self.fitness_radius > 0:
            problems.append(f"fitness_radius must be positive, got {self.fitness_radius}")
        if self.attention_chunk < 0:
            problems.append(f"attention_chunk must be >= 0, got {self.attention_chunk}")
        if problems:
            raise ValueError("invalid DITConfig: " + "; ".join(problems))

    @property
    def min_points(self) -> int:
        """The fewest points per cloud this network accepts: the kNN graph needs k of them, GMCCE k_s + 1."""
        return max(self.k, self.gmcce_k + 1, 3)


def paper(setting: str = "clean") -> DITConfig:
    """The paper's network: E 512, T 64, 12 blocks, FF 1024, 4 heads, k 20, 3 iterations."""
    return DITConfig(gmcce_threshold=GMCCE_THRESHOLDS[setting])


def cpu(setting: str = "clean") -> DITConfig:
    """A network small enough to train on a CPU in hours: E 128, 2 blocks."""
    return DITConfig(emb_dims=128, token_dim=16, n_blocks=2, ff_dims=256, gmcce_threshold=GMCCE_THRESHOLDS[setting])


def tiny(setting: str = "clean") -> DITConfig:
    """The smallest useful network, for tests: E 32, 1 block, k 8."""
    return DITConfig(
        emb_dims=32, token_dim=4, n_blocks=1, ff_dims=32, k=8, temp_hidden=16, gmcce_threshold=GMCCE_THRESHOLDS[setting]
    )


PRESETS = {"paper": paper, "cpu": cpu, "tiny": tiny}


def get(name: str, setting: str = "clean") -> DITConfig:
    """Returns the preset ``name`` for a data ``setting`` (see :data:`GMCCE_THRESHOLDS`)."""
    if name not in PRESETS:
        raise ValueError(f"unknown config {name!r}; choose one of {', '.join(PRESETS)}")
    if setting not in GMCCE_THRESHOLDS:
        raise ValueError(f"unknown setting {setting!r}; choose one of {', '.join(GMCCE_THRESHOLDS)}")
    return PRESETS[name](setting)


# The authors' argument names (as in the check file's `config`) and ours.
_AUTHORS_NAMES = {
    "n_emb_dims": "emb_dims",
    "token_dim": "token_dim",
    "n_blocks": "n_blocks",
    "n_ff_dims": "ff_dims",
    "n_heads": "n_heads",
    "k": "k",
    "gmcce_k": "gmcce_k",
    "gmcce_sharpness": "gmcce_sharpness",
    "gmcce_threshold": "gmcce_threshold",
    "temp_factor": "temp_factor",
    "n_iters": "n_iters",
}


def from_authors(values: Mapping[str, Any] | str, **overrides: Any) -> DITConfig:
    """Builds a config from the authors' argument names (a mapping or its Python literal).

    Keys that describe data rather than the network (such as ``n_points``) are ignored.
    """
    if isinstance(values, str):
        values = ast.literal_eval(values)
    mapped = {ours: values[theirs] for theirs, ours in _AUTHORS_NAMES.items() if theirs in values}
    mapped.update(overrides)
    return DITConfig(**mapped)
