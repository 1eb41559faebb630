"""``arraysel apodize``: bounded weights on the elements of selections, fitted on the scene's loss."""
from __future__ import annotations

import sys

from arraysel.errors import ParameterError


def add_parser(subparsers) -> None:
    from arraysel.selectors.apodization import METHODS, ApodizationSettings

    d = ApodizationSettings()
    p = subparsers.add_parser(
        "apodize", help="fit apodization weights to the elements of selections",
        description="Keep each selection and fit one weight per selected element, in [--w-min, 1], on the "
                    "scene's own loss by gradient (unselected elements stay 0). Writes to --out: apodize.csv "
                    "(per selection a row with weighting = binary, the 0/1 selection, and a row with weighting = "
                    "apodized, its weights: the loss and every metric, PSL_dB included), weights.csv (one row "
                    "per selected element) and weights.json (docs/apodization.md).")
    src = p.add_argument_group("the selections (one of)")
    src.add_argument("--masks", default=None, metavar="FILE", help="a mask file: one selection a line (with --scene)")
    src.add_argument("--from-compare", default=None, metavar="DIR",
                     help="a folder written by arraysel compare: its scene and the selections of its table1.csv")
    p.add_argument("--scene", default=None, help="scene name or .toml file (with --masks)")
    p.add_argument("--configs", default=None, metavar="A,B,...",
                   help="with --from-compare: the rows of table1.csv to apodize (default every row with a selection)")
    p.add_argument("--w-min", type=float, default=d.w_min,
                   help=f"smallest weight of a selected element, in [0, 1) (default {d.w_min})")
    p.add_argument("--steps", type=int, default=d.steps,
                   help=f"gradient steps (adam) or most loss evaluations (lbfgsb), >= 1 (default {d.steps})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam's learning rate, > 0 (default {d.lr})")
    p.add_argument("--method", choices=METHODS, default=d.method, help=f"optimiser (default {d.method})")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--out", default="apodize", metavar="DIR", help="output folder (default apodize)")
    p.add_argument("--force", action="store_true", help="replace the files of an earlier run in --out")
    p.set_defaults(func=run)


def _sources(args):
    """(scene, [(label, elements text)]) of --masks with --scene, or of --from-compare."""
    from arraysel.report.apodization import compare_selections
    from arraysel.scenes.schema import load_scene

    given = [o for o, v in (("--masks", args.masks), ("--from-compare", args.from_compare)) if v is not None]
    if len(given) != 1:
        raise ParameterError("give the selections with one of --masks FILE (and --scene) or --from-compare DIR"
                             + (f" ({' and '.join(given)} given)" if given else ""))
    if args.configs is not None and args.from_compare is None:
        raise ParameterError("--configs goes with --from-compare DIR")
    if args.from_compare is not None:
        if args.scene is not None:
            raise ParameterError("--scene and --from-compare exclude each other: the comparison's run.json "
                                 "names its scene")
        configs = None if args.configs is None else [c.strip() for c in args.configs.split(",") if c.strip()]
        scene, found = compare_selections(args.from_compare, configs)
        return load_scene(scene), found
    if args.scene is None:
        raise ParameterError("--masks needs --scene (the scene the selections are for)")
    return load_scene(args.scene), None


def run(args) -> int:
    from arraysel.io.masks import iter_mask_lines, parse_elements
    from arraysel.io.outputs import check_outputs, check_result_folder, folder_files, scene_input
    from arraysel.objective.build import build_objective
    from arraysel.report.apodization import OUTPUT_FILES, write_apodization
    from arraysel.selectors.apodization import ApodizationSettings, apodize_many

    ApodizationSettings(w_min=args.w_min, steps=args.steps, lr=args.lr, method=args.method)
    check_outputs(folder_files("--out", args.out, OUTPUT_FILES),
                  inputs=[("--scene", scene_input(args.scene) if args.scene else None), ("--masks", args.masks)],
                  folders=[("--out", args.out)])
    check_result_folder(args.out, "--out", held=OUTPUT_FILES, what="an apodization", force=args.force)
    scene, found = _sources(args)
    n = scene.probe().n_elements
    if found is None:
        labels, sels = [], []
        for i, sel in enumerate(iter_mask_lines(args.masks, n, None), start=1):
            labels.append(f"line{i}")
            sels.append(sel)
        if not sels:
            raise ParameterError(f"--masks: {args.masks!r} holds no selection")
    else:
        labels = [label for label, _ in found]
        sels = [parse_elements(text, n, None, where=f"{args.from_compare}/table1.csv, config {label}")
                for label, text in found]
    import torch

    if args.device == "cuda" and not torch.cuda.is_available():
        raise ParameterError("--device cuda was given but torch sees no CUDA device")
    obj = build_objective(scene, device=args.device, dtype=getattr(torch, args.dtype))

    def progress(i, res):
        print(f"{labels[i]}: loss {res.loss_binary:.6g} (binary) -> {res.loss_apodized:.6g} (apodized)",
              file=sys.stderr)

    results = apodize_many(obj, sels, progress=progress, w_min=args.w_min, steps=args.steps, lr=args.lr,
                                 method=args.method)
    paths = write_apodization(args.out, scene.name, labels, results)
    print(f"apodized {len(results)} selection(s) on scene {scene.name!r}")
    for path in paths.values():
        print(f"wrote {path}")
    return 0
