"""Tissue classes and their default low-frequency conductivities."""

import math
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


def per_tissue(value, name: str, *, allowed=TISSUES, allow_none: bool = False,
               positive: bool = True, unit: str = "mm") -> dict[Tissue, float | None]:
    """A per-tissue setting, validated: one number for every tissue, or a mapping per tissue.

    The one parser behind every per-tissue config field (`edge_mm`, `closing_radius_mm`, ...).

    Arguments:
        value: a number (all of `allowed`), a mapping keyed by tissue name or `Tissue`, or None
            (with `allow_none`: no value for any tissue).
        name: the argument's name, for error messages.
        allowed: the tissues the setting has (default all four).
        allow_none: a mapping may leave tissues out (their value is None).
        positive: values must be > 0 (else >= 0).
        unit: the unit named in error messages.

    Returns:
        {Tissue: float (or None)} over `allowed`, in `allowed`'s order.
    """
    names = [t.name.lower() for t in allowed]
    if value is None:
        if not allow_none:
            raise ValueError(f"`{name}` is None; give a number ({unit}) or a mapping over {names}.")
        return {t: None for t in allowed}
    if isinstance(value, Mapping):
        out: dict[Tissue, object] = {t: None for t in allowed}
        for key, v in value.items():
            try:
                t = Tissue.parse(key)
            except ValueError as e:
                raise ValueError(f"`{name}` has key {key!r}: {e}") from None
            if t not in allowed:
                raise ValueError(f"`{name}` has key {key!r}; allowed keys are {names}.")
            out[t] = v
        missing = [t.name.lower() for t, v in out.items() if v is None]
        if missing and not allow_none:
            raise ValueError(f"`{name}` lacks {missing}; give all of {names} or a single number "
                             "for all.")
    else:
        out = {t: value for t in allowed}
    for t, v in out.items():
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not math.isfinite(v) or (v <= 0 if positive else v < 0):
            need = "a positive" if positive else "a finite, non-negative"
            raise ValueError(f"`{name}[{t.name.lower()}]` must be {need} number ({unit}), got {v!r}.")
        out[t] = float(v)
    return out
