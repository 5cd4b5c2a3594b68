"""Weights from the authors' PyTorch state dict to dit-jax params, and back.

:func:`from_torch_state_dict` takes a ``{name: ndarray}`` mapping under the authors' names (as in the
``param/*`` entries of the reference check file) and returns the params tree of :class:`dit_jax.network.dit.DIT`.
PyTorch ``Linear`` weights (out, in) become Flax kernels (in, out). Tensors the authors' model holds but never
uses (``emb_nn.project``, ``attn.norm1`` inside the token transformers, ``head.temperature``, ``head.reflect``)
are dropped.

Command line (PyTorch is needed only for files saved before PyTorch 1.6)::

    python -m dit_jax.network.convert model.best.t7 OUT_DIR [--config paper] [--n-heads 4]

writes an orbax checkpoint of the converted params and the config, restorable with
:func:`dit_jax.network.checkpoint.restore`.
"""

from __future__ import annotations

import argparse
import pickle
import re
import sys
from collections.abc import Callable, Mapping
from typing import Any

import jax
import numpy as np
from flax import traverse_util

from dit_jax.network import configs, model, torch_pickle
from dit_jax.network.configs import DITConfig

UNUSED = (
    re.compile(r"emb_nn\.project\..*"),
    re.compile(r"emb_nn\.attention\d+\.attn\.norm1\..*"),
    re.compile(r"head\.(temperature|reflect)"),
)

_LINEAR_LEAF = {"weight": "kernel", "bias": "bias"}
_NORM_LEAF = {"weight": "scale", "bias": "bias"}
_LNSTAR_LEAF = {"a_2": "a_2", "b_2": "b_2"}
_QKVO = "qkvo"

# (pattern over the authors' name, function of the match to (our path, leaf kind))
_RULES: list[tuple[re.Pattern, Callable[[re.Match], tuple[tuple[str, ...], str]]]] = [
    (
        re.compile(r"emb_nn\.attention(\d+)\.(norm1|norm2)\.(weight|bias)"),
        lambda m: (("pse", f"attention{m[1]}", m[2], _NORM_LEAF[m[3]]), "norm"),
    ),
    (
        re.compile(r"emb_nn\.attention(\d+)\.attn\.(qkv|proj)\.(weight|bias)"),
        lambda m: (("pse", f"attention{m[1]}", m[2], _LINEAR_LEAF[m[3]]), m[3]),
    ),
    (
        re.compile(r"emb_nn\.attention(\d+)\.mlp\.(fc1|fc2)\.(weight|bias)"),
        lambda m: (("pse", f"attention{m[1]}", m[2], _LINEAR_LEAF[m[3]]), m[3]),
    ),
    (re.compile(r"emb_nn\.norm\.(weight|bias)"), lambda m: (("pse", "norm", _NORM_LEAF[m[1]]), "norm")),
    (
        re.compile(r"Position_encoding\.PE\.(0|2)\.(weight|bias)"),
        lambda m: (("positional_encoding", f"fc{m[1]}", _LINEAR_LEAF[m[2]]), m[2]),
    ),
    (
        re.compile(
            r"attention\.model\.(encoder|decoder)\.layers\.(\d+)\.(self_attn|src_attn)\.linears\.([0-3])\."
            r"(weight|bias)"
        ),
        lambda m: (("pft", m[1], f"layers_{m[2]}", m[3], _QKVO[int(m[4])], _LINEAR_LEAF[m[5]]), m[5]),
    ),
    (
        re.compile(r"attention\.model\.(encoder|decoder)\.layers\.(\d+)\.feed_forward\.(w_1|w_2)\.(weight|bias)"),
        lambda m: (("pft", m[1], f"layers_{m[2]}", "feed_forward", m[3], _LINEAR_LEAF[m[4]]), m[4]),
    ),
    (
        re.compile(r"attention\.model\.(encoder|decoder)\.layers\.(\d+)\.sublayer\.(\d)\.norm\.(a_2|b_2)"),
        lambda m: (("pft", m[1], f"layers_{m[2]}", f"norm{m[3]}", m[4]), "norm"),
    ),
    (
        re.compile(r"attention\.model\.(encoder|decoder)\.norm\.(a_2|b_2)"),
        lambda m: (("pft", m[1], "norm", m[2]), "norm"),
    ),
    (re.compile(r"SE_Block\.fc\.(0|2)\.weight"), lambda m: (("se", f"fc{m[1]}", "kernel"), "weight")),
    (
        re.compile(r"temp_net\.nn\.([0369])\.(weight|bias)"),
        lambda m: (("temp_net", f"fc{m[1]}", _LINEAR_LEAF[m[2]]), m[2]),
    ),
    (
        re.compile(r"temp_net\.nn\.([147])\.(weight|bias)"),
        lambda m: (("temp_net", f"norm{m[1]}", _NORM_LEAF[m[2]]), "norm"),
    ),
]


class ConversionError(ValueError):
    """The state dict does not fit the config: missing, unexpected or misshapen tensors."""


def _strip_prefix(name: str) -> str:
    # Checkpoints saved from nn.DataParallel prefix every name with "module.".
    return name[len("module.") :] if name.startswith("module.") else name


def _map_name(name: str) -> tuple[tuple[str, ...], str] | None:
    for pattern, target in _RULES:
        match = pattern.fullmatch(name)
        if match:
            return target(match)
    return None


#: The widths :func:`infer_config` reads: config field (or hidden width) -> (tensor, how many widths its first
#: axis stacks). The tokens' query, key and value share one tensor; the first norm's width is 3k.
_WIDTHS = {
    "emb_dims": ("emb_nn.norm.weight", 1),
    "token_dim": ("emb_nn.attention1.attn.qkv.weight", 3),
    "k": ("emb_nn.attention1.norm1.weight", 3),
    "ff_dims": ("attention.model.encoder.layers.0.feed_forward.w_1.weight", 1),
    "temp_hidden": ("temp_net.nn.0.weight", 1),
    "pe_hidden": ("Position_encoding.PE.0.weight", 1),
    "se_hidden": ("SE_Block.fc.0.weight", 1),
}


def infer_config(state_dict: Mapping[str, Any], **overrides: Any) -> DITConfig:
    """Reads the network's widths and depth off a state dict; heads cannot be read and come from
    ``overrides`` (default 4, as in the paper), as do the inference settings."""
    sd = {_strip_prefix(k): v for k, v in state_dict.items()}
    try:
        widths = {field: np.shape(sd[tensor])[0] // per for field, (tensor, per) in _WIDTHS.items()}
    except KeyError as err:
        raise ConversionError(f"not a DIT state dict: no tensor {err.args[0]!r}") from None
    layer = re.compile(r"attention\.model\.encoder\.layers\.(\d+)\.")
    widths["n_blocks"] = 1 + max(int(m[1]) for m in map(layer.match, sd) if m)
    # The two hidden widths are stored as ratios to the embedding width: expansion E*e, reduction E/r.
    widths["pe_expansion"] = widths.pop("pe_hidden") // widths["emb_dims"]
    widths["se_reduction"] = widths["emb_dims"] // widths.pop("se_hidden")
    return DITConfig(**{**widths, **overrides})


def from_torch_state_dict(state_dict: Mapping[str, Any], config: DITConfig) -> dict:
    """Converts the authors' state dict into params for ``config``.

    Args:
      state_dict: ``{name: array}`` under the authors' names (a ``module.`` prefix is accepted); values may be
        numpy arrays or anything ``np.asarray`` takes (CPU torch tensors included).
      config: the config the weights were trained with.

    Returns:
      The params tree (float32 numpy leaves), with exactly the structure and shapes of
      :func:`dit_jax.network.model.init` for ``config``.

    Raises:
      ConversionError: naming every unknown, missing or misshapen tensor.
    """
    flat: dict[tuple[str, ...], np.ndarray] = {}
    unknown = []
    for raw_name, value in state_dict.items():
        name = _strip_prefix(raw_name)
        if any(p.fullmatch(name) for p in UNUSED):
            continue
        mapped = _map_name(name)
        if mapped is None:
            unknown.append(name)
            continue
        path, kind = mapped
        array = np.asarray(value, dtype=np.float32)
        flat[path] = array.T if kind == "weight" else array

    expected = traverse_util.flatten_dict(jax.eval_shape(lambda: model.init(jax.random.key(0), config)))
    problems = []
    if unknown:
        problems.append("unknown tensors: " + ", ".join(sorted(unknown)))
    missing = sorted("/".join(p) for p in expected if p not in flat)
    if missing:
        problems.append("missing for this config: " + ", ".join(missing))
    extra = sorted("/".join(p) for p in flat if p not in expected)
    if extra:
        problems.append("not in this config (more blocks or layers than it has?): " + ", ".join(extra))
    for path, spec in expected.items():
        if path in flat and flat[path].shape != spec.shape:
            problems.append(f"{'/'.join(path)}: shape {flat[path].shape}, config needs {spec.shape}")
    if problems:
        raise ConversionError("state dict does not fit the config: " + "; ".join(problems))
    return traverse_util.unflatten_dict(flat)


def authors_names(config: DITConfig) -> list[str]:
    """Every tensor name the authors' state dict has for ``config`` that carries a used weight."""
    names = [f"emb_nn.norm.{leaf}" for leaf in ("weight", "bias")]
    for layer in range(1, configs.PSE_LAYERS + 1):
        base = f"emb_nn.attention{layer}."
        names += [base + "attn.qkv.weight", base + "attn.proj.weight", base + "attn.proj.bias"]
        names += [
            base + f"{mod}.{leaf}" for mod in ("norm1", "norm2", "mlp.fc1", "mlp.fc2") for leaf in ("weight", "bias")
        ]
    names += [f"Position_encoding.PE.{i}.{leaf}" for i in (0, 2) for leaf in ("weight", "bias")]
    for part, attns, n_norms in (("encoder", ("self_attn",), 2), ("decoder", ("self_attn", "src_attn"), 3)):
        for block in range(config.n_blocks):
            base = f"attention.model.{part}.layers.{block}."
            names += [
                base + f"{attn}.linears.{i}.{leaf}" for attn in attns for i in range(4) for leaf in ("weight", "bias")
            ]
            names += [base + f"feed_forward.{w}.{leaf}" for w in ("w_1", "w_2") for leaf in ("weight", "bias")]
            names += [base + f"sublayer.{j}.norm.{leaf}" for j in range(n_norms) for leaf in ("a_2", "b_2")]
        names += [f"attention.model.{part}.norm.{leaf}" for leaf in ("a_2", "b_2")]
    names += ["SE_Block.fc.0.weight", "SE_Block.fc.2.weight"]
    names += [f"temp_net.nn.{i}.{leaf}" for i in range(0, 10, 3) for leaf in ("weight", "bias")]
    names += [f"temp_net.nn.{i}.{leaf}" for i in (1, 4, 7) for leaf in ("weight", "bias")]
    return names


def to_torch_state_dict(params: Any, config: DITConfig) -> dict[str, np.ndarray]:
    """The inverse of :func:`from_torch_state_dict`: params to the authors' names and layouts.

    Only the used tensors are produced; the authors' unused ones are absent (PyTorch's
    ``load_state_dict(..., strict=False)`` takes the result).
    """
    flat = traverse_util.flatten_dict(params)
    out = {}
    for name in authors_names(config):
        path, kind = _map_name(name)
        array = np.asarray(flat[path], dtype=np.float32)
        out[name] = array.T if kind == "weight" else array
    return out


def load_pth(path: str) -> dict[str, np.ndarray]:
    """Reads a PyTorch checkpoint (a state dict, or a dict holding one under ``state_dict`` / ``model``).

    Zip-format files (PyTorch >= 1.6) are read without PyTorch (:mod:`dit_jax.network.torch_pickle`); older ones
    need the ``torch`` extra.
    """
    try:
        obj = torch_pickle.load(path)
    except torch_pickle.UnsupportedFile as err:
        try:
            import torch
        except ImportError:
            raise ConversionError(f"{err}; install the torch extra (pip install 'dit-jax[torch]') to read it") from None
        try:
            obj = _to_numpy(torch.load(path, map_location="cpu", weights_only=True))
        except Exception as torch_err:  # torch raises many types; the user needs the file and the reason
            reason = str(torch_err).strip().splitlines()[0] if str(torch_err).strip() else type(torch_err).__name__
            raise ConversionError(f"{path}: not a readable PyTorch checkpoint ({reason[:200]})") from None
    for key in ("state_dict", "model", "model_state_dict"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise ConversionError(f"{path}: expected a state dict, found {type(obj).__name__}")
    return {k: np.asarray(v) for k, v in obj.items() if isinstance(v, np.ndarray)}


def _to_numpy(obj):
    if isinstance(obj, dict):
        return {k: _to_numpy(v) for k, v in obj.items()}
    return obj.detach().cpu().numpy() if hasattr(obj, "detach") else obj


def main(argv: list[str] | None = None) -> int:
    """``dit-convert PTH OUT``: the authors' checkpoint as an orbax checkpoint; returns the exit status."""
    parser = argparse.ArgumentParser(prog="python -m dit_jax.network.convert", description=__doc__.split("\n\n")[0])
    parser.add_argument("pth", help="the authors' checkpoint (.pth / .t7 state dict)")
    parser.add_argument("out", help="directory for the orbax checkpoint (must not exist)")
    parser.add_argument(
        "--config",
        default=None,
        choices=sorted(configs.PRESETS),
        help="preset to check the weights against (default: read widths off the weights)",
    )
    parser.add_argument("--n-heads", type=int, default=4, help="PFT attention heads (not stored in weights)")
    parser.add_argument(
        "--setting",
        default="clean",
        choices=sorted(configs.GMCCE_THRESHOLDS),
        help="data setting whose GMCCE threshold the config gets",
    )
    args = parser.parse_args(argv)

    from dit_jax.network import checkpoint

    try:
        state_dict = load_pth(args.pth)
        threshold = configs.GMCCE_THRESHOLDS[args.setting]
        if args.config:
            config = configs.get(args.config, args.setting).replace(n_heads=args.n_heads)
        else:
            config = infer_config(state_dict, n_heads=args.n_heads, gmcce_threshold=threshold)
        params = from_torch_state_dict(state_dict, config)
        checkpoint.save(args.out, params, config)
    except (ValueError, OSError, pickle.UnpicklingError) as err:  # our errors are all ValueErrors
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({config})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
