"""jaxhead.masks against a brute-force flood fill (an independent implementation)."""

import numpy as np

from jaxhead.masks import largest_component


def _flood_components(mask):
    """Face-connected components by a plain breadth-first flood fill: list of sets of voxel indices."""
    seen, pieces = set(), []
    for start in zip(*np.nonzero(mask)):
        if start in seen:
            continue
        piece, todo = set(), [start]
        seen.add(start)
        while todo:
            v = todo.pop()
            piece.add(v)
            for ax in range(3):
                for d in (-1, 1):
                    w = list(v)
                    w[ax] += d
                    w = tuple(w)
                    if all(0 <= w[i] < mask.shape[i] for i in range(3)) and mask[w] and w not in seen:
                        seen.add(w)
                        todo.append(w)
        pieces.append(piece)
    return pieces


def test_largest_component_matches_a_flood_fill_on_random_masks():
    rng = np.random.default_rng(0)
    for trial in range(20):
        mask = rng.random((7, 8, 6)) < rng.uniform(0.15, 0.45)
        pieces = _flood_components(mask)
        out, n_other = largest_component(mask)
        assert n_other == max(len(pieces) - 1, 0)
        if not pieces:
            assert not out.any()
            continue
        biggest = max(len(p) for p in pieces)
        assert out.sum() == biggest
        got = set(zip(*np.nonzero(out)))
        assert any(got == p for p in pieces if len(p) == biggest)  # one whole component, a largest one


def test_largest_component_of_an_empty_and_of_a_single_piece_mask():
    out, n = largest_component(np.zeros((4, 4, 4), bool))
    assert n == 0 and not out.any()
    m = np.zeros((6, 6, 6), bool)
    m[2:5, 1:3, 3] = True
    out, n = largest_component(m)
    assert n == 0
    np.testing.assert_array_equal(out, m)
