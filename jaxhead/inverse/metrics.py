"""Image metrics of a reconstructed perturbation: localisation error, size, peak."""




import equinox as eqx
import numpy as np

from .grid import Grid


class ImageMetrics(eqx.Module):
    """Figures of merit of a reconstructed blob.

    Attributes:
        localisation_error_mm: distance from the thresholded image's centroid to the true centre.
        diameter_mm: diameter of the sphere with the thresholded region's volume (the FWHM-like
            size when threshold = 0.5).
        volume_ratio: thresholded volume / true perturbation volume (1 ideal).
        peak_value: the image's extreme value of the perturbation's sign.
    """

    localisation_error_mm: float
    diameter_mm: float
    volume_ratio: float
    peak_value: float


def image_metrics(image, grid, *args, threshold: float = 0.5, sign: int = 0) -> ImageMetrics:
    """Localisation error, size and volume ratio of a reconstructed perturbation.

    Called as ``image_metrics(image, grid, true_centre_mm, true_radius_mm)`` with the `Grid` the
    image lives on, or ``image_metrics(image, centres_mm, volumes_mm3, true_centre_mm,
    true_radius_mm)`` for any other elements (e.g. tets).

    Arguments:
        image: (n,) reconstructed change per element (grid cells or tets).
        grid: the `Grid` of the image (its cell centres and volumes), or (n, 3) element centres
            in mm followed by (n,) element volumes in mm^3.
        true_centre_mm, true_radius_mm: the perturbation's ball (mm).
        threshold: keep elements with value >= threshold * peak (0.5: half maximum).
        sign: +1 or -1 for the perturbation's sign; 0 takes the sign of the largest |value|.
    """
    if isinstance(grid, Grid):
        centres_mm, volumes_mm3 = grid.centres, grid.volumes
        expected = 2
    else:
        centres_mm, volumes_mm3, args = grid, args[0] if args else None, args[1:]
        expected = 2
    if len(args) != expected:
        raise TypeError("call image_metrics(image, grid, true_centre_mm, true_radius_mm) or "
                        "image_metrics(image, centres_mm, volumes_mm3, true_centre_mm, true_radius_mm).")
    true_centre_mm, true_radius_mm = args
    x = np.asarray(image, dtype=np.float64)
    c = np.asarray(centres_mm, dtype=np.float64)
    v = np.asarray(volumes_mm3, dtype=np.float64)
    if not (x.shape[0] == c.shape[0] == v.shape[0]):
        raise ValueError(f"`image` ({x.shape[0]}), `centres_mm` ({c.shape[0]}) and `volumes_mm3` "
                         f"({v.shape[0]}) must have one entry per element.")
    if not 0 < threshold < 1:
        raise ValueError(f"`threshold` must be in (0, 1), got {threshold}.")
    if sign == 0:
        sign = 1 if x[np.argmax(np.abs(x))] >= 0 else -1
    y = sign * x
    peak = y.max()
    if not peak > 0:
        raise ValueError("the image has no value of the requested sign; nothing to measure.")
    sel = y >= threshold * peak
    w = v[sel] * y[sel]
    centroid = (c[sel] * w[:, None]).sum(0) / w.sum()
    vol = v[sel].sum()
    true_vol = 4 / 3 * np.pi * true_radius_mm**3
    return ImageMetrics(
        localisation_error_mm=float(np.linalg.norm(centroid - np.asarray(true_centre_mm))),
        diameter_mm=float(2 * (3 * vol / (4 * np.pi)) ** (1 / 3)),
        volume_ratio=float(vol / true_vol),
        peak_value=float(sign * peak),
    )
