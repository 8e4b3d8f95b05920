"""`templates.on_scan_grid`: an anatomy placed on a scan's field of view (centred, the top kept, the neck cut)."""

import numpy as np
import pytest

from jaxhead.segmentation.templates import Anatomy, on_scan_grid


def _head(shape=(20, 24, 30), box=((4, 15), (3, 20), (2, 27)), seed=0) -> Anatomy:
    """Random tissue fractions inside `box` (voxel index ranges, end exclusive), air around it; a shifted,
    anisotropic affine and a diploe so that every field is checked."""
    rng = np.random.default_rng(seed)
    fr = np.zeros((6, *shape), np.float32)
    fr[0] = 1.0
    sl = tuple(slice(*b) for b in box)
    inner = rng.random((6, *(b[1] - b[0] for b in box))).astype(np.float32)
    inner[0] *= 0.2  # some air inside, but never all
    fr[(slice(None),) + sl] = inner / inner.sum(0)
    affine = np.array([[0.9, 0, 0, -7.0], [0, 1.1, 0, 3.0], [0, 0, 1.3, -20.0], [0, 0, 0, 1]])
    return Anatomy(fr, affine, "box", diploe=fr[4] * 0.5)


def _world(affine, idx):
    return (affine @ np.append(np.asarray(idx, np.float64), 1.0))[:3]


@pytest.mark.parametrize("shape", [(16, 30, 18), (26, 14, 40), (11, 17, 25)])
def test_every_kept_voxel_keeps_its_world_position_and_values(shape):
    a = _head()
    out = on_scan_grid(a, shape, top_margin_vox=2)
    assert out.shape == shape and out.t1 is None and out.unmodelled_bone is None
    np.testing.assert_allclose(out.fractions.sum(0), 1.0, rtol=1e-6)
    src = np.asarray(np.meshgrid(*(np.arange(n) for n in a.shape), indexing="ij")).reshape(3, -1)
    # every source voxel that lands on the grid (by world position) holds the same fractions and diploe there
    inv = np.linalg.inv(out.affine)
    dst = np.rint((inv @ (a.affine @ np.vstack([src, np.ones(src.shape[1])])))[:3]).astype(int)
    ok = np.all((dst >= 0) & (dst < np.asarray(shape)[:, None]), axis=0)
    per_axis = [len(np.unique(d[ok])) for d in dst]  # nothing is resampled: a block moves, one voxel to one
    assert ok.sum() == np.prod(per_axis) == len(np.unique(np.ravel_multi_index(tuple(dst[:, ok]), shape)))
    np.testing.assert_array_equal(out.fractions[(slice(None),) + tuple(dst[:, ok])],
                                  a.fractions[(slice(None),) + tuple(src[:, ok])])
    np.testing.assert_array_equal(out.diploe[tuple(dst[:, ok])], a.diploe[tuple(src[:, ok])])
    kept = np.zeros(shape, bool)
    kept[tuple(dst[:, ok])] = True
    assert np.all(out.fractions[0][~kept] == 1.0)  # the padding is air


def test_the_head_is_centred_and_its_top_kept_with_the_margin():
    a = _head()  # head: x 4..14, y 3..19, z 2..26 (inclusive)
    out = on_scan_grid(a, (16, 30, 18), top_margin_vox=2)
    head = np.nonzero(out.fractions[0] < 1 - 1e-6)
    lo, hi = [h.min() for h in head], [h.max() for h in head]
    assert hi[2] == 18 - 1 - 2  # the top, two air voxels below the grid's top; the neck cut
    assert lo[2] == 0
    for ax, n in ((0, 16), (1, 30)):  # centred within a voxel
        assert abs((lo[ax] + hi[ax]) - (n - 1)) <= 1
    # the world position of the top of the head is unchanged
    np.testing.assert_allclose(_world(out.affine, (lo[0], lo[1], hi[2]))[2], _world(a.affine, (4, 3, 26))[2])


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="shape"):
        on_scan_grid(_head(), (10, 10))
    air = _head()
    air = Anatomy(np.concatenate([np.ones_like(air.fractions[:1]), np.zeros_like(air.fractions[1:])]), air.affine, "air")
    with pytest.raises(ValueError, match="all air"):
        on_scan_grid(air, (10, 10, 10))


def test_shipped_heads_folder_env_first_then_beside_the_checkout(monkeypatch, tmp_path):
    from pathlib import Path

    from jaxhead.segmentation.templates import shipped_heads_folder

    monkeypatch.setenv("JAXHEAD_HEADS", str(tmp_path))
    assert shipped_heads_folder() == tmp_path
    monkeypatch.delenv("JAXHEAD_HEADS")
    found = shipped_heads_folder()
    assert found.parts[-3:] == ("shared", "data", "heads")
    assert found.is_dir() or found == Path("../shared/data/heads")  # a folder above the package, or the fallback
