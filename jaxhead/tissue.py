"""Tissue classes and their default low-frequency conductivities."""

from collections.abc import Mapping
from enum import IntEnum

import jax
import jax.numpy as jnp

import numpy as np


class Tissue(IntEnum):
    """The four layers of the seed paper, inside out, plus background (air)."""

    BACKGROUND = 0
    BRAIN = 1
    CSF = 2
    SKULL = 3
    SCALP = 4

    @classmethod
    def parse(cls, name: "str | int | Tissue") -> "Tissue":
        """`Tissue` from a name ("skull", case-insensitive), an int or a Tissue."""
        if isinstance(name, Tissue):
            return name
        if isinstance(name, (int, np.integer)):
            try:
                return cls(int(name))
            except ValueError:
                raise ValueError(
                    f"tissue label {name} is not a Tissue; use 0..4 "
                    f"({', '.join(f'{t.value}={t.name}' for t in cls)})."
                ) from None
        try:
            return cls[str(name).upper()]
        except KeyError:
            raise ValueError(
                f"unknown tissue {name!r}; use one of "
                f"{[t.name.lower() for t in cls]}."
            ) from None


#: Per-tissue arrays everywhere are ordered like this (Tissue values 1..4).
TISSUES: tuple[Tissue, ...] = (Tissue.BRAIN, Tissue.CSF, Tissue.SKULL, Tissue.SCALP)
TISSUE_NAMES: tuple[str, ...] = tuple(t.name.lower() for t in TISSUES)

#: Default low-frequency conductivities in S/m, ordered as TISSUES.
#: - brain 0.3: grey matter as used in UCL head EIT modelling (Horesh 2006, PhD thesis, UCL;
#:   Tizzard et al. 2005, Physiol. Meas. 26:S251); brain treated as one tissue.
#: - CSF 1.79: Baumann et al. 1997, IEEE TBME 44:220 (at 37 C).
#: - skull 0.018: Horesh 2006; Tizzard et al. 2005 (UCL head EIT work).
#: - scalp 0.44: Horesh 2006; Tizzard et al. 2005.
DEFAULT_SIGMA_S_M: tuple[float, float, float, float] = (0.3, 1.79, 0.018, 0.44)


def default_sigma() -> np.ndarray:
    """Default conductivities in S/m, shape (4,), ordered BRAIN, CSF, SKULL, SCALP (float64)."""
    return np.array(DEFAULT_SIGMA_S_M, dtype=np.float64)


def sigma_per_tet(mesh, sigma):
    """Per-tet conductivity from per-tissue values: ``sigma[mesh.labels - 1]``.

    Arguments:
        mesh: a `TetMesh` (anything with integer `labels` 1..4 per tet).
        sigma: (4,) conductivities in S/m ordered as `TISSUES`, a mapping from tissue names
            ("brain", ...) or `Tissue` to S/m, or an (n_tets,) array (returned as is).

    Returns:
        (n_tets,) conductivity in S/m: a JAX array for JAX input (differentiable), else NumPy.
    """
    if isinstance(sigma, Mapping):
        values = {Tissue.parse(k): v for k, v in sigma.items()}
        missing = [t.name.lower() for t in TISSUES if t not in values]
        if missing:
            raise ValueError(f"`sigma` has no value for {missing}; give all of {list(TISSUE_NAMES)}.")
        sigma = np.array([float(values[t]) for t in TISSUES])
    labels = np.asarray(mesh.labels)
    n = labels.shape[0]
    xp = jnp if isinstance(sigma, jax.Array) else np
    sigma = xp.asarray(sigma)
    if sigma.shape == (n,):
        return sigma
    if sigma.shape != (len(TISSUES),):
        raise ValueError(f"`sigma` has shape {tuple(sigma.shape)}; pass (4,) per-tissue values "
                         f"ordered {list(TISSUE_NAMES)} or ({n},) per-tet values.")
    return sigma[labels - 1]
