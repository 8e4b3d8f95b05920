"""Injection/measurement protocols: rows of [source, sink, meas+, meas-].  [host]

A protocol row says: inject `current_a` amperes into electrode `source` and out of `sink`, and
measure the voltage V[meas+] - V[meas-]. This is the format of UCL's head-EIT protocol files
(an (n_rows, 4) matrix [inj+, inj-, meas+, meas-], 1-based in Matlab). Inside jaxhead all
electrode indices are 0-based (electrode i is `Electrodes.centres[i]`); CSV files are 1-based
by default, as UCL writes them (`one_based=False` reads or writes 0-based files).

Injections are ordered (source, sink) pairs: (a, b) and (b, a) are distinct injections (the
second is the negated current pattern), kept in order of first appearance.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Literal

import equinox as eqx
import numpy as np

from ._files import atomic_write_path

#: Default injected current in A: 100 uA. IEC 60601-1 limits the patient auxiliary current to
#: 100 uA below 1 kHz (rising as f/1 kHz above it, to 10 mA at 100 kHz), so 100 uA is within
#: the limit at any frequency. Voltages are linear in the current: pass the current your
#: system injects (head-EIT systems use tens of uA to ~1 mA depending on frequency).
DEFAULT_CURRENT_A = 100e-6

_HEADER = "source,sink,meas_plus,meas_minus"


class Protocol(eqx.Module):
    """A list of drive/measurement electrode quadruples and the drive current.

    Arguments:
        rows: (n_rows, 4) int64, 0-based electrode indices [source, sink, meas+, meas-]:
            current `current_a` enters at `source` and leaves at `sink`; the row's datum is
            V[meas+] - V[meas-] in volts.
        current_a: injected current in A (> 0).
    """

    rows: np.ndarray
    current_a: float = eqx.field(static=True, default=DEFAULT_CURRENT_A)

    def __init__(self, rows, current_a: float = DEFAULT_CURRENT_A):
        r = np.asarray(rows)
        if r.size and not np.issubdtype(r.dtype, np.integer):
            if not np.issubdtype(r.dtype, np.number) or not np.all(r == np.round(r)):
                raise ValueError(
                    f"`rows` must hold integer electrode indices, got dtype {r.dtype}.")
        self.rows = r.astype(np.int64).reshape(r.shape)
        self.current_a = float(current_a)

    def __check_init__(self):
        r = self.rows
        if r.ndim != 2 or r.shape[1] != 4 or r.shape[0] == 0:
            raise ValueError(
                f"`rows` must have shape (n_rows, 4) = [source, sink, meas+, meas-], n_rows >= 1; "
                f"got {r.shape}.")
        if r.min() < 0:
            bad = np.flatnonzero((r < 0).any(axis=1))
            raise ValueError(
                f"`rows` {bad[:10].tolist()} have negative electrode indices; indices are "
                "0-based (use Protocol.from_csv(..., one_based=True) for 1-based files).")
        same = np.flatnonzero(r[:, 0] == r[:, 1])
        if same.size:
            raise ValueError(f"`rows` {same[:10].tolist()} have source == sink; a drive pair "
                             "needs two different electrodes.")
        same = np.flatnonzero(r[:, 2] == r[:, 3])
        if same.size:
            raise ValueError(f"`rows` {same[:10].tolist()} have meas+ == meas-; a measurement "
                             "needs two different electrodes.")
        if not np.isfinite(self.current_a) or self.current_a <= 0:
            raise ValueError(f"`current_a` must be finite and > 0 A, got {self.current_a}.")

    @property
    def n_rows(self) -> int:
        return self.rows.shape[0]

    @property
    def injections(self) -> np.ndarray:
        """Unique (source, sink) pairs in order of first appearance, (n_inj, 2) int64."""
        return self._drives()[0]

    @property
    def drive_index(self) -> np.ndarray:
        """Index into `injections` of each row's drive pair, (n_rows,) int64."""
        return self._drives()[1]

    @property
    def n_inj(self) -> int:
        return self.injections.shape[0]

    @property
    def measurements(self) -> np.ndarray:
        """(meas+, meas-) of each row, (n_rows, 2) int64."""
        return self.rows[:, 2:]

    def _drives(self) -> tuple[np.ndarray, np.ndarray]:
        pairs = self.rows[:, :2]
        uniq, first, inv = np.unique(pairs, axis=0, return_index=True, return_inverse=True)
        order = np.argsort(first)  # unique pairs sorted by first appearance
        rank = np.empty_like(order)
        rank[order] = np.arange(order.size)
        return uniq[order], rank[inv.ravel()].astype(np.int64)

    def check(self, n_elec: int) -> Protocol:
        """Raise ValueError unless every index is < n_elec; returns self."""
        if int(n_elec) < 2:
            raise ValueError(f"`n_elec` must be >= 2, got {n_elec}.")
        bad = np.flatnonzero((self.rows >= n_elec).any(axis=1))
        if bad.size:
            raise ValueError(
                f"protocol rows {bad[:10].tolist()} use electrode indices up to "
                f"{self.rows.max()} but there are {n_elec} electrodes (0-based indices "
                f"0..{n_elec - 1}); is the protocol 1-based or meant for another montage?")
        return self

    @classmethod
    def from_csv(cls, path, *, current_a: float | None = None, one_based: bool = True) -> Protocol:
        """Read a protocol from a CSV (or whitespace) file of 4 integer columns.

        A header line (any non-numeric first line) is skipped; a comment line
        ``# current_a = <A>`` (written by `to_csv`) sets the current unless `current_a` is given.

        Arguments:
            path: file with columns source, sink, meas+, meas- (UCL order).
            current_a: injected current in A; default: the file's comment, else 100 uA.
            one_based: indices in the file start at 1 (UCL/Matlab; default) or at 0.
        """
        lines, file_current = _read_table(path)
        data = []
        for lineno, vals, line in lines:
            if len(vals) != 4:
                raise ValueError(f"{path}:{lineno}: expected 4 columns (source, sink, meas+, "
                                 f"meas-), got {len(vals)}: {line!r}.")
            data.append(vals)
        if not data:
            raise ValueError(f"{path}: no protocol rows found.")
        rows = np.asarray(data)
        if not np.all(rows == np.round(rows)):
            raise ValueError(f"{path}: electrode indices must be integers.")
        rows = rows.astype(np.int64)
        if one_based:
            if rows.min() < 1:
                raise ValueError(f"{path}: has index {rows.min()} but one_based=True; pass "
                                 "one_based=False for 0-based files.")
            rows = rows - 1
        cur = current_a if current_a is not None else (
            file_current if file_current is not None else DEFAULT_CURRENT_A)
        return cls(rows, cur)

    def to_csv(self, path, *, one_based: bool = True) -> None:
        """Write the protocol as CSV (header, ``# current_a = ...`` line, 4 int columns).

        Arguments:
            path: output file (written atomically).
            one_based: write 1-based indices (UCL/Matlab convention; default) or 0-based.
        """

        rows = self.rows + (1 if one_based else 0)
        body = "\n".join(",".join(str(int(v)) for v in r) for r in rows)
        text = f"# current_a = {self.current_a!r}\n{_HEADER}\n{body}\n"
        with atomic_write_path(path) as tmp:
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(text)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _read_table(path) -> tuple[list[tuple[int, list[float], str]], float | None]:
    """Numeric lines of a CSV/whitespace file: [(line number, values, text)], current_a comment.

    Blank lines and ``#`` comments are skipped (``# current_a = <A>`` is returned); a
    non-numeric line before the first numeric one is a header and skipped; one after it is an
    error naming the line.
    """
    text = open(os.fspath(path), encoding="utf-8").read()
    out, file_current = [], None
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s.startswith("#"):
            key, _, val = s[1:].partition("=")
            if key.strip() == "current_a":
                file_current = float(val)
            continue
        fields = s.replace(",", " ").replace(";", " ").split()
        try:
            vals = [float(p) for p in fields]
        except ValueError:
            if not out and not any(_is_number(p) for p in fields):  # a header: no numbers at all
                continue
            bad = [p for p in fields if not _is_number(p)]
            raise ValueError(f"{path}:{lineno}: not numbers: {bad} in {line!r}; fix the value "
                             "(a header line holds names only, no numbers).") from None
        out.append((lineno, vals, line))
    return out, file_current


def save_voltages(path, protocol: Protocol, volts, *, one_based: bool = True) -> None:
    """Write measured or simulated voltages with their protocol rows, one row per line.

    Columns source, sink, meas_plus, meas_minus (1-based by default, as `Protocol.to_csv`),
    volts; a ``# current_a = ...`` comment line first. `load_voltages` reads it back.

    Arguments:
        path: output file (written atomically).
        protocol: the `Protocol` the voltages belong to.
        volts: (n_rows,) voltages in V, in protocol order.
        one_based: electrode indices from 1 (default) or 0.
    """

    v = np.asarray(volts, dtype=np.float64)
    if v.shape != (protocol.n_rows,):
        raise ValueError(f"`volts` has shape {v.shape}; the protocol has {protocol.n_rows} rows.")
    rows = protocol.rows + (1 if one_based else 0)
    body = "\n".join(",".join(str(int(i)) for i in r) + f",{x:.9e}" for r, x in zip(rows, v))
    with atomic_write_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as f:
            f.write(f"# current_a = {protocol.current_a!r}\n{_HEADER},volts\n{body}\n")


def load_voltages(path, protocol: Protocol, *, one_based: bool = True) -> np.ndarray:
    """Read voltages for `protocol` from a CSV (or whitespace) file.

    Either five columns, source, sink, meas+, meas-, volts (as `save_voltages` and the forward
    stage's voltages.csv write), whose electrode columns must match the protocol's rows line by
    line, or one column of volts in protocol order. A header line and ``#`` comments are
    skipped; a ``# current_a = ...`` comment must agree with the protocol's current.

    Arguments:
        path: the file.
        protocol: the `Protocol` the voltages were measured with.
        one_based: the file's electrode indices start at 1 (default) or 0.

    Returns:
        (n_rows,) float64 voltages in V.
    """
    lines, file_current = _read_table(path)
    data = []
    for lineno, vals, line in lines:
        if len(vals) not in (1, 5) or (data and len(vals) != len(data[0][1])):
            raise ValueError(f"{path}:{lineno}: expected 5 columns (source, sink, meas+, meas-, "
                             f"volts) or 1 (volts) on every line, got {len(vals)}: {line!r}.")
        data.append((lineno, vals))
    if len(data) != protocol.n_rows:
        raise ValueError(f"{path}: {len(data)} voltages, but the protocol has {protocol.n_rows} "
                         "rows; measure (or simulate) with the configured protocol.")
    if file_current is not None and not math.isclose(file_current, protocol.current_a,
                                                     rel_tol=1e-9):
        raise ValueError(f"{path}: current_a = {file_current} A, but the protocol injects "
                         f"{protocol.current_a} A; set the protocol's current to the file's.")
    table = np.asarray([vals for _, vals in data], dtype=np.float64)
    if table.shape[1] == 5:
        want = protocol.rows + (1 if one_based else 0)
        bad = np.flatnonzero(np.any(table[:, :4] != want, axis=1))
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"{path}:{data[i][0]}: electrodes {table[i, :4].astype(int).tolist()} differ from "
                f"protocol row {i} {want[i].tolist()} ({bad.size} rows differ; indices are "
                f"{'1' if one_based else '0'}-based); reorder the file to the protocol.")
    volts = table[:, -1]
    if not np.all(np.isfinite(volts)):
        raise ValueError(f"{path}: voltages contain NaN or Inf (line "
                         f"{data[int(np.flatnonzero(~np.isfinite(volts))[0])][0]}).")
    return volts


def _adjacent_meas(n_elec: int, exclude) -> list[tuple[int, int]]:
    """Adjacent pairs (j, j+1 mod n) that use none of the electrodes in `exclude`."""
    ex = set(int(e) for e in exclude)
    return [(j, (j + 1) % n_elec) for j in range(n_elec)
            if j not in ex and (j + 1) % n_elec not in ex]


def _check_n(n_elec, least: int) -> int:
    if isinstance(n_elec, bool) or not isinstance(n_elec, (int, np.integer)) or n_elec < least:
        raise ValueError(f"`n_elec` must be an int >= {least}, got {n_elec!r}.")
    return int(n_elec)


def _build(drives, n_elec: int, current_a: float) -> Protocol:
    rows = [(s, k, mp, mm) for s, k in drives for mp, mm in _adjacent_meas(n_elec, (s, k))]
    return Protocol(np.asarray(rows, dtype=np.int64), current_a).check(n_elec)


def adjacent(n_elec: int, *, current_a: float = DEFAULT_CURRENT_A) -> Protocol:
    """Adjacent drive, adjacent measurement (Sheffield / EIDORS ``{'ad'}, {'ad'}``).

    Drives (i, i+1 mod n) for i = 0..n-1; for each, measurements V_j - V_{j+1 mod n} on every
    adjacent pair not touching a drive electrode (EIDORS ``no_meas_current``: the voltage on a
    current-carrying electrode includes its contact impedance), so n (n - 3) rows.

    Arguments:
        n_elec: number of electrodes (>= 4), in ring order.
        current_a: injected current in A.
    """
    n = _check_n(n_elec, 4)
    return _build([(i, (i + 1) % n) for i in range(n)], n, current_a)


def opposite(n_elec: int, *, current_a: float = DEFAULT_CURRENT_A) -> Protocol:
    """Polar/opposite drive (i, i + n//2), adjacent measurements not on drive electrodes.

    For even n the n/2 pairs (i, i + n/2), i < n/2 (the other half would only negate them);
    for odd n all n pairs (i, i + (n-1)/2 mod n), which are distinct. Each drive measures the
    n - 4 adjacent pairs that avoid both drive electrodes.

    Arguments:
        n_elec: number of electrodes (>= 5), in ring order.
        current_a: injected current in A.
    """
    n = _check_n(n_elec, 5)
    k = n // 2
    drives = [(i, i + k) for i in range(k)] if n % 2 == 0 else [(i, (i + k) % n) for i in range(n)]
    return _build(drives, n, current_a)


def pair_drive(n_elec: int, source: int, sink: int, *,
               current_a: float = DEFAULT_CURRENT_A) -> Protocol:
    """One drive pair, and every adjacent pair (j, j+1 mod n) that avoids it as measurement.

    Arguments:
        n_elec: number of electrodes (>= 4).
        source, sink: 0-based drive electrodes (different).
        current_a: injected current in A.
    """
    n = _check_n(n_elec, 4)
    for name, v in (("source", source), ("sink", sink)):
        if not 0 <= int(v) < n:
            raise ValueError(f"`{name}` = {v} is not an electrode index 0..{n - 1}.")
    if int(source) == int(sink):
        raise ValueError(f"`source` and `sink` are both {source}; use two electrodes.")
    return _build([(int(source), int(sink))], n, current_a)


@dataclass(frozen=True, kw_only=True)
class ProtocolConfig:
    """Settings of :func:`protocol_from_config` (the pipeline's protocol stage).

    Arguments:
        kind: "adjacent", "opposite", "pair" (one drive pair, `source` and `sink`) or "csv"
            (read `csv_path`).
        current_a: injected current in A (for "csv": overrides the file's value if set).
        source, sink: 0-based drive electrodes for kind "pair".
        csv_path: protocol file for kind "csv" (columns source, sink, meas+, meas-).
        one_based: the CSV's indices start at 1 (UCL/Matlab) or 0.
    """

    kind: Literal["adjacent", "opposite", "pair", "csv"] = "adjacent"
    current_a: float | None = DEFAULT_CURRENT_A
    source: int = 0
    sink: int = 1
    csv_path: str | None = None
    one_based: bool = True

    def __post_init__(self):
        if self.kind not in ("adjacent", "opposite", "pair", "csv"):
            raise ValueError(f"`kind` = {self.kind!r}; choose adjacent, opposite, pair or csv.")
        if self.current_a is not None and (
                isinstance(self.current_a, bool) or not isinstance(self.current_a, (int, float))
                or not math.isfinite(self.current_a) or self.current_a <= 0):
            raise ValueError(f"`current_a` must be a positive number of A, got {self.current_a!r}.")
        if self.current_a is None and self.kind != "csv":
            raise ValueError("`current_a` may be None only for kind 'csv' (current from the file).")
        if self.kind == "csv" and not self.csv_path:
            raise ValueError("kind 'csv' needs `csv_path`.")
        if self.kind == "pair" and self.source == self.sink:
            raise ValueError(f"`source` and `sink` are both {self.source}; use two electrodes.")


def protocol_from_config(n_elec: int, cfg: ProtocolConfig = ProtocolConfig()) -> Protocol:
    """Build the protocol a `ProtocolConfig` describes, checked against `n_elec`."""
    if cfg.kind == "csv":
        return Protocol.from_csv(cfg.csv_path, current_a=cfg.current_a,
                                 one_based=cfg.one_based).check(n_elec)
    if cfg.kind == "adjacent":
        return adjacent(n_elec, current_a=cfg.current_a)
    if cfg.kind == "opposite":
        return opposite(n_elec, current_a=cfg.current_a)
    return pair_drive(n_elec, cfg.source, cfg.sink, current_a=cfg.current_a)


def reference_protocol(n_elec: int, reference: int, injections=None, *,
                       include_injecting: bool = False,
                       current_a: float = DEFAULT_CURRENT_A) -> Protocol:
    """Every electrode measured against one common reference electrode that never injects.

    The layout of UCL's head-EIT recordings (Goren et al. 2018, Sci. Data 5:180112: 33
    electrodes, 31 injection pairs, each measured on the 30 non-injecting electrodes against
    the reference, 930 rows). Rows are grouped by injection, in injection order, then electrode
    order. Voltages against a reference whose true potential is unknown are fitted with a free
    offset per injection (`fit_conductivities(..., offsets="per_injection")`).

    Arguments:
        n_elec: number of electrodes, the reference included (>= 4).
        reference: 0-based index of the reference electrode.
        injections: (n_inj, 2) 0-based [source, sink] pairs, none using the reference; default
            the ring of adjacent pairs over the other electrodes (i, next non-reference i).
        include_injecting: also measure the two injecting electrodes (their voltage includes
            the contact impedance's drop I z / |e|: the only rows that inform per-electrode
            contact impedances). UCL's pipeline discards them.
        current_a: injected current in A.

    Returns:
        A `Protocol` with meas- = `reference` on every row.
    """
    n = _check_n(n_elec, 4)
    if isinstance(reference, bool) or not isinstance(reference, (int, np.integer)) \
            or not 0 <= reference < n:
        raise ValueError(f"`reference` = {reference!r} is not an electrode index 0..{n - 1}.")
    others = [e for e in range(n) if e != reference]
    if injections is None:
        inj = np.asarray([(others[i], others[(i + 1) % len(others)])
                          for i in range(len(others))], dtype=np.int64)
    else:
        inj = np.asarray(injections)
        if inj.ndim != 2 or inj.shape[1] != 2 or inj.shape[0] == 0 \
                or not np.issubdtype(inj.dtype, np.integer):
            raise ValueError(f"`injections` must be (n_inj, 2) integer [source, sink] pairs, "
                             f"got shape {inj.shape} {inj.dtype}.")
        bad = np.flatnonzero((inj < 0).any(1) | (inj >= n).any(1) | (inj[:, 0] == inj[:, 1]))
        if bad.size:
            raise ValueError(f"`injections` row {int(bad[0])} {inj[bad[0]].tolist()}: use two "
                             f"different electrodes in 0..{n - 1}.")
        uses = np.flatnonzero((inj == reference).any(1))
        if uses.size:
            raise ValueError(f"`injections` row {int(uses[0])} {inj[uses[0]].tolist()} uses the "
                             f"reference electrode {reference}; the reference never injects.")
    rows = []
    for s, k in inj.tolist():
        for m in others:
            if include_injecting or m not in (s, k):
                rows.append((s, k, m, reference))
    return Protocol(np.asarray(rows, dtype=np.int64), current_a).check(n)


def common_reference(protocol: Protocol) -> int | None:
    """The meas- electrode shared by every row (a reference-electrode protocol), else None."""
    m = np.unique(protocol.rows[:, 3])
    return int(m[0]) if m.size == 1 else None
