"""``arraysel train``: end-to-end training of a selection with the reconstruction network."""
from __future__ import annotations


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a selection end to end with the reconstruction network",
        description="Learn which k elements stay active jointly with an unrolled-ISTA reconstructor "
                    "on MNIST / FashionMNIST scatterer maps (SPEC §3). Writes mask.txt, mask.json, "
                    "table1.csv, reconstruction.csv, history.csv, settings.json, checkpoint.pt and "
                    "figures to --out. Without --full a quick CPU profile is used (64x64 images, "
                    "batch 8, 300 steps, bundled data sample); --full takes the scene's [data] and "
                    "[training] sections (the paper: 128x128, batch 64, 100 epochs).")
    p.add_argument("--scene", default="paper-e2e",
                   help="scene name or .toml file with L_conv / L_rec weights (default paper-e2e)")
    p.add_argument("--dataset", choices=("mnist", "fashion"), default=None,
                   help="data set (default: the scene's)")
    p.add_argument("--source", choices=("auto", "sample", "idx"), default=None,
                   help="images from the IDX files ($ARRAYSEL_DATA), the bundled sample, or auto "
                        "(default: sample in the quick profile, the scene's with --full)")
    p.add_argument("--epochs", type=int, default=None, metavar="N", help="epochs (overrides the profile's steps)")
    p.add_argument("--steps", type=int, default=None, metavar="N", help="optimisation steps (beats --epochs)")
    p.add_argument("--batch-size", type=int, default=None, metavar="B")
    p.add_argument("--image-size", type=int, default=None, metavar="N", help="scene side in pixels")
    p.add_argument("--channels", type=int, default=None, metavar="C",
                   help="head base width C (widths C/2C/4C; the paper: 32)")
    p.add_argument("--finetune-steps", type=int, default=None, metavar="N",
                   help="head fine-tuning steps per selection before the reconstruction metrics")
    p.add_argument("--n-test", type=int, default=None, metavar="N", help="held-out images used (default all)")
    p.add_argument("--scatterers", choices=("points", "image"), default=None,
                   help="points: genscat-like speckle (default); image: the image as reflectivity")
    p.add_argument("--full", action="store_true", help="the paper's configuration (the scene's sections)")
    p.add_argument("--out", default="results/train", metavar="DIR", help="output folder (default results/train)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="torch device (default cpu)")
    p.add_argument("--seed", type=int, default=None, metavar="S", help="random seed (default 0)")
    p.add_argument("--resume", action="store_true", help="continue the checkpoint in --out")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch CPU threads (default: 1 in the quick profile, torch's default with --full)")
    p.add_argument("--no-figures", action="store_true", help="write tables only")
    p.set_defaults(func=run)


def run(args) -> int:
    import torch

    from arraysel.e2e.pipeline import run_training
    from arraysel.errors import ParameterError

    if args.device == "cuda" and not torch.cuda.is_available():
        raise ParameterError("--device cuda was given but torch sees no CUDA device")
    run_training(args.scene, out_dir=args.out, full=args.full, device=args.device, resume=args.resume,
                 figures=not args.no_figures, dataset=args.dataset, source=args.source,
                 epochs=args.epochs, steps=args.steps, batch_size=args.batch_size,
                 image_size=args.image_size, base_channels=args.channels,
                 finetune_steps=args.finetune_steps, n_test=args.n_test, scatterers=args.scatterers,
                 seed=args.seed, threads=args.threads)
    return 0
