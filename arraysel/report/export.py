"""A selection written for a scanner and for other simulators (``arraysel export``).

:func:`export_selection` writes an :class:`~arraysel.physics.probe_files.Aperture` (a probe, its
transmit and receive elements, their apodization weights and scanner channels) to a folder:

* ``channels.csv`` and ``channels.json``: the **channel map**, one row per element of the probe
  in element order, columns :data:`~arraysel.physics.probe_files.CHANNEL_COLUMNS`:
  ``channel`` (the scanner channel; blank / null for an element without one), ``element``,
  ``ix``, ``iy`` (grid column and row; blank for a planar layout), ``x``, ``y`` (metres),
  ``transmit``, ``receive`` (1 / 0), ``weight`` (the apodization; 0 when off). The CSV starts
  with ``# key: value`` lines giving the probe's fields (JSON values), the JSON has them under
  ``"probe"``;
* ``must_param.mat`` and ``must_param.npz``: a **MUST/PyMUST parameter set**
  (:func:`must_param`), loaded by PyMUST's 3-D functions as it is;
* ``mask.png``: the probe with its selection (:func:`arraysel.report.layout_plots.aperture_figure`).

Each file is written atomically; :func:`arraysel.physics.probe_files.read_aperture` reads the
channel maps and the parameter sets back (the same probe, selection and weights).
"""
from __future__ import annotations

import io
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from arraysel.errors import ParameterError
from arraysel.io.atomic import atomic_savez, atomic_write_bytes, atomic_write_text
from arraysel.physics.matrix_probes import MatrixProbe
from arraysel.physics.probe_files import CHANNEL_COLUMNS, Aperture

__all__ = ["EXPORT_FILES", "probe_fields", "channel_rows", "channel_map_csv", "channel_map_json", "must_param",
           "export_selection"]

#: the file each export format writes, in a folder
EXPORT_FILES = {"csv": "channels.csv", "json": "channels.json", "mat": "must_param.mat", "npz": "must_param.npz",
                "png": "mask.png"}


def probe_fields(probe) -> dict[str, Any]:
    """The probe's scalar fields (a grid's included; a planar layout's positions are in the rows)."""
    out: dict[str, Any] = {"name": probe.name}
    if isinstance(probe, MatrixProbe):
        out.update(nx=probe.nx, ny=probe.ny, pitch_x=probe.pitch_x, pitch_y=probe.pitch_y,
                   blank_rows=list(probe.blank_rows), blank_columns=list(probe.blank_columns))
    out.update(width=probe.width, height=probe.height, fc=probe.fc, bandwidth=probe.bandwidth, baffle=probe.baffle)
    return out


def channel_rows(aperture: Aperture) -> list[dict[str, Any]]:
    """One dict per element (columns :data:`CHANNEL_COLUMNS`)."""
    probe = aperture.probe
    pos = probe.element_positions()
    n = probe.n_elements
    if isinstance(probe, MatrixProbe):
        ix, iy = (v.tolist() for v in probe.element_grid(np.arange(n)))
    else:
        ix = iy = [None] * n
    rows = []
    for e in range(n):
        ch = int(aperture.channels[e])
        rows.append({"channel": ch if ch >= 0 else None, "element": e, "ix": ix[e], "iy": iy[e],
                     "x": float(pos[e, 0]), "y": float(pos[e, 1]), "transmit": int(aperture.transmit[e]),
                     "receive": int(aperture.receive[e]), "weight": float(aperture.weights[e])})
    return rows


def channel_map_csv(aperture: Aperture) -> str:
    """The channel map as CSV text (``# key: value`` lines with the probe's fields, a header, rows)."""
    lines = ["# arraysel channel map: one row per element; transmit, receive: 1 = on; weight: apodization "
             "(0 = off); channel: scanner channel (blank = none); x, y in metres"]
    lines += [f"# {k}: {json.dumps(v)}" for k, v in probe_fields(aperture.probe).items()]
    lines.append(",".join(CHANNEL_COLUMNS))
    for r in channel_rows(aperture):
        lines.append(",".join("" if r[c] is None else repr(r[c]) for c in CHANNEL_COLUMNS))
    return "\n".join(lines) + "\n"


def channel_map_json(aperture: Aperture) -> str:
    """The channel map as JSON text: ``{"format", "version", "columns", "probe", "elements"}``."""
    doc = {"format": "arraysel-channel-map", "version": 1, "columns": list(CHANNEL_COLUMNS),
           "probe": probe_fields(aperture.probe), "elements": channel_rows(aperture)}
    return json.dumps(doc, indent=1) + "\n"


def must_param(aperture: Aperture, acquisition=None, delays=None) -> dict[str, Any]:
    """The MUST/PyMUST parameter set of an aperture.

    MUST's fields: ``elements`` (2 x Ne: x; y, metres), ``Nelements``, ``width``, ``height``,
    ``fc``, ``bandwidth``, ``baffle``, ``TXapodization`` (1 x Ne: the weights of the transmitting
    elements, 0 elsewhere), ``radius`` (inf) and ``pitch`` (not used by MUST's 3-D functions;
    PyMUST 0.1.9's ``txdelay3`` reads them), and with an ``acquisition``: ``c``, ``fs``,
    ``attenuation``, ``TXnow``. Fields MUST does not read: ``RXapodization`` (1 x Ne: the receive
    weights; multiply the RF columns of ``simus3`` by it), ``channels`` (1 x Ne, -1: none),
    ``TXdelays`` (n_tx x Ne, seconds: the scene's transmits, one row per call of ``simus3`` /
    ``dasmtx3``), ``probe_name`` and a grid's ``nx``, ``ny``, ``pitch_x``, ``pitch_y``,
    ``blank_rows``, ``blank_columns``.
    """
    probe = aperture.probe
    pos = probe.element_positions()
    n = probe.n_elements
    pitch = probe.pitch_x if isinstance(probe, MatrixProbe) else probe.width
    out: dict[str, Any] = {
        "elements": np.ascontiguousarray(pos[:, :2].T), "Nelements": float(n), "width": probe.width,
        "height": probe.height, "fc": probe.fc, "bandwidth": probe.bandwidth, "baffle": probe.baffle,
        "radius": math.inf, "pitch": pitch,
        "TXapodization": aperture.tx_apodization.reshape(1, n),
        "RXapodization": aperture.rx_apodization.reshape(1, n),
        "channels": aperture.channels.astype(np.float64).reshape(1, n), "probe_name": probe.name,
    }
    if isinstance(probe, MatrixProbe):
        out.update(nx=float(probe.nx), ny=float(probe.ny), pitch_x=probe.pitch_x, pitch_y=probe.pitch_y,
                   blank_rows=np.array(probe.blank_rows, dtype=np.float64).reshape(1, -1),
                   blank_columns=np.array(probe.blank_columns, dtype=np.float64).reshape(1, -1))
    if acquisition is not None:
        out.update(c=acquisition.c, fs=acquisition.fs, attenuation=acquisition.attenuation,
                   TXnow=acquisition.tx_cycles)
    if delays is not None:
        d = np.asarray(delays, dtype=np.float64)
        d = d.reshape(1, -1) if d.ndim == 1 else d
        if d.ndim != 2 or d.shape[1] != n or not np.isfinite(d).all():
            raise ParameterError(f"delays must be finite, (n_tx, {n}) seconds, got shape {d.shape}")
        out["TXdelays"] = d
    return out


def _mat_bytes(param: dict) -> bytes:
    from scipy.io import savemat

    buf = io.BytesIO()
    savemat(buf, param, do_compression=True, oned_as="row")
    return buf.getvalue()


def export_selection(aperture: Aperture, folder: "str | os.PathLike", formats: Iterable[str] | None = None,
                     acquisition=None, delays=None, transmit_events=None) -> dict[str, Path]:
    """Write ``aperture`` to ``folder`` (created) in ``formats`` (keys of :data:`EXPORT_FILES`,
    default all); ``acquisition`` and ``delays`` go into the MUST parameter set. Returns
    ``{format: path}``.

    ``transmit_events`` (per-transmit apertures, ``docs/apertures.md``): boolean ``(n_tx, Ne)``,
    the elements that transmit in each transmit event (``aperture.transmit`` is their union).
    It adds ``transmit_events.csv`` (``event,elements``: one row per event, its elements
    space-separated; key ``"events"``) and the field ``TXapodizations`` (``n_tx x Ne``: event
    ``i``'s transmit apodization, for ``simus3`` with row ``i`` of ``TXdelays``) to the MUST
    parameter set."""
    formats = list(EXPORT_FILES) if formats is None else [str(f).strip().lower() for f in formats]
    bad = [f for f in formats if f not in EXPORT_FILES]
    if bad or not formats:
        raise ParameterError(f"formats = {formats!r}: allowed a non-empty subset of {list(EXPORT_FILES)}")
    if not isinstance(aperture, Aperture):
        raise ParameterError(f"aperture must be an arraysel.physics.probe_files.Aperture, got "
                             f"{type(aperture).__name__}")
    aperture.check()
    events = None if transmit_events is None else _checked_events(transmit_events, aperture, delays)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {f: folder / EXPORT_FILES[f] for f in formats}
    param = must_param(aperture, acquisition, delays) if {"mat", "npz"} & set(formats) else None
    if events is not None:
        if param is not None:
            param["TXapodizations"] = events * aperture.weights[None]
        rows = ["# arraysel transmit events: the elements that transmit in each transmit event "
                "(row i goes with row i of TXdelays)", "event,elements"]
        rows += [f"{i},{' '.join(str(int(e)) for e in np.flatnonzero(ev))}" for i, ev in enumerate(events)]
        atomic_write_text(folder / "transmit_events.csv", "\n".join(rows) + "\n")
    for f, path in paths.items():
        if f == "csv":
            atomic_write_text(path, channel_map_csv(aperture))
        elif f == "json":
            atomic_write_text(path, channel_map_json(aperture))
        elif f == "mat":
            atomic_write_bytes(path, _mat_bytes(param))
        elif f == "npz":
            atomic_savez(path, **{k: np.asarray(v) for k, v in param.items()})
        else:
            from arraysel.report.layout_plots import aperture_figure
            from arraysel.report.plots import save_figure

            save_figure(aperture_figure(aperture), path)
    if events is not None:
        paths["events"] = folder / "transmit_events.csv"
    return paths


def _checked_events(events, aperture: Aperture, delays) -> np.ndarray:
    """``events`` as a boolean ``(n_tx, Ne)`` array whose union is the aperture's transmit elements
    (and whose rows match the delays' transmits); ParameterError naming ``transmit_events``."""
    ev = np.asarray(events)
    n = aperture.probe.n_elements
    if ev.ndim != 2 or ev.shape[1] != n:
        raise ParameterError(f"transmit_events must be a boolean (n_tx, {n}) array, got shape {ev.shape}")
    ev = ev.astype(bool)
    if delays is not None and np.ndim(delays) == 2 and np.shape(delays)[0] != ev.shape[0]:
        raise ParameterError(f"transmit_events has {ev.shape[0]} events, the delays {np.shape(delays)[0]} transmits")
    if not np.array_equal(ev.any(0), aperture.transmit):
        raise ParameterError("transmit_events: their union must be the aperture's transmit elements")
    if not ev.any(1).all():
        raise ParameterError(f"transmit_events: event {int(np.argmin(ev.any(1)))} has no transmit element")
    return ev
