"""Small building blocks shared by PSE, PFT and the temperature net."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from flax import linen as nn


def dot_precision(name: str) -> jax.lax.Precision:
    """``jax.lax.Precision`` of a :attr:`dit_jax.network.configs.DITConfig.precision` setting.

    Passed explicitly to every product, it overrides JAX's global default (TF32 on NVIDIA GPUs): "highest"
    is float32 on every backend, "tf32" ``Precision.HIGH`` (TensorFloat-32 on GPUs, three bfloat16 passes
    on TPUs, float32 on CPUs), "bfloat16" ``Precision.DEFAULT`` on operands rounded to bfloat16 (see
    :func:`dot_general`).
    """
    if name == "highest":
        return jax.lax.Precision.HIGHEST
    if name == "tf32":
        return jax.lax.Precision.HIGH
    if name == "bfloat16":
        return jax.lax.Precision.DEFAULT
    raise ValueError(f"unknown precision {name!r}; choose highest, tf32 or bfloat16")


def _operands(name: str, *arrays: jax.Array) -> tuple[tuple[jax.Array, ...], jnp.dtype | None, jax.lax.Precision]:
    """The operands as the setting multiplies them, the result type to ask for, and the precision: "bfloat16"
    rounds float32 operands to bfloat16 and accumulates in float32, on every backend alike. (XLA's bfloat16
    dot algorithm, ``DotAlgorithmPreset.BF16_BF16_F32``, is refused by its CPU backend for some shapes.)
    A product with a vector operand (the squeeze-and-excitation gate's) stays float32: it has no speed to
    gain, and XLA's CPU backend runs the outer product of its gradient in bfloat16 a hundred times slower
    (docs/benchmarks.md)."""
    if name != "bfloat16":
        return arrays, None, dot_precision(name)
    if min(a.ndim for a in arrays) < 2:
        return arrays, None, jax.lax.Precision.HIGHEST
    return tuple(a.astype(jnp.bfloat16) for a in arrays), jnp.float32, dot_precision(name)


def dot_general(name: str):
    """``jax.lax.dot_general`` computed as the precision setting ``name`` says, for ``nn.Dense(dot_general=)``;
    the precision the caller passes is replaced."""

    def dot(lhs, rhs, dimension_numbers, precision=None, preferred_element_type=None, **kwargs):
        del precision
        (lhs, rhs), wanted, chosen = _operands(name, lhs, rhs)
        return jax.lax.dot_general(
            lhs,
            rhs,
            dimension_numbers,
            precision=chosen,
            preferred_element_type=wanted or preferred_element_type,
            **kwargs,
        )

    return dot


def einsum(subscripts: str, a: jax.Array, b: jax.Array, *, precision: str, preferred_element_type=None) -> jax.Array:
    """``jnp.einsum`` of two operands computed as the precision setting says (see :func:`dot_precision`)."""
    (a, b), wanted, chosen = _operands(precision, a, b)
    return jnp.einsum(subscripts, a, b, precision=chosen, preferred_element_type=wanted or preferred_element_type)


def _row_blocks(x: jax.Array, rows: int) -> jax.Array:
    """(h, N, d) -> (ceil(N / rows), h, rows, d), the last block padded with zero rows."""
    heads, n, width = x.shape
    x = jnp.pad(x, ((0, 0), (0, -n % rows), (0, 0)))
    return jnp.moveaxis(x.reshape(heads, -1, rows, width), 1, 0)


def _from_row_blocks(x: jax.Array, n: int) -> jax.Array:
    """The inverse of :func:`_row_blocks`: (B, h, rows, d) -> (h, N, d)."""
    blocks, heads, rows, width = x.shape
    return jnp.moveaxis(x, 0, 1).reshape(heads, blocks * rows, width)[:, :n]


def _attention_forward(q, k, v, rows: int, precision: str):
    """Heads-first attention q (h, N, d), k (h, M, d), v (h, M, e) -> out (h, N, e) and the logits'
    log-sum-exp (h, N), ``rows`` query rows at a time. ``q`` comes already divided by the divisor."""
    low = q.dtype != jnp.float32

    def block(_, q_rows):
        logits = einsum(
            "hnd,hmd->hnm", q_rows, k, precision=precision, preferred_element_type=jnp.float32 if low else None
        )
        peak = jnp.max(logits, axis=-1, keepdims=True)
        weights = jnp.exp(logits - peak)
        total = jnp.sum(weights, axis=-1, keepdims=True)
        out = (
            einsum(
                "hnm,hmd->hnd",
                weights.astype(v.dtype),
                v,
                precision=precision,
                preferred_element_type=jnp.float32 if low else None,
            )
            / total
        )
        return None, (out.astype(v.dtype), (peak + jnp.log(total))[..., 0])

    n = q.shape[1]
    if rows >= n:
        _, (out, lse) = block(None, q)
        return out, lse
    _, (out, lse) = jax.lax.scan(block, None, _row_blocks(q, rows))
    return _from_row_blocks(out, n), _from_row_blocks(lse[..., None], n)[..., 0]


@functools.partial(jax.custom_vjp, nondiff_argnums=(3, 4))
def _attention(q, k, v, rows: int, precision: str):
    return _attention_forward(q, k, v, rows, precision)[0]


def _attention_fwd(q, k, v, rows, precision):
    out, lse = _attention_forward(q, k, v, rows, precision)
    return out, (q, k, v, out, lse)


def _attention_bwd(rows, precision, residuals, d_out):
    # The softmax is recomputed from the saved log-sum-exp instead of stored: the (h, N, M) weights, the
    # largest arrays of the network, are never kept between the passes.
    q, k, v, out, lse = residuals
    f32 = lambda a: a.astype(jnp.float32)
    d_out = f32(d_out)
    row_dot = jnp.sum(d_out * f32(out), axis=-1)  # (h, N): sum_e dO * O, the softmax's own term

    def block(carry, xs):
        # Key-major, (h, M, n): the products for d_k and d_v then contract the arrays' last axis, which
        # XLA's CPU backend runs several times faster than a contraction over their first.
        d_k, d_v = carry
        q_rows, d_out_rows, lse_rows, row_dot_rows = xs
        logits = einsum("hmd,hnd->hmn", k, q_rows, precision=precision, preferred_element_type=jnp.float32)
        weights = jnp.exp(logits - lse_rows[:, None, :])
        d_v = d_v + einsum("hmn,hne->hme", weights, d_out_rows, precision=precision)
        d_weights = einsum("hme,hne->hmn", f32(v), d_out_rows, precision=precision)
        d_logits = weights * (d_weights - row_dot_rows[:, None, :])
        d_k = d_k + einsum("hmn,hnd->hmd", d_logits, f32(q_rows), precision=precision)
        d_q = einsum("hnm,hmd->hnd", jnp.swapaxes(d_logits, 1, 2), f32(k), precision=precision)
        return (d_k, d_v), d_q

    start = (jnp.zeros(k.shape, jnp.float32), jnp.zeros(v.shape, jnp.float32))
    n = q.shape[1]
    if rows >= n:
        (d_k, d_v), d_q = block(start, (q, d_out, lse, row_dot))
    else:
        # Padded rows have zero cotangents, so they add nothing to d_k and d_v.
        xs = (
            _row_blocks(q, rows),
            _row_blocks(d_out, rows),
            _row_blocks(lse[..., None], rows)[..., 0],
            _row_blocks(row_dot[..., None], rows)[..., 0],
        )
        (d_k, d_v), d_q = jax.lax.scan(block, start, xs)
        d_q = _from_row_blocks(d_q, n)
    return d_q.astype(q.dtype), d_k.astype(k.dtype), d_v.astype(v.dtype)


_attention.defvjp(_attention_fwd, _attention_bwd)


def attention(
    q: jax.Array, k: jax.Array, v: jax.Array, divisor: float | None = None, chunk: int = 0, *, precision: str
) -> jax.Array:
    """softmax(q k^T / divisor) v for each head: q (N, h, d), k (M, h, d), v (M, h, d_v) -> (N, h, d_v).

    ``divisor`` is a Python number (a constant of the program); it divides ``q`` before the product, which
    spares a pass over the (h, N, M) logits in each direction (the same logits to float rounding).

    The products run heads-first, (h, N, d) x (h, M, d), which XLA's CPU backend runs faster than the
    points-first layout. The backward pass is written out (as in FlashAttention): it keeps q, k, v, the
    output and each row's log-sum-exp, and recomputes the (h, N, M) softmax weights instead of storing them,
    which cuts the memory traffic of PSE's narrow heads. With ``0 < chunk < N`` the query rows go ``chunk``
    at a time in both passes (rows are independent, so the result is the same): the (h, N, M) logits never
    exist at once, and memory grows linearly in N instead of N M. Low-precision (bfloat16) inputs multiply
    in their precision, while the logits and the softmax stay float32. ``precision``: see
    :func:`dot_precision`.
    """
    rows = q.shape[0] if chunk <= 0 else min(chunk, q.shape[0])
    if divisor is not None:
        q = q * jnp.asarray(1.0 / divisor, q.dtype)
    heads_first = lambda a: jnp.swapaxes(a, 0, 1)
    return heads_first(_attention(heads_first(q), heads_first(k), heads_first(v), rows, precision))


def stack_of_layers(
    parent: nn.Module,
    template: nn.Module,
    names: Sequence[str],
    x: jax.Array,
    call: Callable[[nn.Module, jax.Array], jax.Array],
    *,
    remat: bool = False,
    dropout: bool = False,
    collect: bool = False,
) -> tuple[jax.Array, jax.Array | None]:
    """Layers of one structure and shape applied in turn, ``x = call(layer, x)``, as one ``lax.scan``.

    Each layer keeps its parameters under its own name in ``parent`` (``names``), as if it were a separate
    submodule; the scan runs over them stacked along a new leading axis, so a compiled program holds one copy
    of the layer however many there are (compilation and tracing time grow with the program, not the
    arithmetic). At initialisation the layers run one by one, so each draws its parameters exactly as a
    separately called submodule would.

    Args:
      parent: the module that owns the layers' parameters; call from its compact method.
      template: an unbound layer (``parent=None``) with the layers' attributes.
      names: the layers' names, in the order they apply.
      x: the input of the first layer.
      call: ``call(layer, x)`` runs one layer on its input, e.g. ``lambda layer, x: layer(x, memory)``;
        closures over other arrays are fine.
      remat: rematerialise each layer in the backward pass (``jax.checkpoint`` around the scan's body).
      dropout: each layer gets its own key of the ``dropout`` stream (``parent.make_rng``, folded with the
        layer's index).
      collect: also return every layer's output, stacked (L, ...).

    Returns:
      The last layer's output, and the stacked outputs where ``collect`` (else None).
    """
    if parent.is_initializing():
        outputs = []
        for name in names:
            x = call(template.clone(parent=parent, name=name), x)
            outputs.append(x)
        return x, (jnp.stack(outputs) if collect else None)
    params = parent.variables["params"]
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *(params[name] for name in names))
    key = parent.make_rng("dropout") if dropout else None

    def body(carry, layer):
        layer_params, index = layer
        rngs = {} if key is None else {"dropout": jax.random.fold_in(key, index)}
        out = template.apply({"params": layer_params}, carry, method=call, rngs=rngs)
        return out, (out if collect else None)

    if remat:
        body = jax.checkpoint(body)
    x, outputs = jax.lax.scan(body, x, (stacked, jnp.arange(len(names))))
    return x, outputs


def layer_norm(name: str, eps: float = 1e-5) -> nn.LayerNorm:
    """PyTorch's ``nn.LayerNorm``: biased variance, ``eps`` inside the square root, scale and bias.

    Flax's fast variance (E[x^2] - E[x]^2) loses digits when the mean is large; the two-pass form matches
    PyTorch to float rounding.
    """
    return nn.LayerNorm(epsilon=eps, use_fast_variance=False, name=name)


class AnnotatedLayerNorm(nn.Module):
    """LN* of the authors' PFT (docs/network.md, section 4): ``a_2 (x - mean) / (std + eps) + b_2``.

    ``std`` is the unbiased (n - 1) standard deviation and ``eps`` (1e-6) is added to it, not to the
    variance: both differ from a standard LayerNorm and both matter for matching their numbers.
    """

    eps: float = 1e-6

    @nn.compact
    def __call__(self, x: jax.Array) -> jax.Array:
        width = x.shape[-1]
        scale = self.param("a_2", nn.initializers.ones, (width,), jnp.float32)
        bias = self.param("b_2", nn.initializers.zeros, (width,), jnp.float32)
        mean = jnp.mean(x, axis=-1, keepdims=True)
        centred = x - mean
        std = jnp.sqrt(jnp.sum(centred * centred, axis=-1, keepdims=True) / (width - 1))
        return scale * centred / (std + self.eps) + bias


def torch_dense(features: int, name: str, use_bias: bool = True, dtype: str = "float32", *, precision: str) -> nn.Dense:
    """A Dense layer whose kernel starts like PyTorch's ``nn.Linear`` weight: U(+-1/sqrt(fan_in)).

    (variance scaling 1/3 with a uniform law has exactly that bound.) Biases start at zero. Kernels are
    stored (in, out), the transpose of PyTorch's (out, in). ``dtype`` is the computation's (the parameters
    stay float32); "bfloat16" gives bfloat16 outputs. ``precision``: see :func:`dot_precision`.
    """
    return nn.Dense(
        features,
        use_bias=use_bias,
        dtype=None if dtype == "float32" else jnp.dtype(dtype),
        dot_general=dot_general(precision),
        kernel_init=nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform"),
        name=name,
    )


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2))
def clip_inward(x: jax.Array, lower: float, upper: float) -> jax.Array:
    """``jnp.clip(x, lower, upper)`` whose gradient does not die outside the range.

    The value is exactly the clip's. The cotangent passes where ``x`` lies in the range, as with the clip,
    and also where it lies outside and a descent step (against the cotangent) moves ``x`` back towards the
    range; it is zero only where descent would push ``x`` further out. A plain clip passes nothing outside
    the range, so a value that starts or lands there never learns its way back: DIT's temperature net
    often starts below its lower bound, and its soft correspondences then stayed uniform (see
    :class:`dit_jax.network.head.TemperatureNet`).
    """
    return jnp.clip(x, lower, upper)


def _clip_inward_fwd(x, lower, upper):
    return jnp.clip(x, lower, upper), x


def _clip_inward_bwd(lower, upper, x, cotangent):
    # Descent moves x by -cotangent: below the range that raises x when the cotangent is negative.
    passes = ((x >= lower) & (x <= upper)) | ((x < lower) & (cotangent < 0)) | ((x > upper) & (cotangent > 0))
    return (jnp.where(passes, cotangent, jnp.zeros_like(cotangent)),)


clip_inward.defvjp(_clip_inward_fwd, _clip_inward_bwd)
