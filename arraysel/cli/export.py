"""``arraysel export``: a selection as a channel map, a MUST parameter set and a mask image."""
from __future__ import annotations

import os

from arraysel.errors import ParameterError

#: the files an export writes, by format (:data:`arraysel.report.export.EXPORT_FILES`)
FORMATS = ("csv", "json", "mat", "npz", "png")


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write a selection for a scanner or another simulator",
        description="Write a selection of a 2-D array (a matrix probe, a grid with blank rows, an imported "
                    "layout) to a folder: channels.csv and channels.json (the channel map: channel, element, "
                    "ix, iy, x, y, transmit, receive, weight, one row per element), must_param.mat and "
                    "must_param.npz (a MUST/PyMUST parameter set: element positions, TX and RX apodization, "
                    "the probe's fields, the scene's acquisition and transmit delays) and mask.png "
                    "(docs/matrix.md, 'Export'). The probe comes from --scene, --probe or --compare; the "
                    "selection from --elements, a line of a mask file, or a row of a comparison's table1.csv.")
    src = p.add_argument_group("the probe (one of)")
    src.add_argument("--scene", default=None, help="scene name or .toml file: its probe, acquisition and transmits")
    src.add_argument("--probe", default=None, metavar="FILE",
                     help="a probe file: element positions (.csv, .npy, .npz) or a MUST parameter set (.mat, .npz)")
    src.add_argument("--compare", default=None, metavar="DIR",
                     help="a folder written by arraysel compare: the scene of its run.json and the selection "
                          "of --config in its table1.csv")
    sel = p.add_argument_group("the selection (one of)")
    sel.add_argument("--elements", default=None, metavar="I,J,...", help="0-based active elements (transmit and "
                     "receive)")
    sel.add_argument("--masks", default=None, metavar="FILE", help="a mask file (one selection a line) ...")
    sel.add_argument("--line", default=None, type=int, metavar="N", help="... and the line of it to export (1-based)")
    sel.add_argument("--config", default=None, metavar="NAME", help="with --compare: the row of table1.csv "
                     "(a selector configuration, e.g. ste)")
    p.add_argument("--transmit", default=None, metavar="I,J,...", help="transmitting elements (default: the "
                   "selection)")
    p.add_argument("--receive", default=None, metavar="I,J,...", help="receiving elements (default: the selection)")
    p.add_argument("--weights", default=None, metavar="W,W,...|FILE",
                   help="apodization weights (> 0): one per element or one per active element in element order, "
                        "as text or a file (.npy or text); default 1")
    p.add_argument("--formats", default=",".join(FORMATS), help=f"comma-separated subset of {','.join(FORMATS)} "
                   "(default all)")
    p.add_argument("--out", default="export", metavar="DIR", help="output folder (default export)")
    p.add_argument("--force", action="store_true", help="replace the files of an earlier export in --out")
    p.set_defaults(func=run)


def _formats(text: str) -> list[str]:
    out = [f.strip().lower() for f in str(text).split(",") if f.strip()]
    bad = [f for f in out if f not in FORMATS]
    if bad or not out or len(set(out)) != len(out):
        raise ParameterError(f"--formats = {text!r}: allowed a comma-separated subset of {','.join(FORMATS)}")
    return out


def _weights(text: str | None):
    """The weights of ``--weights``: numbers in the text, or in the file it names."""
    import numpy as np

    if text is None:
        return None
    if os.path.isfile(text):
        if text.endswith(".npy"):
            try:
                return np.load(text, allow_pickle=False).reshape(-1)
            except ValueError as exc:
                raise ParameterError(f"--weights: {text!r} is not a NumPy array file ({exc})") from None
        from arraysel.io.masks import _open_text

        with _open_text(text, "--weights") as fh:
            text = " ".join(line.split("#", 1)[0] for line in fh)
    try:
        return np.array([float(t) for t in text.replace(",", " ").split()])
    except ValueError:
        raise ParameterError(f"--weights: {text[:60]!r} is not a list of numbers or a file") from None


def _compare_source(folder: str, config: str | None):
    """(scene, selection text) of a comparison folder's run.json and table1.csv row ``config``."""
    from arraysel.report.tables import compare_folder
    from arraysel.scenes.schema import load_scene

    if config is None:
        raise ParameterError("--compare needs --config NAME (the row of table1.csv to export)")
    scene, rows, table = compare_folder(folder, "--compare")
    names = [r.get("config") for r in rows]
    row = next((r for r in rows if r.get("config") == config), None)
    if row is None or not (row.get("elements") or "").strip():
        raise ParameterError(f"--config {config!r}: {table!r} has no selection for it; its configs: {names}")
    return load_scene(scene), row["elements"]


def _elements(args, n: int):
    """The selection (indices) of --elements, --masks/--line, or None (--transmit and --receive)."""
    from arraysel.io.masks import mask_line, parse_elements

    given = [o for o, v in (("--elements", args.elements), ("--masks", args.masks)) if v is not None]
    if len(given) > 1:
        raise ParameterError(f"give one selection: {' and '.join(given)} both given")
    if args.masks is not None:
        if args.line is None:
            raise ParameterError("--masks needs --line N (the line of the file to export)")
        return mask_line(args.masks, args.line, n)
    if args.line is not None:
        raise ParameterError("--line goes with --masks FILE")
    if args.elements is not None:
        return parse_elements(args.elements, n, None)
    if args.transmit is None or args.receive is None:
        raise ParameterError("give the selection: --elements, --masks FILE --line N, --compare DIR --config NAME, "
                             "or both --transmit and --receive")
    return None


def run(args) -> int:
    import numpy as np

    from arraysel.io.masks import parse_elements
    from arraysel.io.outputs import check_outputs, check_result_folder, folder_files, scene_input
    from arraysel.physics.probe_files import Aperture, load_probe
    from arraysel.report.export import EXPORT_FILES, export_selection
    from arraysel.scenes.schema import load_scene

    formats = _formats(args.formats)
    sources = [o for o, v in (("--scene", args.scene), ("--probe", args.probe), ("--compare", args.compare))
               if v is not None]
    if len(sources) != 1:
        raise ParameterError("give the probe with one of --scene, --probe, --compare"
                             + (f" ({' and '.join(sources)} given)" if sources else ""))
    if args.config is not None and args.compare is None:
        raise ParameterError("--config goes with --compare DIR")
    names = [EXPORT_FILES[f] for f in formats]
    check_outputs(folder_files("--out", args.out, names),
                  inputs=[("--scene", scene_input(args.scene) if args.scene else None), ("--probe", args.probe),
                          ("--masks", args.masks)], folders=[("--out", args.out)])
    check_result_folder(args.out, "--out", held=names, what="an export", force=args.force)
    scene, text = (None, None)
    if args.compare is not None:
        scene, text = _compare_source(args.compare, args.config)
    elif args.scene is not None:
        scene = load_scene(args.scene)
    if scene is not None:
        probe = scene.probe()
        if not probe.is_matrix:
            raise ParameterError(f"arraysel export writes 2-D arrays (matrix probes, planar layouts); scene "
                                 f"{scene.name!r} has the 1-D probe {probe.name!r}")
        acq = scene.acquisition()
        delays = scene.matrix_setup().delays if scene.is_volume else None
    else:
        probe, acq, delays = load_probe(args.probe), None, None
    n = probe.n_elements
    mode = "shared" if scene is None or text is None else scene.section("aperture").get("mode", "shared")
    where = f"{args.compare}/table1.csv, config {args.config}"
    n_events = len(delays) if mode == "per-transmit" else 1
    blocks = {"separate": 2, "per-transmit": n_events + 1}.get(mode, 1)
    elements = parse_elements(text, n * blocks, None, where=where) if text is not None else _elements(args, n)
    tx = None if args.transmit is None else parse_elements(args.transmit, n, None, where="--transmit")
    rx = None if args.receive is None else parse_elements(args.receive, n, None, where="--receive")
    events = None
    if mode != "shared":  # a comparison of full-tx, separate or per-transmit apertures (docs/apertures.md)
        from arraysel.objective.aperture import split_apertures, split_events

        tx, rx = split_apertures(elements, n, mode, n_events)
        if mode == "per-transmit":
            events = np.zeros((n_events, n), dtype=bool)
            for i, ev in enumerate(split_events(elements, n, n_events)[0]):
                events[i, ev] = True
        elements = None
    aperture = Aperture.of(probe, elements, transmit=tx, receive=rx, weights=_weights(args.weights))
    paths = export_selection(aperture, args.out, formats, acquisition=acq, delays=delays, transmit_events=events)
    print(f"{probe.name}: {int(aperture.active.sum())} of {n} elements (transmit {int(aperture.transmit.sum())}, "
          f"receive {int(aperture.receive.sum())})")
    for path in paths.values():
        print(f"wrote {path}")
    return 0
