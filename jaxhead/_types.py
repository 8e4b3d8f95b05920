"""Shape-annotated array aliases, one set of dimension names for the whole package.

Dimension names: ``n_nodes``, ``n_tets``, ``n_faces``, ``n_verts``, ``n_elec``, ``n_rows``
(protocol rows), ``n_inj``, ``n_meas``, ``n_tissue`` (4: BRAIN, CSF, SKULL, SCALP), ``x y z``.
"""

from typing import TypeAlias

import jax
import numpy as np
from jaxtyping import Float, Int, Shaped

Array: TypeAlias = jax.Array | np.ndarray

Nodes: TypeAlias = Float[Array, "n_nodes 3"]
Tets: TypeAlias = Int[Array, "n_tets 4"]
TetLabels: TypeAlias = Int[Array, " n_tets"]
Faces: TypeAlias = Int[Array, "n_faces 3"]
Vertices: TypeAlias = Float[Array, "n_verts 3"]
Affine: TypeAlias = Float[Array, "4 4"]
Grid: TypeAlias = Shaped[Array, "x y z"]
TissueSigma: TypeAlias = Float[Array, " 4"]
TetSigma: TypeAlias = Float[Array, " n_tets"]
Sigma: TypeAlias = Float[Array, " n_sigma"]  # 4 per-tissue values, or one per tet
