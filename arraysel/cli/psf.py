"""``arraysel psf``: the PSF kernel of one selection (npz or netCDF, optional PNG)."""
from __future__ import annotations

import os

from arraysel.errors import ParameterError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("psf", help="synthesise the PSF kernel of a selection",
                              description="Compute the complex PSF kernel (docs/paper-scene.md) of an element selection "
                                          "and write it, with the full-array reference and the Table-1 "
                                          "metrics, to an npz file, or to a netCDF file (--out ending .nc: "
                                          "coordinates in metres, units and the scene as attributes; "
                                          "pip install 'arraysel[netcdf]'). A 3-D scene writes each plane "
                                          "(psf_xy, psf_ref_xy, coords_xy: pixel positions in metres, ...) "
                                          "and the figures of merit (PSL_dB, width_x_6dB, width_y_6dB).")
    p.add_argument("--scene", default="paper", help="scene name or .toml file (default paper)")
    p.add_argument("--elements", default=None, metavar="I,J,...",
                   help="0-based active elements (default: every second element, 0,2,4,...; a matrix probe: "
                        "every second grid cell in x and in y, element iy * nx + ix without blank rows)")
    p.add_argument("--out", default="psf.npz",
                   help="output file: .npz (default psf.npz) or netCDF-4 (.nc, .nc4, .h5; docs/formats.md)")
    p.add_argument("--plot", action="store_true", help="also write a PNG (40 dB dynamic range) next to --out")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    import torch

    from arraysel.io.masks import atomic_savez, parse_elements
    from arraysel.objective.build import build_objective
    from arraysel.selection import masks_from_indices
    from arraysel.scenes.schema import load_scene

    from arraysel.io.outputs import check_outputs, scene_input
    from arraysel.report.plots import psf_figure, save_figure

    from arraysel.report import netcdf

    if not (args.out.endswith(".npz") or netcdf.is_netcdf(args.out)):
        raise ParameterError(f"--out must end with .npz or a netCDF ending ({', '.join(netcdf.SUFFIXES)}), "
                             f"got {args.out!r}")
    if netcdf.is_netcdf(args.out):
        netcdf.require("--out")
    png = os.path.splitext(args.out)[0] + ".png"
    check_outputs([("--out", args.out), ("--plot", png if args.plot else None)],
                  inputs=[("--scene", scene_input(args.scene))])
    scene = load_scene(args.scene)
    probe = scene.probe()
    ne = probe.n_elements
    if args.elements is None:
        if scene.is_volume and hasattr(probe, "element_grid"):  # every second grid cell in x and in y
            ix, iy = probe.element_grid(np.arange(ne))
            elements = [int(e) for e in np.flatnonzero((ix % 2 == 0) & (iy % 2 == 0))]
        else:
            elements = list(range(0, ne, 2))
    else:
        elements = parse_elements(args.elements, ne, None)
    obj = build_objective(scene, device=args.device, dtype=getattr(torch, args.dtype))
    if scene.is_volume:
        return _volume(args, obj, scene, elements, masks_from_indices([elements], ne), png)
    res = obj.evaluate(masks_from_indices([elements], ne), return_kernels=True)
    kernel = res["kernels"][0]
    ref = obj.reference_kernel().cpu().numpy()
    metrics = {k: float(res[k][0]) for k in obj.metric_names}
    if netcdf.is_netcdf(args.out):
        layout = netcdf.kernel_layout(ref, obj.setup.pitch, scene.points())
        _write_netcdf(args.out, scene, layout, {"psf": kernel}, elements, metrics)
    else:
        atomic_savez(args.out, psf=kernel, psf_ref=ref, elements=np.array(elements),
                     pixel=np.float64(obj.setup.pitch), **{k: np.float64(v) for k, v in metrics.items()})
    _print_result(elements, metrics, args.out, width=10)
    if args.plot:
        save_figure(psf_figure(kernel, ref, obj.setup.pitch, elements, ne), png)
        print(f"wrote {png}")
    return 0


def _write_netcdf(path: str, scene, layout, kernels: dict, elements, metrics: dict) -> None:
    from arraysel.report.netcdf import PsfFile, scene_attrs

    attrs = scene_attrs(scene, f"arraysel psf: the PSF of {len(elements)} of {scene.probe().n_elements} elements")
    with PsfFile(path, layout, n=None, k=len(elements), attrs=attrs, metrics=tuple(metrics)) as f:
        f.write(kernels, elements, metrics)
        f.commit()


def _print_result(elements, metrics: dict, out: str, width: int) -> None:
    """Print the selection, its metrics (names right-aligned to ``width``) and the file written."""
    print(f"elements: {','.join(map(str, elements))}")
    for k, v in metrics.items():
        print(f"{k:>{width}s} = {v:.6g}")
    print(f"wrote {out}")


def _volume(args, obj, scene, elements, mask, png: str) -> int:
    """``arraysel psf`` on a 3-D scene: every plane with its pixel positions, the metrics."""
    import numpy as np

    from arraysel.io.masks import atomic_savez
    from arraysel.report.plots import planes_figure, save_figure

    res = obj.evaluate(mask, return_planes=True)
    ref = {k: v[0].cpu().numpy() for k, v in obj.reference_planes().items()}
    metrics = {k: float(res[k][0]) for k in (*obj.metric_names, *obj.breakdown_names)}
    from arraysel.report import netcdf

    if netcdf.is_netcdf(args.out):
        layout = netcdf.planes_layout(ref, obj.coords)
        _write_netcdf(args.out, scene, layout, {f"psf_{k}": v[0] for k, v in res["planes"].items()}, elements,
                      metrics)
    else:
        arrays = {}
        for k, v in res["planes"].items():
            arrays[f"psf_{k}"] = v[0]
            arrays[f"psf_ref_{k}"] = ref[k]
            arrays[f"coords_{k}"] = obj.coords[k]
        atomic_savez(args.out, **arrays, elements=np.array(elements), planes=np.array(list(ref)),
                     **{k: np.float64(v) for k, v in metrics.items()})
    _print_result(elements, metrics, args.out, width=12)
    if args.plot:
        planes = {k: v[:1] for k, v in res["planes"].items()}
        save_figure(planes_figure([f"{len(elements)} elements"], planes, obj.coords, ref), png)
        print(f"wrote {png}")
    return 0
