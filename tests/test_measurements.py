"""Measured recordings: every layout written here, read back, converted to SI / 0-based in one
place; bad files are errors naming the file, the row and the fix."""

import json

import h5py
import numpy as np
import pytest
import scipy.io

from jaxhead.io import Measurements, load_measurements, mat73_arrays, save_measurements
from jaxhead.protocol import Protocol, common_reference, reference_protocol, save_voltages

N_ELEC = 6
NAMES = ("Fp1", "Fp2", "T7", "T8", "Oz", "NFpz")
FREQS = [5.0, 50.0, 2000.0]


@pytest.fixture
def rec():
    prot = reference_protocol(N_ELEC, 5, [(0, 1), (2, 3)], current_a=2e-4)
    rng = np.random.default_rng(0)
    volts = rng.normal(0, 1e-3, (len(FREQS), prot.n_rows))  # V
    pos = rng.normal(0, 80, (N_ELEC, 3))  # mm
    return prot, volts, pos


def write_mat73(path, arrays):
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 with a 512-byte user block, header text,
    column-major arrays (h5py sees them transposed) tagged with MATLAB_class."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for k, a in arrays.items():
            d = f.create_dataset(k, data=np.asarray(a, dtype=np.float64).T)
            d.attrs["MATLAB_class"] = np.bytes_("double")
    with open(path, "r+b") as fh:
        fh.write(b"MATLAB 7.3 MAT-file, Platform: GLNXA64".ljust(116) + b"\0" * 8 + b"\x00\x02IM")


def write_ucl(tmp_path, prot, volts, pos, *, vkind="mat73", **extra):
    settings = {"Freq": FREQS, "Protocol": (prot.rows + 1).tolist(),
                "ElectrodePosition": (pos / 1000).tolist(), "ElectrodeNames": list(NAMES),
                "CurrentA": prot.current_a, **extra}
    js = tmp_path / "rec.json"
    mv = volts.T * 1e3  # (n_rows, n_freq) in mV, as the lab's files hold them
    if vkind == "mat73":
        write_mat73(tmp_path / "rec.mat", {"BV": mv})
    elif vkind == "mat5":
        scipy.io.savemat(tmp_path / "rec.mat", {"BV": mv})
    elif vkind == "json":
        settings["Voltages"] = mv.tolist()
    js.write_text(json.dumps(settings))
    return js


@pytest.mark.parametrize("vkind", ["mat73", "mat5", "json"])
def test_ucl_layout_round_trip(tmp_path, rec, vkind):
    prot, volts, pos = rec
    m = load_measurements(write_ucl(tmp_path, prot, volts, pos, vkind=vkind))
    np.testing.assert_array_equal(m.rows, prot.rows)  # 1-based -> 0-based
    # mV -> V (x 1e-3 then back) and m -> mm: exact to float64 round-off
    np.testing.assert_allclose(m.voltages, volts, rtol=1e-14)
    np.testing.assert_allclose(m.positions_mm, pos, rtol=1e-14)
    np.testing.assert_array_equal(m.frequencies_hz, FREQS)
    assert m.electrode_names == NAMES and m.current_a == 2e-4 and m.reference == 5
    np.testing.assert_array_equal(m.at(50.0), volts[1])
    assert common_reference(Protocol(m.rows, m.current_a)) == 5


def test_mat73_reader_transposes_to_matlab_shape(tmp_path):
    a = np.arange(12.0).reshape(3, 4)
    write_mat73(tmp_path / "x.mat", {"A": a})
    np.testing.assert_array_equal(mat73_arrays(tmp_path / "x.mat")["A"], a)


@pytest.mark.parametrize("units,base", [("V", 1), ("mV", 0), ("uV", 1)])
def test_csv_round_trip(tmp_path, rec, units, base):
    prot, volts, pos = rec
    m = Measurements(rows=prot.rows, voltages=volts, frequencies_hz=np.array(FREQS),
                     current_a=prot.current_a, electrode_names=NAMES, positions_mm=pos)
    save_measurements(tmp_path / "r.csv", m, units=units, one_based=bool(base))
    text = (tmp_path / "r.csv").read_text()
    assert f"# units = {units}" in text and f"# index_base = {base}" in text
    back = load_measurements(tmp_path / "r.csv")
    np.testing.assert_array_equal(back.rows, prot.rows)
    np.testing.assert_allclose(back.voltages, volts, rtol=1e-11)  # 13 significant digits
    np.testing.assert_allclose(back.positions_mm, pos, rtol=1e-15)
    np.testing.assert_array_equal(back.frequencies_hz, FREQS)
    assert back.electrode_names == NAMES and back.current_a == prot.current_a


def test_our_voltages_csv_reads_as_one_unknown_frequency(tmp_path, rec):
    prot, volts, _ = rec
    save_voltages(tmp_path / "v.csv", prot, volts[0])  # the forward stage's voltages.csv
    m = load_measurements(tmp_path / "v.csv")
    np.testing.assert_allclose(m.at(), volts[0], rtol=1e-9)
    assert np.isnan(m.frequencies_hz).all() and m.current_a == prot.current_a


def test_plain_layout_with_names(tmp_path):
    (tmp_path / "p.txt").write_text(
        "# current_a = 1e-4\n# units = mV\n# electrodes = A B C D\n"
        "source\tsink\tmeas_plus\tmeas_minus\t10Hz\t1000\n"
        "A\tB\tC\tD\t1.5\t1.25\nB\tC\tA\tD\t-2\t-1.75\n")
    m = load_measurements(tmp_path / "p.txt")
    np.testing.assert_array_equal(m.rows, [[0, 1, 2, 3], [1, 2, 0, 3]])
    np.testing.assert_allclose(m.voltages, [[1.5e-3, -2e-3], [1.25e-3, -1.75e-3]])
    np.testing.assert_array_equal(m.frequencies_hz, [10.0, 1000.0])


def _csv(tmp_path, body, head="# current_a = 1e-4\nsource,sink,meas_plus,meas_minus,10Hz\n"):
    p = tmp_path / "bad.csv"
    p.write_text(head + body)
    return p


@pytest.mark.parametrize("body,match", [
    ("1,2,3,4,1e-3\n0,2,3,4,1e-3\n", r"bad.csv: line 4 has electrode index 0 .*index_base = 0"),
    ("1,2,3,4,1e-3\n1,2,3,4,nan\n", r"bad.csv:4: voltage is nan at 10 Hz"),
    ("1,2,3,4,1e-3\n1,2,3,4,abc\n", r"bad.csv:4: voltage 'abc' .* not a number"),
    ("1,2,3,4,1e-3\n1,2,3,4\n", r"bad.csv:4: 4 columns, but the first row has 5"),
    ("1,2,3,Cz,1e-3\n", r"bad.csv:3: meas_minus 'Cz' .*# electrodes"),
    ("1,2,3.5,4,1e-3\n", r"bad.csv:3: meas_plus '3.5' is not an integer"),
])
def test_bad_csv_names_file_row_and_fix(tmp_path, body, match):
    with pytest.raises(ValueError, match=match):
        load_measurements(_csv(tmp_path, body))


def test_csv_needs_current_and_known_names(tmp_path):
    with pytest.raises(ValueError, match="current_a"):
        load_measurements(_csv(tmp_path, "1,2,3,4,1e-3\n", head="s,k,p,m,volts\n"))
    p = _csv(tmp_path, "A,B,C,X,1e-3\n",
             head="# current_a = 1e-4\n# electrodes = A B C D\ns,k,p,m,volts\n")
    with pytest.raises(ValueError, match=r"bad.csv:4: meas_minus 'X' .*known names: A B C D"):
        load_measurements(p)


def test_frequency_not_in_file(tmp_path, rec):
    prot, volts, pos = rec
    m = load_measurements(write_ucl(tmp_path, prot, volts, pos))
    with pytest.raises(ValueError, match=r"rec.json: frequency 100.0 Hz is not in the file; "
                                         r"its frequencies \(Hz\): 5, 50, 2000"):
        m.at(100.0)
    with pytest.raises(ValueError, match="3 frequencies"):
        m.at()


def test_bad_ucl_files(tmp_path, rec):
    prot, volts, pos = rec
    # wrong row count: voltages of a shorter recording
    js = write_ucl(tmp_path, prot, volts[:, :-1], pos)
    with pytest.raises(ValueError, match=r"rec.mat: voltages have shape \(5, 3\), but the Protocol has 6 rows"):
        load_measurements(js)
    # 0-based protocol where the layout is 1-based
    js = write_ucl(tmp_path, prot, volts, pos)
    s = json.loads(js.read_text())
    s["Protocol"] = prot.rows.tolist()
    js.write_text(json.dumps(s))
    with pytest.raises(ValueError, match=r"Protocol row 1 \(1-based\) .* index 0 .*0-based"):
        load_measurements(js)
    # NaN voltage: names the row and the frequency
    bad = volts.copy()
    bad[2, 3] = np.nan
    with pytest.raises(ValueError, match=r"rec.mat: voltage of Protocol row 4 at 2000 Hz is nan"):
        load_measurements(write_ucl(tmp_path, prot, bad, pos))
    # an electrode beyond ElectrodePosition
    with pytest.raises(ValueError, match=r"Protocol row 1 uses electrode 6 but "
                                         r"ElectrodePosition has 5"):
        load_measurements(write_ucl(tmp_path, prot, volts, pos[:5],
                                    ElectrodeNames=list(NAMES[:5])))
    # text where numbers belong
    js = write_ucl(tmp_path, prot, volts, pos)
    s = json.loads(js.read_text())
    s["Freq"] = ["five", 50, 2000]
    js.write_text(json.dumps(s))
    with pytest.raises(ValueError, match=r"Freq: not a numeric array: entry 1 is 'five', not a "
                                         r"number; write the number"):
        load_measurements(js)
    s["Freq"] = FREQS
    s["Protocol"][2][1] = "T7"  # a name where the layout has 1-based electrode numbers
    js.write_text(json.dumps(s))
    with pytest.raises(ValueError, match=r"rec.json: Protocol: not a numeric array: row 3, column "
                                         r"2 is 'T7', not a number"):
        load_measurements(js)
    s = json.loads(write_ucl(tmp_path, prot, volts, pos, vkind="json").read_text())
    s["Voltages"][4][1] = "1.5e-3 mV"  # text in the voltages: row and column named
    js.write_text(json.dumps(s))
    with pytest.raises(ValueError, match=r"Voltages: not a numeric array: row 5, column 2 is "
                                         r"'1.5e-3 mV'"):
        load_measurements(js)
    # missing current
    js = write_ucl(tmp_path, prot, volts, pos)
    s = json.loads(js.read_text())
    del s["CurrentA"]
    js.write_text(json.dumps(s))
    with pytest.raises(ValueError, match="pass current_a="):
        load_measurements(js)
    assert load_measurements(js, current_a=1e-4).current_a == 1e-4
    # two candidate arrays
    scipy.io.savemat(tmp_path / "rec.mat", {"A": volts.T, "B": volts.T})
    with pytest.raises(ValueError, match=r"several: \['A', 'B'\].*variable="):
        load_measurements(js, current_a=1e-4)
    np.testing.assert_allclose(load_measurements(js, current_a=1e-4, variable="B").voltages,
                               volts * 1e-3)


def test_format_and_path_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_measurements(tmp_path / "none.csv")
    (tmp_path / "x.dat").write_text("")
    with pytest.raises(ValueError, match="format='csv' or 'ucl'"):
        load_measurements(tmp_path / "x.dat")
    with pytest.raises(ValueError, match="`format`"):
        load_measurements(tmp_path / "x.dat", format="edf")


def test_reference_protocol():
    p = reference_protocol(33, 32, [(i, (i + 11) % 32) for i in range(31)])
    assert p.n_rows == 31 * 30 == 930 and p.n_inj == 31  # UCL's stroke dataset
    assert common_reference(p) == 32
    assert not np.any(p.rows[:, 2:3] == p.rows[:, :2])  # no injecting electrode measured
    q = reference_protocol(33, 32, [(i, (i + 11) % 32) for i in range(31)],
                           include_injecting=True)
    assert q.n_rows == 31 * 32
    ring = reference_protocol(8, 3)
    assert ring.n_inj == 7 and 3 not in ring.rows[:, :3]
    with pytest.raises(ValueError, match="uses the reference electrode 3"):
        reference_protocol(8, 3, [(0, 3)])
    with pytest.raises(ValueError, match="not an electrode index"):
        reference_protocol(8, 8)
