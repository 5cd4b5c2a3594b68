"""dit-jax: DIT (Deep Interaction Transformer) point-cloud registration in JAX/Flax.

Quick use::

    from dit_jax import io, registration
    result = registration.load().register(io.read("a.ply"), io.read("b.ply"))   # result.matrix, result.level

    import jax, dit_jax                                # the network alone, one pure jittable function
    config = dit_jax.configs.tiny()
    params = dit_jax.init(jax.random.key(0), config)
    R, t, extras = dit_jax.register(params, src, tgt, config)   # src (B, N, 3), tgt (B, M, 3)

The folders, in layers (each imports only the rows above it; docs/implementation.md, "The package map"):

    geometry, io                          classical geometry; point-cloud files
    network, features, pictures, data     the paper's network and its weights; local features; figures and
                                          pages; datasets
    pipeline                              registration: load(), the Registrar, its stages, the verdict
    scenes                                many scans: series and scenes
    evaluators, cli                       evaluate.py's tables; the console commands
    training                              python train.py

The names below are imported on first use (PEP 562), so that ``import dit_jax.io`` or ``dit-register --help``
does not pay for importing JAX.
"""

import importlib

#: Public name -> (module, attribute or None for the module itself).
_EXPORTS = {
    "configs": ("dit_jax.network.configs", None),
    "DITConfig": ("dit_jax.network.configs", "DITConfig"),
    "forward": ("dit_jax.network.model", "forward"),
    "init": ("dit_jax.network.model", "init"),
    "register": ("dit_jax.network.model", "register"),
    "registration": ("dit_jax.pipeline.registration", None),
}

__all__ = list(_EXPORTS)
__version__ = "0.1.0"


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'dit_jax' has no attribute {name!r}")
    module_name, attribute = _EXPORTS[name]
    module = importlib.import_module(module_name)
    value = module if attribute is None else getattr(module, attribute)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))
