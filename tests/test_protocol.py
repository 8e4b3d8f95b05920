"""Protocol type, builders, CSV round trip and errors."""

import jax
import numpy as np
import pytest

from jaxhead.protocol import (DEFAULT_CURRENT_A, Protocol, adjacent, load_voltages, opposite,
                              pair_drive, save_voltages)


def _valid(p: Protocol, n: int):
    r = p.rows
    assert r.dtype == np.int64 and r.shape[1] == 4
    assert r.min() >= 0 and r.max() < n
    assert np.all(r[:, 0] != r[:, 1]) and np.all(r[:, 2] != r[:, 3])
    # no measurement on a current-carrying electrode
    for s, k, a, b in r:
        assert not {a, b} & {s, k}
    # rows unique
    assert len(np.unique(r, axis=0)) == len(r)


@pytest.mark.parametrize("n", [4, 8, 16, 31, 32])
def test_adjacent(n):
    p = adjacent(n)
    _valid(p, n)
    assert p.n_rows == n * (n - 3)
    assert p.n_inj == n
    np.testing.assert_array_equal(p.injections, [[i, (i + 1) % n] for i in range(n)])
    # every measurement is an adjacent pair
    assert np.all((p.rows[:, 3] - p.rows[:, 2]) % n == 1)
    assert p.current_a == DEFAULT_CURRENT_A


@pytest.mark.parametrize("n", [5, 8, 16, 31, 32])
def test_opposite(n):
    p = opposite(n)
    _valid(p, n)
    n_inj = n // 2 if n % 2 == 0 else n
    assert p.n_inj == n_inj and p.n_rows == n_inj * (n - 4)
    d = (p.injections[:, 1] - p.injections[:, 0]) % n
    assert np.all(d == n // 2)
    # no drive pair is another one reversed
    pairs = {frozenset(x) for x in p.injections.tolist()}
    assert len(pairs) == n_inj


def test_pair_drive():
    p = pair_drive(16, 3, 11, current_a=1e-3)
    _valid(p, 16)
    assert p.n_inj == 1 and p.n_rows == 16 - 4
    assert p.current_a == 1e-3
    np.testing.assert_array_equal(p.drive_index, 0)
    p2 = pair_drive(8, 2, 3)  # adjacent drive pair: 3 measurements excluded
    assert p2.n_rows == 8 - 3


def test_injections_and_drive_index():
    rows = [[2, 5, 0, 1], [0, 1, 2, 3], [2, 5, 3, 4], [5, 2, 0, 1], [0, 1, 4, 5]]
    p = Protocol(rows, 1e-4)
    # unique ordered pairs in order of first appearance; (5, 2) is its own injection
    np.testing.assert_array_equal(p.injections, [[2, 5], [0, 1], [5, 2]])
    np.testing.assert_array_equal(p.drive_index, [0, 1, 0, 2, 1])
    np.testing.assert_array_equal(p.injections[p.drive_index], p.rows[:, :2])
    np.testing.assert_array_equal(p.measurements, p.rows[:, 2:])


def test_drive_index_consistent_for_builders():
    for p in (adjacent(16), opposite(16), pair_drive(16, 0, 8)):
        np.testing.assert_array_equal(p.injections[p.drive_index], p.rows[:, :2])


@pytest.mark.parametrize("one_based", [True, False])
def test_csv_round_trip(tmp_path, one_based):
    p = opposite(16, current_a=2.5e-4)
    path = tmp_path / "prot.csv"
    p.to_csv(path, one_based=one_based)
    q = Protocol.from_csv(path, one_based=one_based)
    np.testing.assert_array_equal(q.rows, p.rows)
    assert q.current_a == p.current_a
    # explicit current wins over the file's
    assert Protocol.from_csv(path, one_based=one_based, current_a=1e-3).current_a == 1e-3


def test_csv_ucl_style_plain_matrix(tmp_path):
    # UCL/Matlab style: 1-based, no header, whitespace or commas
    path = tmp_path / "ucl.txt"
    path.write_text("1 2 3 4\n1 2 4 5\n\n2 3 5 6\n")
    p = Protocol.from_csv(path)
    np.testing.assert_array_equal(p.rows, [[0, 1, 2, 3], [0, 1, 3, 4], [1, 2, 4, 5]])
    assert p.current_a == DEFAULT_CURRENT_A


@pytest.mark.parametrize("text,match", [
    ("1,2,3\n", "expected 4 columns"),
    ("0,1,2,3\n", "one_based=False"),
    ("1,2,3,4\n1,2,x,4\n", "not numbers"),
    ("source,sink,a,b\n", "no protocol rows"),
    ("1,2,3.5,4\n", "integers"),
])
def test_csv_errors(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        Protocol.from_csv(path)


def test_to_csv_is_atomic_on_missing_dir(tmp_path):
    with pytest.raises(FileNotFoundError):
        adjacent(8).to_csv(tmp_path / "nope" / "p.csv")


@pytest.mark.parametrize("rows,cur,match", [
    (np.zeros((3, 3), int), 1e-4, r"shape \(n_rows, 4\)"),
    (np.zeros((0, 4), int), 1e-4, r"n_rows >= 1"),
    ([[0, 1, 2, -3]], 1e-4, "negative"),
    ([[1, 1, 2, 3]], 1e-4, "source == sink"),
    ([[0, 1, 2, 2]], 1e-4, "meas\\+ == meas-"),
    ([[0, 1, 2, 3]], 0.0, "current_a"),
    ([[0, 1, 2, 3]], np.nan, "current_a"),
    ([[0, 1, 2.5, 3]], 1e-4, "integer"),
])
def test_protocol_validation(rows, cur, match):
    with pytest.raises(ValueError, match=match):
        Protocol(rows, cur)


def test_check_n_elec():
    p = adjacent(16)
    assert p.check(16) is p
    with pytest.raises(ValueError, match="16 electrodes"):
        Protocol(p.rows + 1, 1e-4).check(16)


@pytest.mark.parametrize("fn,args,match", [
    (adjacent, (3,), "n_elec"),
    (opposite, (4,), "n_elec"),
    (adjacent, (8.0,), "n_elec"),
    (pair_drive, (8, 0, 0), "both 0"),
    (pair_drive, (8, 0, 8), "sink"),
])
def test_builder_errors(fn, args, match):
    with pytest.raises(ValueError, match=match):
        fn(*args)


def test_protocol_is_a_pytree():
    p = adjacent(8)
    leaves = jax.tree_util.tree_leaves(p)
    assert len(leaves) == 1 and leaves[0] is p.rows


def test_protocol_config(tmp_path):
    from jaxhead.protocol import ProtocolConfig, protocol_from_config

    assert protocol_from_config(16).n_rows == adjacent(16).n_rows
    p = protocol_from_config(16, ProtocolConfig(kind="opposite", current_a=1e-3))
    assert p.n_inj == 8 and p.current_a == 1e-3
    p = protocol_from_config(16, ProtocolConfig(kind="pair", source=2, sink=9))
    np.testing.assert_array_equal(p.injections, [[2, 9]])
    path = tmp_path / "p.csv"
    opposite(16, current_a=3e-4).to_csv(path)
    p = protocol_from_config(16, ProtocolConfig(kind="csv", csv_path=str(path), current_a=None))
    assert p.current_a == 3e-4
    with pytest.raises(ValueError, match="there are 8 electrodes"):
        protocol_from_config(8, ProtocolConfig(kind="csv", csv_path=str(path)))
    for kw, match in ((dict(kind="ring"), "kind"), (dict(current_a=-1.0), "current_a"),
                      (dict(kind="csv"), "csv_path"), (dict(current_a=None), "None"),
                      (dict(kind="pair", source=3, sink=3), "both 3")):
        with pytest.raises(ValueError, match=match):
            ProtocolConfig(**kw)


@pytest.mark.parametrize("one_based", [True, False])
def test_voltages_round_trip(tmp_path, one_based):
    p = adjacent(8)
    v = np.random.default_rng(0).standard_normal(p.n_rows) * 1e-3
    save_voltages(tmp_path / "v.csv", p, v, one_based=one_based)
    np.testing.assert_allclose(load_voltages(tmp_path / "v.csv", p, one_based=one_based), v,
                               rtol=1e-9)
    # A plain column of volts in protocol order reads the same.
    np.savetxt(tmp_path / "col.txt", v)
    np.testing.assert_allclose(load_voltages(tmp_path / "col.txt", p), v, rtol=1e-15)


def test_voltages_errors(tmp_path):
    p = adjacent(8)
    v = np.linspace(1e-3, 2e-3, p.n_rows)
    with pytest.raises(ValueError, match="`volts` has shape"):
        save_voltages(tmp_path / "x.csv", p, v[:-1])
    save_voltages(tmp_path / "v.csv", p, v)
    lines = (tmp_path / "v.csv").read_text().splitlines()
    # Rows out of protocol order: named by line and row, never reordered silently.
    swapped = lines[:2] + [lines[3], lines[2]] + lines[4:]
    (tmp_path / "s.csv").write_text("\n".join(swapped))
    with pytest.raises(ValueError, match=r"s.csv:3: electrodes .* differ from protocol row 0"):
        load_voltages(tmp_path / "s.csv", p)
    (tmp_path / "short.csv").write_text("\n".join(lines[:-1]))
    with pytest.raises(ValueError, match=f"the protocol has {p.n_rows} rows"):
        load_voltages(tmp_path / "short.csv", p)
    (tmp_path / "cur.csv").write_text("\n".join(["# current_a = 0.001"] + lines[1:]))
    with pytest.raises(ValueError, match="current_a"):
        load_voltages(tmp_path / "cur.csv", p)
    (tmp_path / "nan.csv").write_text("\n".join(lines[:2] + [lines[2].rsplit(",", 1)[0] + ",nan"]
                                               + lines[3:]))
    with pytest.raises(ValueError, match="NaN"):
        load_voltages(tmp_path / "nan.csv", p)
    (tmp_path / "cols.csv").write_text("\n".join(lines[:2] + ["1,2,3,0.5"] + lines[3:]))
    with pytest.raises(ValueError, match="expected 5 columns"):
        load_voltages(tmp_path / "cols.csv", p)
