"""A skull with a diploe between compact tables (`templates.with_diploe`) in the synthetic scans."""

import numpy as np
import pytest

from jaxhead.segmentation.templates import CT_HU, MRI_CONTRAST, Anatomy, fatty_marrow, random_contrast, render, with_diploe


def _shell(r_in: float, r_out: float, vox: float = 0.5, n: int = 72) -> Anatomy:
    """A ball of brain (white matter) inside a spherical skull shell, in air; binary fractions."""
    c = (np.arange(n) - (n - 1) / 2) * vox
    r = np.sqrt(sum(g**2 for g in np.meshgrid(c, c, c, indexing="ij")))
    fr = np.zeros((6, n, n, n), np.float32)
    fr[2] = r < r_in
    fr[4] = (r >= r_in) & (r < r_out)
    fr[0] = r >= r_out
    aff = np.diag([vox, vox, vox, 1.0])
    return Anatomy(fr, aff, "shell")


def test_diploe_is_the_skull_deeper_than_a_table():
    a = with_diploe(_shell(8.0, 15.0), table_mm=1.5)
    vox3 = 0.5**3
    # the diploe is the shell 8 + 1.5 .. 15 - 1.5 mm (distance to the nearest non-skull voxel centre,
    # so within a voxel of the analytic surfaces)
    lo, hi = 4 / 3 * np.pi * ((13.5 - 0.5) ** 3 - (9.5 + 0.5) ** 3), 4 / 3 * np.pi * ((13.5 + 0.5) ** 3 - (9.5 - 0.5) ** 3)
    assert lo < a.diploe.sum() * vox3 < hi
    assert np.all(a.diploe <= a.fractions[4]) and np.all(a.diploe[a.fractions[4] == 0] == 0)
    # a skull thinner than two tables has none
    assert with_diploe(_shell(8.0, 10.5), table_mm=1.5).diploe.sum() == 0
    with pytest.raises(ValueError, match="table_mm"):
        with_diploe(_shell(8.0, 15.0), table_mm=0.0)


@pytest.mark.parametrize("modality, values", [("mri", MRI_CONTRAST), ("ct", CT_HU)])
def test_render_gives_the_diploe_its_own_value(modality, values):
    plain = _shell(8.0, 15.0)
    a = with_diploe(plain)
    img = render(a, modality, texture=False).data
    d, tables = a.diploe > 0.99, (a.fractions[4] > 0.99) & (a.diploe == 0)
    np.testing.assert_allclose(img[d], values["diploe"], atol=1e-9)
    table = values.get("table", values["skull"])  # CT: compact bone; MRI: the skull's own value
    np.testing.assert_allclose(img[tables], table, atol=1e-9)
    # a partial-volume voxel: each fraction at its tissue's value, the skull's split marrow : table
    f, dip = a.fractions.astype(np.float64), a.diploe.astype(np.float64)
    scalp = 0.5 * (values["fat"] + values["muscle"])
    want = (f[0] * values["air"] + f[1] * values["grey_matter"] + f[2] * values["white_matter"] + f[3] * values["csf"]
            + dip * values["diploe"] + (f[4] - dip) * table + f[5] * scalp)
    np.testing.assert_allclose(img, want, atol=1e-9)
    # without a diploe map the contrast's "diploe" and "table" change nothing (the evaluation's earlier scans)
    np.testing.assert_array_equal(render(plain, modality, texture=False, contrast={"diploe": 123.0, "table": 7.0}).data,
                                  render(plain, modality, texture=False).data)


def test_resampled_diploe_is_averaged_like_the_fractions():
    a = with_diploe(_shell(8.0, 15.0))
    b = a.resampled(1.0)  # 2 x 2 x 2 blocks
    np.testing.assert_allclose(b.diploe.sum() * 8, a.diploe.sum(), rtol=1e-5)
    assert np.all(b.diploe <= b.fractions[4] + 1e-6)
    c = a.resampled(0.75)  # interpolated, renormalised fractions: the diploe stays inside the skull
    assert np.all(c.diploe <= c.fractions[4] + 1e-6)
    with pytest.raises(ValueError, match="diploe"):
        Anatomy(a.fractions, a.affine, "bad", diploe=a.fractions[2])  # "diploe" in the brain


def test_fatty_marrow_is_as_bright_as_the_contrasts_fat():
    a = with_diploe(_shell(8.0, 15.0))
    d = a.diploe > 0.99
    drawn = random_contrast("mri", np.random.default_rng(3))
    for given in (None, drawn):
        c = fatty_marrow(given)
        base = dict(MRI_CONTRAST, **(given or {}))
        assert c["diploe"] == base["fat"] and {k: v for k, v in c.items() if k != "diploe"} == {
            k: v for k, v in base.items() if k != "diploe"}
        np.testing.assert_allclose(render(a, "mri", contrast=c, texture=False).data[d], base["fat"], atol=1e-9)
    assert drawn["diploe"] != drawn["fat"]  # the caller's contrast is not changed
    with pytest.raises(ValueError, match="table"):
        fatty_marrow(dict(CT_HU))
