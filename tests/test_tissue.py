"""Tissue helpers: per-tet conductivity and per-tissue settings."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxhead import TISSUES, Tissue, sigma_per_tet
from jaxhead.tissue import per_tissue


class _Labels:
    labels = np.array([1, 2, 3, 4, 4, 1])


def test_sigma_per_tet_indexes_by_label_and_keeps_jax():
    s = np.array([0.3, 1.79, 0.018, 0.44])
    np.testing.assert_array_equal(sigma_per_tet(_Labels, s), s[_Labels.labels - 1])
    assert isinstance(sigma_per_tet(_Labels, jnp.asarray(s)), jax.Array)
    by_name = sigma_per_tet(_Labels, {"brain": 0.3, "csf": 1.79, "skull": 0.018, "scalp": 0.44})
    np.testing.assert_array_equal(by_name, s[_Labels.labels - 1])
    # differentiable: d sum(sigma_tet) / d sigma counts each tissue's tets
    g = jax.grad(lambda x: jnp.sum(sigma_per_tet(_Labels, x)))(jnp.asarray(s))
    np.testing.assert_array_equal(np.asarray(g), [2, 1, 1, 2])
    per_tet = np.arange(6.0)
    assert sigma_per_tet(_Labels, per_tet) is not None and np.all(sigma_per_tet(_Labels, per_tet) == per_tet)
    with pytest.raises(ValueError, match="shape"):
        sigma_per_tet(_Labels, np.ones(3))
    with pytest.raises(ValueError, match="no value for"):
        sigma_per_tet(_Labels, {"brain": 1.0})


def test_per_tissue_parses_and_names_the_problem():
    assert per_tissue(2.0, "x") == {t: 2.0 for t in TISSUES}
    assert per_tissue({"brain": 1, "CSF": 2, Tissue.SKULL: 3, 4: 4}, "x") == dict(zip(TISSUES, [1.0, 2.0, 3.0, 4.0]))
    shells = (Tissue.CSF, Tissue.SKULL, Tissue.SCALP)
    assert per_tissue({"csf": 1.0}, "t", allowed=shells, allow_none=True) == {
        Tissue.CSF: 1.0, Tissue.SKULL: None, Tissue.SCALP: None}
    assert per_tissue(0.0, "r", positive=False)[Tissue.BRAIN] == 0.0
    for bad, match in [({"brain": 1}, "lacks"), ({"bone": 1}, "unknown tissue"), (-1.0, "positive"),
                       (float("nan"), "positive"), (True, "positive"), (None, "is None"),
                       ({"brain": 1.0}, "lacks")]:
        with pytest.raises(ValueError, match=match):
            per_tissue(bad, "edge_mm")
    with pytest.raises(ValueError, match="allowed keys"):
        per_tissue({"brain": 1.0}, "t", allowed=shells, allow_none=True)
