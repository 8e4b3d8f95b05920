"""Boolean voxel-mask helpers shared by segmentation and geometry (neither imports the other)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def largest_component(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The largest face-connected (6-neighbourhood) component of a boolean mask, and how many others it has.

    Labelled inside the mask's bounding box only (a head's layer is a fraction of the grid).

    Arguments:
        mask: (x, y, z) boolean.
    Returns:
        (the largest component (x, y, z) boolean, all False where `mask` is empty; the number of other
        components, 0 where `mask` has at most one). Ties go to the component labelled first.
    """
    mask = np.asarray(mask, bool)
    out = np.zeros_like(mask)
    rows = [np.flatnonzero(mask.any(axis=tuple(a for a in range(mask.ndim) if a != ax))) for ax in range(mask.ndim)]
    if any(r.size == 0 for r in rows):
        return out, 0
    box = tuple(slice(r[0], r[-1] + 1) for r in rows)
    sub = mask[box]
    lab, n = ndimage.label(sub)
    if n <= 1:
        out[box] = sub
        return out, 0
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    out[box] = lab == int(np.argmax(sizes))
    return out, n - 1
