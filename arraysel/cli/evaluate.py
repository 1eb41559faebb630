"""``arraysel evaluate``: Table-1 metrics of the selections listed in a file.

The mask file is read twice as a stream: once to validate every line (so a bad
line is reported, with its number, before any work or output), then in chunks
that are scored and written as they finish. Memory stays bounded whatever the
number of masks; the CSV (and the ``--psf-out`` npz or netCDF file) grow in
temporary files next to their targets and are renamed into place at the end, so
a target is never half-written.
"""
from __future__ import annotations

import sys

from arraysel.errors import ParameterError

#: masks scored per chunk (metrics only / with kernels kept for --psf-out)
CHUNK = 4096
CHUNK_WITH_KERNELS = 256


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="score selections listed in a file",
                              description="Score every selection of --masks (one per line, 0-based active "
                                          "element indices separated by commas or spaces, '#' starts a "
                                          "comment) and write one CSV row per selection, in order. Any "
                                          "number of selections: they are read, scored and written in "
                                          "chunks.")
    p.add_argument("--scene", default="paper",
                   help="scene name or .toml file (default paper); 'toy' is the cheap synthetic objective "
                        "of arraysel.testing (Ne=64, k=32)")
    p.add_argument("--masks", required=True, metavar="FILE", help="selections, one per line (UTF-8 text)")
    p.add_argument("--out", default="metrics.csv", help="output CSV (default metrics.csv)")
    p.add_argument("--psf-out", default=None, metavar="FILE",
                   help="also write the kernels (psf, psf_ref; a 3-D scene's planes): .npz, or netCDF-4 (.nc, "
                        ".nc4, .h5: coordinates in metres, units, the scene as attributes, one 'selection' per "
                        "mask; pip install 'arraysel[netcdf]'; docs/formats.md)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    from tqdm.auto import tqdm

    from arraysel.io.atomic import AtomicFile, StreamingNpz
    from arraysel.cli.compare import build_objective
    from arraysel.io.masks import count_masks, iter_mask_chunks
    from arraysel.io.outputs import check_outputs, scene_input
    from arraysel.objective.psf_objective import METRIC_NAMES

    from arraysel.report import netcdf

    # every path, encoding and selection problem before any heavy work
    nc = args.psf_out is not None and netcdf.is_netcdf(args.psf_out)
    if args.psf_out is not None and not (args.psf_out.endswith(".npz") or nc):
        raise ParameterError(f"--psf-out must end with .npz or a netCDF ending ({', '.join(netcdf.SUFFIXES)}), "
                             f"got {args.psf_out!r}")
    if nc:
        netcdf.require("--psf-out")
    check_outputs([("--out", args.out), ("--psf-out", args.psf_out)],
                  inputs=[("--masks", args.masks), ("--scene", scene_input(args.scene))])
    if args.scene == "toy":
        if args.psf_out is not None:
            raise ParameterError("--psf-out needs a physics scene; the toy objective has no kernels")
        ne, k, name = 64, 32, "toy"
    else:
        from arraysel.scenes.schema import load_scene

        scene = load_scene(args.scene)
        ne, k, name = scene.probe().n_elements, scene.k, scene.name
    n = count_masks(args.masks, ne, k)

    obj = build_objective(args.scene if args.scene == "toy" else scene, args.device, args.dtype)
    volume = getattr(obj, "image_kind", None) == "planes"  # a 3-D scene: planes, and the figures of merit as columns
    names = (*METRIC_NAMES, *obj.breakdown_names) if volume else METRIC_NAMES
    kernels = args.psf_out is not None
    chunk = CHUNK_WITH_KERNELS if kernels else CHUNK
    if nc:
        return _evaluate_netcdf(args, obj, scene, n, k, names, volume)
    with AtomicFile(args.out) as csv, (StreamingNpz(args.psf_out) if kernels else _Null()) as npz:
        csv.write((",".join(("elements", *names)) + "\n").encode())
        ref, ref_planes = _begin_npz(npz, obj, n, volume) if kernels else (None, None)
        bar = tqdm(total=n, unit="mask", desc="evaluate", file=sys.stderr, disable=args.no_progress or None,
                   dynamic_ncols=True)
        done = 0
        for sels, masks in iter_mask_chunks(args.masks, ne, k, chunk):
            if kernels and volume:
                res = obj.evaluate(masks, return_planes=True)
                res["kernels"] = np.concatenate([v.reshape(len(sels), -1) for v in res["planes"].values()], axis=1)
            else:
                res = obj.evaluate(masks, return_kernels=True) if kernels else obj.evaluate(masks)
            cols = np.stack([np.asarray(res[m], dtype=np.float64) for m in names], axis=1)
            lines = [" ".join(map(str, s)) + "," + ",".join(f"{v:.8g}" for v in row)
                     for s, row in zip(sels, cols.tolist())]
            csv.write(("\n".join(lines) + "\n").encode())
            if kernels:
                npz.write_rows(res["kernels"])
            done += len(sels)
            bar.update(len(sels))
        bar.close()
        if done != n:  # the file changed between the two passes
            raise ParameterError(f"--masks: {args.masks!r} changed while it was read ({n} then {done} "
                                 f"selections)")
        if kernels:
            _finish_npz(npz, obj, ref, ref_planes)  # the kernels first: no CSV without its npz
        csv.commit()
    print(f"scored {n} selection(s) on scene {name!r}: wrote {args.out}"
          + (f" and {args.psf_out}" if args.psf_out else ""))
    return 0


def _begin_npz(npz, obj, n: int, volume: bool):
    """Start ``--psf-out``'s ``psf`` array for ``n`` selections; return the reference kernel (a 3-D
    scene: its planes' pixels in one row) and the reference planes (None for a 1-D scene)."""
    import numpy as np

    if volume:
        ref_planes = {k: v[0].cpu().numpy() for k, v in obj.reference_planes().items()}
        ref = np.concatenate([v.reshape(-1) for v in ref_planes.values()])
        npz.begin("psf", (n, ref.size), ref.dtype)
        return ref, ref_planes
    ref = obj.reference_kernel().cpu().numpy()
    npz.begin("psf", (n, *ref.shape), ref.dtype)
    return ref, None


def _finish_npz(npz, obj, ref, ref_planes) -> None:
    """End ``psf``, add the reference (and a 3-D scene's plane coordinates) and commit the file."""
    import numpy as np

    npz.end()
    npz.add("psf_ref", ref)
    if ref_planes is not None:  # the planes' pixels in the columns of psf, and each plane on its own
        npz.add("coords", np.concatenate([c.reshape(-1, 3) for c in obj.coords.values()]))
        npz.add("planes", np.array(list(obj.coords)))
        npz.add("plane_shapes", np.array([c.shape[:2] for c in obj.coords.values()]))
        for k, v in ref_planes.items():
            npz.add(f"psf_ref_{k}", v)
            npz.add(f"coords_{k}", obj.coords[k])
    npz.commit()


def _evaluate_netcdf(args, obj, scene, n: int, k: int, names, volume: bool) -> int:
    """``evaluate --psf-out FILE.nc``: the CSV and the netCDF file of the kernels, in chunks."""
    import numpy as np

    from arraysel.io.atomic import AtomicFile
    from arraysel.io.masks import iter_mask_chunks
    from arraysel.report import netcdf

    if volume:
        layout = netcdf.planes_layout({p: v[0].cpu().numpy() for p, v in obj.reference_planes().items()}, obj.coords)
    else:
        layout = netcdf.kernel_layout(obj.reference_kernel().cpu().numpy(), obj.setup.pitch, scene.points())
    attrs = netcdf.scene_attrs(scene, f"arraysel evaluate: the PSFs of the {n} selections of {args.masks}")
    bar = _bar(args, n)
    with AtomicFile(args.out) as csv, netcdf.PsfFile(args.psf_out, layout, n=n, k=k, attrs=attrs,
                                                    metrics=tuple(names)) as out:
        csv.write((",".join(("elements", *names)) + "\n").encode())
        for sels, masks in iter_mask_chunks(args.masks, int(obj.n_elements), k, CHUNK_WITH_KERNELS):
            if out.done + len(sels) > n:
                break
            res = obj.evaluate(masks, return_planes=True) if volume else obj.evaluate(masks, return_kernels=True)
            found = {f"psf_{p}": v for p, v in res["planes"].items()} if volume else {"psf": res["kernels"]}
            cols = {m: np.asarray(res[m], dtype=np.float64) for m in names}
            csv.write(_csv_lines(sels, np.stack([cols[m] for m in names], axis=1)))
            out.write(found, [list(s) for s in sels], cols)
            bar.update(len(sels))
        bar.close()
        if out.done != n:  # the file changed between the two passes
            raise ParameterError(f"--masks: {args.masks!r} changed while it was read ({n} then {out.done} "
                                 f"selections or more)")
        out.commit()  # the kernels first: no CSV without its kernels
        csv.commit()
    print(f"scored {n} selection(s) on scene {scene.name!r}: wrote {args.out} and {args.psf_out}")
    return 0


def _bar(args, n: int):
    from tqdm.auto import tqdm

    return tqdm(total=n, unit="mask", desc="evaluate", file=sys.stderr, disable=args.no_progress or None,
                dynamic_ncols=True)


def _csv_lines(sels, cols) -> bytes:
    """The CSV rows of the selections ``sels`` and their metric columns ``cols`` (B, metrics)."""
    return ("\n".join(" ".join(map(str, s)) + "," + ",".join(f"{v:.8g}" for v in row)
                      for s, row in zip(sels, cols.tolist())) + "\n").encode()


class _Null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
