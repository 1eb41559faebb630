"""``arraysel evaluate``: Table-1 metrics of the selections listed in a file."""
from __future__ import annotations

from ..errors import ParameterError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("evaluate", help="score selections listed in a file",
                              description="Score every selection of --masks (one per line, 0-based active "
                                          "element indices separated by commas or spaces, '#' starts a "
                                          "comment) and write one CSV row per selection, in order.")
    p.add_argument("--scene", default="paper", help="scene name or .toml file (default paper)")
    p.add_argument("--masks", required=True, metavar="FILE", help="selections, one per line")
    p.add_argument("--out", default="metrics.csv", help="output CSV (default metrics.csv)")
    p.add_argument("--psf-out", default=None, metavar="NPZ", help="also write the kernels (psf, psf_ref)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.set_defaults(func=run)


def run(args) -> int:
    import pandas as pd
    import torch

    from ..maskio import atomic_savez, atomic_write_bytes, read_mask_file
    from ..objective import METRIC_NAMES, build_objective, masks_from_indices
    from ..scene import load_scene

    if args.psf_out is not None and not args.psf_out.endswith(".npz"):
        raise ParameterError(f"--psf-out must end with .npz, got {args.psf_out!r}")
    scene = load_scene(args.scene)
    ne = scene.probe().n_elements
    selections = read_mask_file(args.masks, ne, scene.k)  # validated before any work or output
    obj = build_objective(scene, device=args.device, dtype=getattr(torch, args.dtype))
    res = obj.evaluate(masks_from_indices(selections, ne, scene.k), return_kernels=args.psf_out is not None)
    df = pd.DataFrame({"elements": [" ".join(map(str, s)) for s in selections],
                       **{k: res[k] for k in METRIC_NAMES}})
    atomic_write_bytes(args.out, df.to_csv(index=False, float_format="%.8g").encode())
    if args.psf_out is not None:
        atomic_savez(args.psf_out, psf=res["kernels"], psf_ref=obj.reference_kernel().cpu().numpy())
    print(f"scored {len(selections)} selection(s) on scene {scene.name!r}: wrote {args.out}"
          + (f" and {args.psf_out}" if args.psf_out else ""))
    return 0
