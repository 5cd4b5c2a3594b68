"""dit-jax: DIT (Deep Interaction Transformer) point-cloud registration in JAX/Flax.

Quick use::

    import jax, dit_jax
    config = dit_jax.configs.tiny()
    params = dit_jax.init(jax.random.key(0), config)
    R, t, extras = dit_jax.register(params, src, tgt, config)   # src (B, N, 3), tgt (B, M, 3)
"""

from dit_jax import configs
from dit_jax.configs import DITConfig
from dit_jax.model import features, forward, init, register

__all__ = ["DITConfig", "configs", "features", "forward", "init", "register"]
__version__ = "0.1.0"
