"""Probes and selections read from files: element positions, channel maps, MUST parameter sets.

:func:`load_probe` reads a probe, :func:`read_aperture` a probe with its selection (an
:class:`Aperture`: transmit and receive elements, apodization weights, scanner channels), from

* ``.csv``: one row per element, a header row naming the columns; ``x`` and ``y`` (metres) are
  required, ``element``, ``ix``, ``iy``, ``channel``, ``transmit``, ``receive`` and ``weight``
  optional (the columns ``arraysel export`` writes). Lines starting with ``#`` before the header
  may give the probe's fields, one ``# key: value`` a line (``value`` in JSON: ``# fc: 3e6``,
  ``# blank_rows: [8, 17, 26]``);
* ``.json``: an ``arraysel export`` channel map (``{"probe": {...}, "elements": [...]}``);
* ``.npy``: an (Ne, 2) array of x, y (an (Ne, 3) one with z = 0, or MUST's 2 x Ne);
* ``.npz``: a MUST parameter set (``elements``, 2 x Ne, and the other fields below) or an array
  ``positions`` (Ne, 2) with the probe's fields as scalars;
* ``.mat``: a MUST/PyMUST parameter set (``scipy.io.loadmat``): ``elements`` (2 x Ne: x; y in
  metres), ``width``, ``height``, ``fc``, ``bandwidth`` (default 75), ``baffle`` (default
  ``'soft'``), the selection in ``TXapodization`` and ``RXapodization`` (1 x Ne, default all
  ones), and the fields ``arraysel export`` adds (``nx``, ``ny``, ``pitch_x``, ``pitch_y``,
  ``blank_rows``, ``blank_columns``, ``channels``, ``probe_name``); a grid without ``elements``
  is read from ``nx``, ``ny``, ``pitch_x``, ``pitch_y`` (and its blank rows and columns).

Fields a file does not give come from the keyword arguments (a scene's ``[probe]`` keys), which
also replace the file's; ``width``, ``height`` and ``fc`` are required, ``name`` defaults to the
file's stem. The probe is a :class:`~arraysel.physics.matrix_probes.MatrixProbe` when the file
gives its grid (``nx``, ``ny``, ``pitch_x``, ``pitch_y``) or when the positions form one
(:func:`~arraysel.physics.matrix_probes.probe_from_positions`), a
:class:`~arraysel.physics.matrix_probes.PlanarProbe` otherwise. Every problem is one
:class:`~arraysel.errors.ParameterError` line naming the file and what is wrong.
"""
from __future__ import annotations

import csv
import io
import json
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from arraysel.errors import ArrayselError, ParameterError
from arraysel.physics.matrix_probes import MatrixProbe, PlanarProbe, POSITION_TOL, probe_from_positions

__all__ = ["Aperture", "load_probe", "read_aperture", "PROBE_FILE_TYPES", "PROBE_FIELDS", "GRID_FIELDS",
           "CHANNEL_COLUMNS"]

#: the file types :func:`load_probe` reads
PROBE_FILE_TYPES = (".csv", ".json", ".npy", ".npz", ".mat")
#: the fields of every planar probe a file or the keyword arguments may give
PROBE_FIELDS = ("name", "width", "height", "fc", "bandwidth", "baffle")
#: the fields of a grid
GRID_FIELDS = ("nx", "ny", "pitch_x", "pitch_y", "blank_rows", "blank_columns")
#: the columns of a channel map, in order
CHANNEL_COLUMNS = ("channel", "element", "ix", "iy", "x", "y", "transmit", "receive", "weight")


def _mask(name: str, value: Any, n: int) -> np.ndarray:
    """A boolean (Ne,) mask from a mask or a list of element indices."""
    a = np.asarray(value)
    if a.dtype == bool and a.shape == (n,):
        return a.copy()
    idx = a.reshape(-1)
    if idx.size and (not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= n):
        raise ParameterError(f"{name}: element indices must be integers in [0, {n - 1}] (or a boolean mask of "
                             f"{n}), got {value!r}"[:300])
    if np.unique(idx).size != idx.size:
        raise ParameterError(f"{name}: repeated element index")
    out = np.zeros(n, dtype=bool)
    out[idx.astype(np.int64)] = True
    return out


@dataclass(frozen=True, eq=False)
class Aperture:
    """A probe with a selection as a scanner drives it.

    ``transmit``, ``receive``: boolean (Ne,), the elements that transmit and that receive;
    ``weights``: float64 (Ne,), the apodization of each active element (> 0; 0 on inactive
    elements), applied in transmit where ``transmit`` and in receive where ``receive``;
    ``channels``: int64 (Ne,), the scanner channel of each element (-1: none). Elements that
    transmit share no channel, nor do elements that receive. Build one with :meth:`of`.
    """

    probe: "MatrixProbe | PlanarProbe"
    transmit: np.ndarray
    receive: np.ndarray
    weights: np.ndarray
    channels: np.ndarray

    @classmethod
    def of(cls, probe, elements=None, *, transmit=None, receive=None, weights=None, channels=None) -> "Aperture":
        """The aperture of ``elements`` (indices or a boolean mask; transmit and receive), or of
        separate ``transmit`` and ``receive`` selections (each defaults to ``elements``).

        ``weights``: one per element (Ne values; those of inactive elements are ignored) or one
        per active element in element order; default 1. An active element must have a weight
        > 0. ``channels``: the scanner channel of every element (Ne integers, -1 for none, e.g.
        from a channel-group map); default: the active elements numbered 0, 1, ... in element
        order, the others -1.
        """
        if not isinstance(probe, (MatrixProbe, PlanarProbe)):
            raise ParameterError(f"probe must be a MatrixProbe or a PlanarProbe, got {type(probe).__name__}")
        n = probe.n_elements
        if elements is None and (transmit is None or receive is None):
            raise ParameterError("give the elements, or both transmit and receive")
        both = None if elements is None else _mask("elements", elements, n)
        tx = both if transmit is None else _mask("transmit", transmit, n)
        rx = both if receive is None else _mask("receive", receive, n)
        active = tx | rx
        if not active.any():
            raise ParameterError("the selection holds no element")
        w = _weights(weights, active)
        if channels is None:
            ch = np.full(n, -1, dtype=np.int64)
            ch[active] = np.arange(int(active.sum()))
        else:
            ch = np.asarray(channels)
            if ch.shape != (n,) or not np.issubdtype(ch.dtype, np.integer) or ch.min(initial=0) < -1:
                raise ParameterError(f"channels must be {n} integers >= -1 (-1: no channel), got shape {ch.shape}")
            ch = ch.astype(np.int64)
        out = cls(probe, tx.copy(), rx.copy(), w, ch)
        out.check()
        return out

    def check(self) -> None:
        """Refuse channels an active element lacks or two elements of one aperture share."""
        for what, m in (("transmit", self.transmit), ("receive", self.receive)):
            ch = self.channels[m]
            if (ch < 0).any():
                e = int(np.flatnonzero(m)[np.argmax(ch < 0)])
                raise ParameterError(f"channels: element {e} is active ({what}) but has no channel")
            vals, counts = np.unique(ch, return_counts=True)
            if (counts > 1).any():
                c = int(vals[np.argmax(counts > 1)])
                es = np.flatnonzero(m & (self.channels == c)).tolist()
                raise ParameterError(f"channels: elements {es} both {what} on channel {c}; a channel drives one "
                                     "element at a time")

    @property
    def active(self) -> np.ndarray:
        """Boolean (Ne,): the elements that transmit or receive."""
        return self.transmit | self.receive

    @property
    def tx_apodization(self) -> np.ndarray:
        """float64 (Ne,): the transmit apodization, ``weights`` where ``transmit``, else 0."""
        return np.where(self.transmit, self.weights, 0.0)

    @property
    def rx_apodization(self) -> np.ndarray:
        """float64 (Ne,): the receive apodization, ``weights`` where ``receive``, else 0."""
        return np.where(self.receive, self.weights, 0.0)

    def same_as(self, other: "Aperture") -> bool:
        """The same probe, apertures, weights (to 1e-12 relative) and channels."""
        return (self.probe == other.probe and np.array_equal(self.transmit, other.transmit)
                and np.array_equal(self.receive, other.receive)
                and np.allclose(self.weights, other.weights, rtol=1e-12, atol=0)
                and np.array_equal(self.channels, other.channels))


def _weights(weights, active: np.ndarray) -> np.ndarray:
    n, k = active.size, int(active.sum())
    if weights is None:
        return active.astype(np.float64)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    if w.size == k and k != n:
        full = np.zeros(n)
        full[active] = w
        w = full
    elif w.size != n:
        raise ParameterError(f"weights: give {n} values (one per element) or {k} (one per active element), "
                             f"got {w.size}")
    if not np.isfinite(w).all() or (w < 0).any():
        raise ParameterError("weights must be finite and >= 0")
    if (w[active] <= 0).any():
        e = int(np.flatnonzero(active & (w <= 0))[0])
        raise ParameterError(f"weights: element {e} is active but its weight is 0; leave it out of the selection")
    return np.where(active, w, 0.0)


# ---------------------------------------------------------------------- reading
def load_probe(path: "str | os.PathLike", **fields: Any) -> "MatrixProbe | PlanarProbe":
    """The probe of a probe file (see the module docstring); ``fields`` fill in or replace the
    file's (``name``, ``width``, ``height``, ``fc``, ``bandwidth``, ``baffle``)."""
    return _read(path, fields)[0]


def read_aperture(path: "str | os.PathLike", **fields: Any) -> Aperture:
    """The probe and its selection from a channel map (.csv, .json) or a MUST parameter set
    (.mat, .npz), as :func:`arraysel.report.export.export_selection` writes them."""
    probe, sel = _read(path, fields)
    if sel is None:
        raise ParameterError(f"{os.fspath(path)}: the file holds a probe but no selection (a channel map's "
                             "transmit and receive columns, or a MUST parameter set's TXapodization)")
    try:
        return Aperture.of(probe, transmit=sel["transmit"], receive=sel["receive"], weights=sel["weights"],
                           channels=sel.get("channels"))
    except ParameterError as exc:
        raise ParameterError(f"{os.fspath(path)}: {exc}") from None


def _read(path, fields: dict) -> tuple:
    path = os.fspath(path)
    bad = [k for k in fields if k not in PROBE_FIELDS]
    if bad:
        raise ParameterError(f"probe field {bad[0]!r} cannot be given with a probe file; allowed: {list(PROBE_FIELDS)} "
                             "(the geometry comes from the file)")
    ext = os.path.splitext(path)[1].lower()
    if ext not in PROBE_FILE_TYPES:
        raise ParameterError(f"{path}: a probe file must end with one of {', '.join(PROBE_FILE_TYPES)}")
    if os.path.isdir(path):
        raise ParameterError(f"{path}: is a folder, not a probe file")
    if not os.path.exists(path):
        raise ParameterError(f"{path}: probe file does not exist")
    try:
        positions, meta, sel = _READERS[ext](path)
        return _build(path, positions, meta, {k: v for k, v in fields.items() if v is not None}), sel
    except ArrayselError as exc:
        text = str(exc)
        raise ParameterError(text if text.startswith(path) else f"{path}: {text}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterError(f"{path}: cannot be read ({getattr(exc, 'strerror', None) or exc})") from None


def _build(path: str, positions, meta: dict, fields: dict):
    """The probe of positions (or None) and fields (the file's, replaced by ``fields``)."""
    merged = {**meta, **fields}
    missing = [k for k in ("width", "height", "fc") if merged.get(k) is None]
    if missing:
        raise ParameterError(f"the file gives no {missing[0]}; give it (probe.{missing[0]} in a scene, "
                             f"{missing[0]}= in Python)")
    common = {k: merged[k] for k in ("width", "height", "fc", "bandwidth", "baffle") if merged.get(k) is not None}
    name = str(merged.get("name") or os.path.splitext(os.path.basename(path))[0])
    grid = {k: merged[k] for k in GRID_FIELDS if merged.get(k) is not None}
    if all(k in grid for k in GRID_FIELDS[:4]):
        probe = MatrixProbe(name, **grid, **common)
        if positions is not None:
            pos = np.asarray(positions, dtype=np.float64)
            if pos.shape != (probe.n_elements, 2) or np.abs(pos - probe.element_positions()[:, :2]).max() > 10 * POSITION_TOL:
                raise ParameterError(f"the positions disagree with the grid fields ({probe.n_elements} elements of "
                                     f"nx = {probe.nx}, ny = {probe.ny}, blank rows {list(probe.blank_rows)}, blank "
                                     f"columns {list(probe.blank_columns)}); fix or remove the grid fields")
        return probe
    if positions is None:
        raise ParameterError("the file gives neither element positions nor a grid (nx, ny, pitch_x, pitch_y)")
    return probe_from_positions(name, positions, **common)


def _json_value(text: str):
    try:
        return json.loads(text)
    except ValueError:
        return text.strip()


def _number(v: str, what: str) -> float:
    try:
        x = float(v)
    except ValueError:
        raise ParameterError(f"{what} = {v[:40]!r} is not a number") from None
    if not math.isfinite(x):
        raise ParameterError(f"{what} = {v!r} is not finite")
    return x


def _flag(v: str, what: str) -> bool:
    s = v.strip().lower()
    if s in ("1", "true", "yes"):
        return True
    if s in ("0", "false", "no", ""):
        return False
    raise ParameterError(f"{what} = {v[:40]!r} must be 0 or 1")


def _read_csv(path: str):
    with open(path, encoding="utf-8", newline="") as fh:
        text = fh.read()
    lines = text.splitlines()
    meta, start = {}, 0
    while start < len(lines) and (lines[start].startswith("#") or not lines[start].strip()):
        body = lines[start][1:].strip()
        if ":" in body:
            key, value = body.split(":", 1)
            if key.strip() in PROBE_FIELDS + GRID_FIELDS:
                meta[key.strip()] = _json_value(value)
        start += 1
    rows = list(csv.reader(io.StringIO("\n".join(lines[start:]))))
    if not rows:
        raise ParameterError("no header row (the columns x and y are required)")
    header = [h.strip().lower() for h in rows[0]]
    for col in ("x", "y"):
        if col not in header:
            raise ParameterError(f"line {start + 1}: the header has no column {col!r} (found {header})")
    col = {h: i for i, h in enumerate(header)}
    data = [r for r in rows[1:] if any(c.strip() for c in r)]
    if not data:
        raise ParameterError("holds no element row")
    cells = {h: [] for h in header}
    for no, r in enumerate(data):
        if len(r) != len(header):
            raise ParameterError(f"element row {no + 1} has {len(r)} values, the header {len(header)}")
        for h in header:
            cells[h].append(r[col[h]].strip())
    return _table(cells, meta, "row")


def _table(cells: dict, meta: dict, what: str):
    """Positions, fields and selection of a channel map given column by column (text or values)."""
    n = len(cells["x"])
    pos = np.array([[_num(cells["x"][i], f"{what} {i + 1}: x"), _num(cells["y"][i], f"{what} {i + 1}: y")]
                    for i in range(n)])
    if "element" in cells:
        order = [int(_num(v, f"{what} {i + 1}: element")) for i, v in enumerate(cells["element"])]
        if order != list(range(n)):
            raise ParameterError(f"the column element must list 0, 1, ..., {n - 1} in order")
    sel = None
    if "transmit" in cells or "receive" in cells:
        # one of the two columns alone: the same elements transmit and receive
        tx_col = cells["transmit"] if "transmit" in cells else cells["receive"]
        rx_col = cells["receive"] if "receive" in cells else cells["transmit"]
        tx = np.array([_bool(v, f"{what} {i + 1}: transmit") for i, v in enumerate(tx_col)])
        rx = np.array([_bool(v, f"{what} {i + 1}: receive") for i, v in enumerate(rx_col)])
        w = np.array([_num(v, f"{what} {i + 1}: weight") if (tx[i] or rx[i]) else 0.0
                      for i, v in enumerate(cells.get("weight", ["1"] * n))])
        sel = {"transmit": tx, "receive": rx, "weights": w}
        if "channel" in cells:
            sel["channels"] = np.array([-1 if v in ("", None) else int(_num(v, f"{what} {i + 1}: channel"))
                                        for i, v in enumerate(cells["channel"])], dtype=np.int64)
    return pos, meta, sel


def _num(v, what: str) -> float:
    """A number from a CSV cell (text) or a JSON value."""
    if v is None or isinstance(v, bool):
        raise ParameterError(f"{what} = {v!r} is not a number")
    if isinstance(v, (int, float)):
        if not math.isfinite(v):
            raise ParameterError(f"{what} = {v!r} is not finite")
        return float(v)
    return _number(str(v), what)


def _bool(v, what: str) -> bool:
    return bool(v) if isinstance(v, bool) else _flag(str(v) if v is not None else "", what)


def _read_json(path: str):
    with open(path, encoding="utf-8") as fh:
        try:
            doc = json.load(fh)
        except ValueError as exc:
            raise ParameterError(f"is not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("elements"), list) or not doc["elements"]:
        raise ParameterError("a channel map must be an object with a non-empty list 'elements' (and 'probe')")
    probe = doc.get("probe") or {}
    if not isinstance(probe, dict):
        raise ParameterError("'probe' must be an object of the probe's fields")
    rows = doc["elements"]
    if not all(isinstance(r, dict) and "x" in r and "y" in r for r in rows):
        raise ParameterError("every entry of 'elements' must be an object with x and y")
    keys = [k for k in CHANNEL_COLUMNS if k in rows[0]]
    cells = {k: [r.get(k) for r in rows] for k in keys}
    meta = {k: v for k, v in probe.items() if k in PROBE_FIELDS + GRID_FIELDS}
    return _table(cells, meta, "element")


def _read_npy(path: str):
    try:
        a = np.load(path, allow_pickle=False)
    except ValueError as exc:
        raise ParameterError(f"is not a NumPy array file ({exc})") from None
    if not isinstance(a, np.ndarray) or a.ndim != 2 or not np.issubdtype(a.dtype, np.number):
        raise ParameterError(f"must hold an (Ne, 2) array of element positions x, y in metres, got "
                             f"{getattr(a, 'shape', '?')}")
    if a.shape[0] in (2, 3) and a.shape[1] not in (2, 3):
        a = a.T  # MUST's layout: one column per element
    return a, {}, None


def _read_npz(path: str):
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except (ValueError, OSError) as exc:
        raise ParameterError(f"is not a NumPy .npz file ({exc})") from None
    if "positions" in d and "elements" not in d:
        meta = _must_fields(d)
        return np.asarray(d["positions"], dtype=np.float64), meta, None
    return _must(d)


def _read_mat(path: str):
    from scipy.io import loadmat

    try:
        d = loadmat(path, squeeze_me=False)
    except Exception as exc:  # scipy raises ValueError, TypeError, MatReadError ... on a bad file
        raise ParameterError(f"is not a MATLAB .mat file ({type(exc).__name__}: {exc})") from None
    return _must({k: v for k, v in d.items() if not k.startswith("__")})


def _scalar(d: dict, key: str):
    """A MUST field as a Python number or string (None when absent)."""
    if key not in d:
        return None
    a = np.asarray(d[key])
    if a.dtype.kind in "US":
        return str(a.reshape(-1)[0]).strip() if a.size else None
    if a.size != 1 or not np.issubdtype(a.dtype, np.number):
        raise ParameterError(f"field {key} must be one number, got shape {a.shape}")
    v = a.reshape(-1)[0].item()
    return v


def _int_list(d: dict, key: str):
    if key not in d:
        return None
    a = np.asarray(d[key]).reshape(-1)
    if a.size and not np.issubdtype(a.dtype, np.number):
        raise ParameterError(f"field {key} must be a list of integers")
    return [int(v) for v in a]


def _must_fields(d: dict) -> dict:
    meta = {k: _scalar(d, k) for k in ("width", "height", "fc", "bandwidth", "baffle", "nx", "ny", "pitch_x",
                                        "pitch_y")}
    meta["name"] = _scalar(d, "probe_name") or _scalar(d, "name")
    for k in ("blank_rows", "blank_columns"):
        meta[k] = _int_list(d, k)
    return {k: v for k, v in meta.items() if v is not None}


def _row(d: dict, key: str, n: int):
    if key not in d:
        return None
    a = np.asarray(d[key])
    if not np.issubdtype(a.dtype, np.number) or a.size != n:
        raise ParameterError(f"field {key} must hold {n} numbers (one per element), got shape {a.shape}")
    a = a.astype(np.float64).reshape(-1)
    if not np.isfinite(a).all():
        raise ParameterError(f"field {key} holds non-finite values")
    return a


def _must(d: dict):
    """Positions, fields and selection of a MUST parameter set (a dict of arrays)."""
    meta = _must_fields(d)
    pos = None
    if "elements" in d:
        el = np.asarray(d["elements"])
        if el.ndim != 2 or el.shape[0] != 2 or not np.issubdtype(el.dtype, np.number):
            raise ParameterError(f"field elements must be 2 x Ne (x; y of each element, metres), got shape {el.shape}")
        pos = el.T.astype(np.float64)
    if "TXapodization" not in d and "RXapodization" not in d:
        return pos, meta, None
    n = pos.shape[0] if pos is not None else int(np.asarray(d["TXapodization" if "TXapodization" in d
                                                              else "RXapodization"]).size)
    tx = _row(d, "TXapodization", n)
    rx = _row(d, "RXapodization", n)
    tx = np.ones(n) if tx is None else tx
    rx = np.ones(n) if rx is None else rx
    if (tx < 0).any() or (rx < 0).any():
        raise ParameterError("TXapodization and RXapodization must be >= 0")
    both = (tx > 0) & (rx > 0)
    if not np.allclose(tx[both], rx[both], rtol=1e-12, atol=0):
        e = int(np.flatnonzero(both & ~np.isclose(tx, rx, rtol=1e-12, atol=0))[0])
        raise ParameterError(f"element {e} transmits and receives with different weights ({tx[e]!r}, {rx[e]!r}): "
                             "one weight per element is supported")
    sel = {"transmit": tx > 0, "receive": rx > 0, "weights": np.where(tx > 0, tx, rx)}
    ch = _row(d, "channels", n)
    if ch is not None:
        sel["channels"] = ch.astype(np.int64)
    return pos, meta, sel


_READERS = {".csv": _read_csv, ".json": _read_json, ".npy": _read_npy, ".npz": _read_npz, ".mat": _read_mat}
