"""dit_jax.pipeline.sampling: the checks every cloud passes before the pipeline takes it."""

import numpy as np
import pytest

from dit_jax.pipeline import sampling


def test_a_cloud_in_any_unit_passes_the_checks_and_one_beyond_float64_is_named():
    """The same-point and one-line checks are relative: a cloud a millionth of a micrometre across passes; one
    whose squared lengths would overflow float64 is refused with its name, never a LinAlgError. One point
    reads as one point."""
    cloud = np.random.default_rng(0).normal(size=(50, 3))
    for scale in (1e-12, 1.0, 1e12):
        np.testing.assert_array_equal(sampling.check_cloud("source", cloud * scale, 3), cloud * scale)
    with pytest.raises(sampling.InputError, match="^target: coordinates up to"):
        sampling.check_cloud("target", cloud * 1e155, 3)
    with pytest.raises(sampling.InputError, match="^source: 1 point;"):
        sampling.check_cloud("source", cloud[:1], 3)
    with pytest.raises(sampling.InputError, match="same point"):
        sampling.check_cloud("source", np.full((10, 3), 1e-12), 3)
