"""benchmarks/train_throughput.py's sorting of compiled operations by kind (``--by-part``'s ``by_kind_ms``)."""

import re
import sys

import jax
import jax.numpy as jnp
from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))
import train_throughput  # noqa: E402


def _kinds(fn, *args) -> set[str]:
    text = jax.jit(fn).lower(*args).compile().as_text()
    with_products = train_throughput._computations_with_products(text)
    entry = text[text.index("ENTRY") :]
    kinds = set()
    for line in entry.splitlines()[1:]:
        found = re.match(r"\s*(?:ROOT )?%?([\w.\-]+) = ", line)
        if found and " parameter(" not in line:
            kinds.add(train_throughput._operation_kind(found.group(1), line, with_products))
    return kinds


def test_products_elementwise_work_and_conversions_are_told_apart():
    a = jnp.ones((64, 32), jnp.float32)
    assert "products (fusions included)" in _kinds(lambda a, b: a @ b.T, a, a)
    assert _kinds(lambda a: jnp.exp(a) * 2.0, a) == {"elementwise and reductions"}
    assert _kinds(lambda a: (a * 3.0).astype(jnp.bfloat16), a) == {"conversions (fusions holding one)"}
