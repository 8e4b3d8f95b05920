"""Measured EIT recordings: voltages with their protocol, frequencies, electrodes and current.  [host]

`load_measurements(path)` reads three layouts into one `Measurements` (SI units, 0-based
electrode indices; `_to_volts`, `_to_mm` and `_zero_based` are the one place that converts):

- ``csv`` (our CSV and the plain layout for other systems; ``.csv``, ``.txt``, ``.tsv``):
  a table with one row per measurement, written by `save_measurements` and by
  ``jaxhead.protocol.save_voltages``::

      # current_a = 0.0001              injected current in A (required unless passed)
      # units = mV                      V (default), mV or uV
      # index_base = 1                  1 (default, as UCL/Matlab) or 0
      # electrodes = Fp1 Fp2 ... NFpz   optional: names in index order (rows may then use names)
      # position Fp1 = -27.0 86.0 31.0  optional: electrode centre in mm (one line each)
      source,sink,meas_plus,meas_minus,10Hz,100Hz,1000Hz
      1,2,3,33,0.152,0.151,0.149
      ...

  The first four columns are electrodes (indices, or names from ``# electrodes``); every
  further column is one frequency, its header the frequency (``10``, ``10Hz``, ``volts@10Hz``)
  or ``volts`` for a single unknown frequency (then ``frequencies_hz`` is NaN).
- ``ucl`` (``.json``): the layout of UCL's head-EIT datasets (Goren et al. 2018, Sci. Data
  5:180112): a JSON settings file with ``Freq`` (Hz), ``Protocol`` (n_rows, 4) 1-based
  [source, sink, meas+, meas-], ``ElectrodePosition`` (n_elec, 3) in metres, optionally
  ``ElectrodeNames`` and ``CurrentA`` (A); voltages in mV, (n_rows, n_freq) or (n_freq,
  n_rows), from ``voltages_path`` (a MATLAB .mat, v5 or v7.3/HDF5, or a JSON file), else
  from the settings' own ``Voltages`` entry, else from a .mat beside the JSON with the same
  stem.

A mismatch (row count, electrode index or name, frequency, NaN, text where a number belongs)
is a ValueError naming the file, the row and the fix; nothing is repaired.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import equinox as eqx
import h5py
import numpy as np
import scipy.io

from .._files import atomic_write_path

#: Voltage units the readers accept, as factors to volts.
VOLT_UNITS = {"v": 1.0, "mv": 1e-3, "uv": 1e-6, "µv": 1e-6}
#: Length units of electrode positions, as factors to mm.
LENGTH_UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0}
#: Layouts `load_measurements` reads.
MEASUREMENT_FORMATS = ("csv", "ucl")
_EXT_FORMAT = {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".json": "ucl"}


class Measurements(eqx.Module):
    """A recording: protocol rows, voltages at one or more frequencies, electrodes, current.

    Attributes:
        rows: (n_rows, 4) int64 0-based electrode indices [source, sink, meas+, meas-]
            (`jaxhead.protocol.Protocol(m.rows, m.current_a)` is the protocol).
        voltages: (n_freq, n_rows) float64 in V for `current_a` amperes.
        frequencies_hz: (n_freq,) float64 in Hz (NaN where the file gives none).
        current_a: injected current in A.
        electrode_names: names in index order, or () when the file gives none.
        positions_mm: (n_elec, 3) electrode positions in mm in the file's own frame, or None
            (register them to a head with `jaxhead.electrodes.register_positions`).
        source: the file read (for messages).
    """

    rows: np.ndarray
    voltages: np.ndarray
    frequencies_hz: np.ndarray
    current_a: float = eqx.field(static=True)
    electrode_names: tuple[str, ...] = eqx.field(static=True, default=())
    positions_mm: np.ndarray | None = None
    source: str = eqx.field(static=True, default="")

    def __check_init__(self):
        r, v, f = self.rows, self.voltages, self.frequencies_hz
        where = f"{self.source}: " if self.source else ""
        if r.ndim != 2 or r.shape[1] != 4 or r.shape[0] == 0 or not np.issubdtype(r.dtype, np.integer):
            raise ValueError(f"{where}`rows` must be (n_rows, 4) integers, got {r.shape} {r.dtype}.")
        if r.min() < 0:
            raise ValueError(f"{where}`rows` has negative electrode indices; they are 0-based.")
        if v.ndim != 2 or v.shape[1] != r.shape[0]:
            raise ValueError(f"{where}`voltages` has shape {v.shape}; expected (n_freq, "
                             f"{r.shape[0]}) for {r.shape[0]} rows.")
        if f.shape != (v.shape[0],):
            raise ValueError(f"{where}{f.shape[0] if f.ndim else 0} frequencies for "
                             f"{v.shape[0]} voltage columns.")
        if not (math.isfinite(self.current_a) and self.current_a > 0):
            raise ValueError(f"{where}`current_a` must be > 0 A, got {self.current_a}.")
        n = self.n_elec
        if self.electrode_names and len(self.electrode_names) != n:
            raise ValueError(f"{where}{len(self.electrode_names)} electrode names but the rows "
                             f"use electrodes up to index {int(r.max())} (n_elec {n}).")
        if self.positions_mm is not None and self.positions_mm.shape != (n, 3):
            raise ValueError(f"{where}`positions_mm` has shape {self.positions_mm.shape}; "
                             f"expected ({n}, 3).")

    @property
    def n_rows(self) -> int:
        return self.rows.shape[0]

    @property
    def n_elec(self) -> int:
        """Electrodes: the names' or positions' count, else the largest index + 1."""
        if self.electrode_names:
            return len(self.electrode_names)
        if self.positions_mm is not None:
            return self.positions_mm.shape[0]
        return int(self.rows.max()) + 1

    @property
    def reference(self) -> int | None:
        """The common meas- electrode of every row (a reference-electrode recording), else None."""
        m = np.unique(self.rows[:, 3])
        return int(m[0]) if m.size == 1 else None

    def frequency_index(self, frequency_hz: float) -> int:
        """Index of `frequency_hz` in `frequencies_hz` (relative tolerance 1e-6); error if absent."""
        f = np.asarray(self.frequencies_hz)
        hit = np.flatnonzero(np.isclose(f, float(frequency_hz), rtol=1e-6, atol=0.0))
        if hit.size == 0:
            known = "none (the file gives no frequencies; pass frequency_hz=None)" \
                if np.all(np.isnan(f)) else ", ".join(f"{x:g}" for x in f)
            raise ValueError(f"{self.source}: frequency {float(frequency_hz)} Hz is not in the file; "
                             f"its frequencies (Hz): {known}.")
        return int(hit[0])

    def at(self, frequency_hz: float | None = None) -> np.ndarray:
        """(n_rows,) voltages in V at one frequency (None: the file's only frequency)."""
        if frequency_hz is None:
            if self.voltages.shape[0] != 1:
                raise ValueError(
                    f"{self.source}: the file has {self.voltages.shape[0]} frequencies "
                    f"({', '.join(f'{x:g}' for x in self.frequencies_hz)} Hz); name one.")
            return self.voltages[0]
        return self.voltages[self.frequency_index(frequency_hz)]


# ---------------------------------------------------------------------------------------------
# The one place that converts units and indexing


def _to_volts(values, unit: str, where: str) -> np.ndarray:
    key = str(unit).strip().lower()
    if key not in VOLT_UNITS:
        raise ValueError(f"{where}: unknown voltage unit {unit!r}; use V, mV or uV.")
    return np.asarray(values, dtype=np.float64) * VOLT_UNITS[key]


def _to_mm(values, unit: str, where: str) -> np.ndarray:
    key = str(unit).strip().lower()
    if key not in LENGTH_UNITS:
        raise ValueError(f"{where}: unknown length unit {unit!r}; use mm, cm or m.")
    return np.asarray(values, dtype=np.float64) * LENGTH_UNITS[key]


def _zero_based(rows: np.ndarray, base: int, where: str, row_label) -> np.ndarray:
    """File indices -> 0-based; an index below `base` is an error naming the row."""
    rows = np.asarray(rows)
    low = np.flatnonzero((rows < base).any(axis=1))
    if low.size:
        i = int(low[0])
        hint = (" The file looks 0-based: write `# index_base = 0` (CSV) or add 1 to every "
                "index." if base == 1 and rows.min() == 0 else "")
        raise ValueError(f"{where}: {row_label(i)} has electrode index {int(rows[i].min())} "
                         f"but indices start at {base} ({int(low.size)} such rows).{hint}")
    return (rows - base).astype(np.int64)


# ---------------------------------------------------------------------------------------------
# Reading


def load_measurements(path, *, format: str | None = None, voltages_path=None,
                      current_a: float | None = None, variable: str | None = None
                      ) -> Measurements:
    """Read a recording (see the module docstring for the layouts).

    Arguments:
        path: a CSV (our/plain layout) or a UCL-layout JSON settings file.
        format: "csv" or "ucl" ("plain" is "csv"); default from the extension.
        voltages_path: UCL layout: the voltages (.mat v5 or v7.3, or .json), in mV.
        current_a: injected current in A; overrides the file's (and is required when the file
            gives none).
        variable: UCL layout: the .mat/JSON variable holding the voltages (default: the one
            numeric array of the right size).

    Returns:
        `Measurements` in V, Hz, mm, A with 0-based indices.
    """
    path = Path(path)
    fmt = "csv" if format == "plain" else format
    if fmt is None:
        fmt = _EXT_FORMAT.get(path.suffix.lower())
        if fmt is None:
            raise ValueError(f"{path}: cannot tell the layout from the extension "
                             f"{path.suffix!r}; pass format='csv' or 'ucl'.")
    if fmt not in MEASUREMENT_FORMATS:
        raise ValueError(f"`format` = {format!r}; use one of {MEASUREMENT_FORMATS} (or 'plain').")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; check the path.")
    if current_a is not None and not (isinstance(current_a, (int, float)) and current_a > 0):
        raise ValueError(f"`current_a` must be a positive number of A, got {current_a!r}.")
    if fmt == "csv":
        return _read_csv(path, current_a)
    return _read_ucl(path, voltages_path, current_a, variable)


_COMMENT = re.compile(r"^#\s*([A-Za-z_]+)\s*(\S*)\s*=\s*(.*)$")
_FREQ = re.compile(r"^(?:volts?\s*@\s*)?([0-9.eE+-]+)\s*(hz)?$", re.IGNORECASE)


def _split(line: str) -> list[str]:
    sep = "," if "," in line else ("\t" if "\t" in line else None)
    return [c.strip() for c in (line.split(sep) if sep else line.split())]


def _is_data(cells, meta) -> bool:
    """Whether a line parses as a measurement row (else the first such line is the header)."""
    names = set()
    if "electrodes" in meta:
        names = {n.lower() for n in _split(meta["electrodes"][1].replace(",", " "))}

    def num(c):
        try:
            float(c)
            return True
        except ValueError:
            return False
    return all(num(c) or c.lower() in names for c in cells[:4]) and all(map(num, cells[4:]))


def _read_csv(path: Path, current_a):
    text = path.read_text(encoding="utf-8")
    meta, positions, header, data = {}, {}, None, []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            m = _COMMENT.match(s)
            if m and m.group(1).lower() == "position":
                positions[m.group(2)] = (lineno, m.group(3))
            elif m and not m.group(2):
                meta[m.group(1).lower()] = (lineno, m.group(3).strip())
            continue
        cells = _split(s)
        if header is None and not data and not _is_data(cells, meta):
            header = (lineno, cells)
            continue
        data.append((lineno, cells))
    where = str(path)
    if not data:
        raise ValueError(f"{where}: no measurement rows found; expected lines of "
                         "source,sink,meas_plus,meas_minus,volts.")
    n_col = len(data[0][1])
    if n_col < 5:
        raise ValueError(f"{where}:{data[0][0]}: {n_col} columns; expected source, sink, "
                         "meas_plus, meas_minus and one voltage column per frequency.")
    for lineno, cells in data:
        if len(cells) != n_col:
            raise ValueError(f"{where}:{lineno}: {len(cells)} columns, but the first row has "
                             f"{n_col}; every row needs the same columns.")
    # frequencies from the header
    n_v = n_col - 4
    freqs = np.full(n_v, np.nan)
    if header is not None:
        hl, hcells = header
        if len(hcells) != n_col:
            raise ValueError(f"{where}:{hl}: the header has {len(hcells)} columns but the rows "
                             f"have {n_col}.")
        for k, name in enumerate(hcells[4:]):
            if name.lower() in ("volts", "voltage", "v"):
                if n_v > 1:
                    raise ValueError(f"{where}:{hl}: column {name!r}: with several voltage "
                                     "columns each header must be its frequency (e.g. 10Hz).")
                continue
            m = _FREQ.match(name)
            if not m:
                raise ValueError(f"{where}:{hl}: voltage column header {name!r} is not a "
                                 "frequency; write e.g. 10Hz, 10 or volts@10Hz, or 'volts'.")
            freqs[k] = float(m.group(1))
        if np.unique(freqs[~np.isnan(freqs)]).size != np.sum(~np.isnan(freqs)):
            raise ValueError(f"{where}:{hl}: a frequency appears twice in the header.")
    get = lambda k, d=None: meta.get(k, (None, d))  # noqa: E731
    unit_line, unit = get("units", "V")
    base_line, base_s = get("index_base", "1")
    if base_s not in ("0", "1"):
        raise ValueError(f"{where}:{base_line}: index_base = {base_s!r}; use 0 or 1.")
    base = int(base_s)
    names = ()
    if "electrodes" in meta:
        names = tuple(_split(meta["electrodes"][1].replace(",", " ")))
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"{where}:{meta['electrodes'][0]}: electrode names {dup} appear "
                             "twice.")
    lookup = {n.lower(): i for i, n in enumerate(names)}
    rows = np.empty((len(data), 4), np.int64)
    volts = np.empty((len(data), n_v))
    cols = ("source", "sink", "meas_plus", "meas_minus")
    for r, (lineno, cells) in enumerate(data):
        for c in range(4):
            cell = cells[c]
            try:
                x = float(cell)
            except ValueError:
                if cell.lower() in lookup:
                    rows[r, c] = lookup[cell.lower()] + base
                    continue
                hint = (f"known names: {' '.join(names)}" if names else
                        "list the names in a `# electrodes = ...` line to use names")
                raise ValueError(f"{where}:{lineno}: {cols[c]} {cell!r} is neither an index "
                                 f"nor a known electrode name; {hint}.") from None
            if x != round(x):
                raise ValueError(f"{where}:{lineno}: {cols[c]} {cell!r} is not an integer "
                                 "electrode index.")
            rows[r, c] = int(x)
        for k, cell in enumerate(cells[4:]):
            try:
                volts[r, k] = float(cell)
            except ValueError:
                raise ValueError(f"{where}:{lineno}: voltage {cell!r} (column {k + 5}) is not a "
                                 "number; fix or remove the row.") from None
            if not math.isfinite(volts[r, k]):
                f = "" if np.isnan(freqs[k]) else f" at {freqs[k]:g} Hz"
                raise ValueError(f"{where}:{lineno}: voltage is {cell}{f}; jaxhead fits no NaN/"
                                 "Inf: remove the row from the file (and the protocol) or "
                                 "replace the value.")
    lines = [ln for ln, _ in data]
    rows = _zero_based(rows, base, where, lambda i: f"line {lines[i]}")
    volts = _to_volts(volts, unit, f"{where}:{unit_line}")
    cur_line, cur = get("current_a")
    if current_a is None:
        if cur is None:
            raise ValueError(f"{where}: no `# current_a = <A>` line; add one or pass current_a=.")
        try:
            current_a = float(cur)
        except ValueError:
            raise ValueError(f"{where}:{cur_line}: current_a = {cur!r} is not a number.") from None
    n_elec = len(names) if names else int(rows.max()) + 1
    if names and rows.max() >= n_elec:
        i = int(np.flatnonzero((rows >= n_elec).any(axis=1))[0])
        raise ValueError(f"{where}:{lines[i]}: electrode index {int(rows[i].max()) + base} but "
                         f"`# electrodes` names {n_elec}; add the missing names.")
    pos = None
    if positions:
        if not names:
            raise ValueError(f"{where}: `# position` lines need a `# electrodes = ...` line.")
        unit_p = get("position_units", "mm")[1]
        pos = np.full((n_elec, 3), np.nan)
        for name, (ln, val) in positions.items():
            if name.lower() not in lookup:
                raise ValueError(f"{where}:{ln}: position of unknown electrode {name!r}.")
            try:
                xyz = [float(t) for t in _split(val.replace(",", " "))]
            except ValueError:
                xyz = []
            if len(xyz) != 3 or not np.all(np.isfinite(xyz)):
                raise ValueError(f"{where}:{ln}: position {val!r} is not 3 numbers.")
            pos[lookup[name.lower()]] = xyz
        missing = [names[i] for i in np.flatnonzero(np.isnan(pos[:, 0]))]
        if missing:
            raise ValueError(f"{where}: electrodes {missing} have no `# position` line.")
        pos = _to_mm(pos, unit_p, where)
    return Measurements(rows=rows, voltages=volts.T.copy(), frequencies_hz=freqs,
                        current_a=float(current_a), electrode_names=names, positions_mm=pos,
                        source=where)


def _read_ucl(path: Path, voltages_path, current_a, variable):
    where = str(path)
    try:
        settings = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{where}: not a JSON settings file ({e}).") from e
    if not isinstance(settings, dict):
        raise ValueError(f"{where}: the settings must be a JSON object with Freq, Protocol, "
                         "ElectrodePosition.")
    for key in ("Freq", "Protocol", "ElectrodePosition"):
        if key not in settings:
            raise ValueError(f"{where}: no {key!r} entry (it has {sorted(settings)}); the UCL "
                             "layout needs Freq (Hz), Protocol (n, 4, 1-based), "
                             "ElectrodePosition (n_elec, 3, m).")
    freqs = _numeric(settings["Freq"], f"{where}: Freq").ravel()
    if freqs.size == 0 or not np.all(np.isfinite(freqs) & (freqs > 0)):
        raise ValueError(f"{where}: Freq must be positive frequencies in Hz, got {freqs[:5]}.")
    prot = _numeric(settings["Protocol"], f"{where}: Protocol")
    if prot.ndim != 2 or prot.shape[1] != 4:
        raise ValueError(f"{where}: Protocol has shape {prot.shape}; expected (n_rows, 4) "
                         "[source, sink, meas+, meas-].")
    bad = np.flatnonzero(np.any(prot != np.round(prot), axis=1))
    if bad.size:
        raise ValueError(f"{where}: Protocol row {int(bad[0]) + 1} {prot[bad[0]].tolist()} is "
                         "not integer electrode numbers.")
    pos = _numeric(settings["ElectrodePosition"], f"{where}: ElectrodePosition")
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise ValueError(f"{where}: ElectrodePosition has shape {pos.shape}; expected "
                         "(n_elec, 3) in metres.")
    n_elec = pos.shape[0]
    rows = _zero_based(prot.astype(np.int64), 1, where,
                       lambda i: f"Protocol row {i + 1} (1-based) {prot[i].astype(int).tolist()}")
    high = np.flatnonzero((rows >= n_elec).any(axis=1))
    if high.size:
        i = int(high[0])
        raise ValueError(f"{where}: Protocol row {i + 1} uses electrode {int(rows[i].max()) + 1}"
                         f" but ElectrodePosition has {n_elec} electrodes.")
    names = settings.get("ElectrodeNames", ())
    if names:
        if not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise ValueError(f"{where}: ElectrodeNames must be a list of strings.")
        if len(names) != n_elec:
            raise ValueError(f"{where}: {len(names)} ElectrodeNames for {n_elec} "
                             "ElectrodePosition rows.")
    if current_a is None:
        current_a = settings.get("CurrentA")
        if current_a is None:
            raise ValueError(f"{where}: no 'CurrentA' entry (A); pass current_a= (UCL's "
                             "processed voltages are for the largest injected current).")
    n_rows, n_freq = rows.shape[0], freqs.size
    if voltages_path is not None:
        vpath = Path(voltages_path)
        raw, vwhere = _voltage_array(vpath, variable, n_rows, n_freq), str(vpath)
    elif "Voltages" in settings:
        raw, vwhere = _numeric(settings["Voltages"], f"{where}: Voltages"), f"{where}: Voltages"
    elif path.with_suffix(".mat").is_file():
        vpath = path.with_suffix(".mat")
        raw, vwhere = _voltage_array(vpath, variable, n_rows, n_freq), str(vpath)
    else:
        raise ValueError(f"{where}: no voltages: pass voltages_path= (.mat or .json), add a "
                         f"'Voltages' entry, or put {path.with_suffix('.mat').name} beside it.")
    volts = _orient(raw, n_rows, n_freq, vwhere)
    nonfinite = np.argwhere(~np.isfinite(volts))
    if nonfinite.size:
        r, f = nonfinite[0]
        raise ValueError(f"{vwhere}: voltage of Protocol row {r + 1} at {freqs[f]:g} Hz is "
                         f"{volts[r, f]} ({len(nonfinite)} non-finite values); jaxhead fits "
                         "no NaN: drop those rows from the Protocol and the voltages.")
    return Measurements(rows=rows, voltages=_to_volts(volts.T, "mV", vwhere),
                        frequencies_hz=freqs.astype(np.float64), current_a=float(current_a),
                        electrode_names=tuple(names), positions_mm=_to_mm(pos, "m", where),
                        source=where)


def _numeric(value, where) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: not a numeric array: {_first_non_number(value)}.") from None
    return a


def _first_non_number(value) -> str:
    """Where a nested list stops being a rectangular array of numbers (1-based row, column)."""
    if not isinstance(value, (list, tuple)):
        return f"{value!r} is not a number or a list of numbers; write numbers"
    lengths = {len(v) for v in value if isinstance(v, (list, tuple))}
    for i, row in enumerate(value, 1):
        for j, x in enumerate(row if isinstance(row, (list, tuple)) else [row], 1):
            if isinstance(x, bool) or not isinstance(x, (int, float)):
                at = f"row {i}, column {j}" if isinstance(row, (list, tuple)) else f"entry {i}"
                return f"{at} is {x!r}, not a number; write the number (or drop the row)"
    if len(lengths) > 1:
        return (f"rows of different lengths {sorted(lengths)}; every row needs the same number "
                "of entries")
    return "not numbers; write numbers only"


def _orient(raw: np.ndarray, n_rows: int, n_freq: int, where: str) -> np.ndarray:
    """Voltages as (n_rows, n_freq) from (n_rows, n_freq), (n_freq, n_rows) or (n_rows,)."""
    a = np.asarray(raw, dtype=np.float64)
    if a.ndim == 1 and n_freq == 1:
        a = a[:, None]
    if a.ndim == 2 and a.shape == (n_rows, n_freq):
        return a
    if a.ndim == 2 and a.shape == (n_freq, n_rows):
        return a.T
    raise ValueError(f"{where}: voltages have shape {a.shape}, but the Protocol has {n_rows} "
                     f"rows and Freq {n_freq} frequencies; expected ({n_rows}, {n_freq}). "
                     "Are the protocol and the voltages from the same recording?")


def _voltage_array(vpath: Path, variable, n_rows, n_freq) -> np.ndarray:
    if not vpath.is_file():
        raise FileNotFoundError(f"{vpath}: no such file; check voltages_path.")
    ext = vpath.suffix.lower()
    if ext == ".json":
        try:
            d = json.loads(vpath.read_text(encoding="utf-8"))
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise ValueError(f"{vpath}: not JSON ({e}).") from e
        arrays = d if isinstance(d, dict) else {"(top level)": d}
    elif ext == ".mat":
        arrays = _mat_arrays(vpath)
    else:
        raise ValueError(f"{vpath}: voltages must be a .mat (v5 or v7.3) or .json file.")
    if variable is not None:
        if variable not in arrays:
            raise ValueError(f"{vpath}: no variable {variable!r}; it has {sorted(arrays)}.")
        return _numeric(arrays[variable], f"{vpath}: {variable}")
    numeric = {}
    for k, v in arrays.items():
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if a.ndim in (1, 2) and a.size > 1:
            numeric[k] = a
    # the one numeric array (its shape is checked by _orient), else the one of the right size
    fits = numeric if len(numeric) == 1 else {
        k: a for k, a in numeric.items() if a.size == n_rows * n_freq}
    if len(fits) != 1:
        what = "none" if not fits else f"several: {sorted(fits)}"
        raise ValueError(f"{vpath}: expected one numeric array of {n_rows} x {n_freq} voltages "
                         f"(mV), found {what} (variables: {sorted(arrays)}); pass variable=.")
    return next(iter(fits.values()))


def _mat_arrays(path: Path) -> dict:
    """Variables of a MATLAB file, v5 (scipy.io) or v7.3 (HDF5, h5py), as MATLAB shapes."""
    try:
        d = scipy.io.loadmat(path, appendmat=False)
        return {k: v for k, v in d.items() if not k.startswith("__")}
    except NotImplementedError:  # scipy: "Please use HDF reader for matlab v7.3 files"
        pass
    except Exception as e:  # MatReadError, ValueError, ... on damaged files
        raise ValueError(f"{path}: could not be read as a MATLAB .mat file "
                         f"({type(e).__name__}: {e}).") from e
    return mat73_arrays(path)


def mat73_arrays(path) -> dict:
    """Numeric datasets of a MATLAB v7.3 (HDF5) file, transposed to MATLAB's (row, col) shape.

    MATLAB writes arrays column-major, so h5py sees an (m, n) MATLAB matrix as (n, m); every
    dataset is transposed back here (the one place). Groups (structs) are flattened with
    dotted names ("materials.ref"); cell arrays of strings (object references to uint16 char
    arrays) become lists of str.
    """
    out = {}
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise ValueError(f"{path}: not a MATLAB v7.3 (HDF5) file either ({e}).") from e
    with f:
        def visit(name, obj):
            if not isinstance(obj, h5py.Dataset) or name.startswith("#refs#"):
                return
            cls = obj.attrs.get("MATLAB_class", b"")
            cls = cls.decode() if isinstance(cls, bytes) else str(cls)
            key = name.replace("/", ".")
            if obj.dtype == h5py.ref_dtype:
                vals = []
                for ref in np.asarray(obj).T.ravel():
                    tgt = f[ref]
                    vals.append("".join(map(chr, np.asarray(tgt).ravel())))
                out[key] = vals
            elif cls == "char":
                out[key] = "".join(map(chr, np.asarray(obj).ravel()))
            else:
                out[key] = np.asarray(obj).T
        f.visititems(visit)
    return out


# ---------------------------------------------------------------------------------------------
# Writing


def save_measurements(path, m: Measurements, *, units: str = "V", one_based: bool = True) -> None:
    """Write a `Measurements` as the CSV layout (atomic); `load_measurements` reads it back.

    Arguments:
        path: output file.
        m: the recording.
        units: voltage unit of the file: V, mV or uV.
        one_based: electrode indices from 1 (default) or 0.
    """
    scale = 1.0 / _to_volts(1.0, units, str(path))
    base = 1 if one_based else 0
    lines = [f"# current_a = {m.current_a!r}", f"# units = {units}", f"# index_base = {base}"]
    if m.electrode_names:
        lines.append("# electrodes = " + " ".join(m.electrode_names))
        if m.positions_mm is not None:
            lines += [f"# position {n} = {float(p[0])!r} {float(p[1])!r} {float(p[2])!r}"
                      for n, p in zip(m.electrode_names, m.positions_mm)]
    f = m.frequencies_hz
    if np.all(np.isnan(f)) and f.size == 1:
        cols = ["volts"]
    elif np.any(np.isnan(f)):
        raise ValueError("`m.frequencies_hz` mixes known and unknown (NaN) frequencies.")
    else:
        cols = [f"{float(x)!r}Hz" for x in f]
    lines.append(",".join(["source", "sink", "meas_plus", "meas_minus", *cols]))
    v = m.voltages.T * scale
    for r, row in zip(m.rows + base, v):
        lines.append(",".join(str(int(i)) for i in r) + "," + ",".join(f"{x:.12e}" for x in row))
    with atomic_write_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write("\n".join(lines) + "\n")
