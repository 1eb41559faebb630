"""``arraysel train``: end-to-end training of a selection with the reconstruction network."""
from __future__ import annotations


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a selection end to end with the reconstruction network",
        description="Learn which k elements stay active jointly with an unrolled-ISTA reconstructor "
                    "on MNIST / FashionMNIST scatterer maps (docs/training.md). Writes mask.txt, mask.json, "
                    "table1.csv, reconstruction.csv, history.csv, settings.json, checkpoint.pt and "
                    "figures to --out. Without --full a quick CPU profile is used (a 3.5 mm field of "
                    "64x64 px of 55 um, linear convolution, speckle scenes, the full array's envelope "
                    "as target, noise 0.01, balanced loss terms, 300 PSF-only + 150 joint steps, "
                    "batch 8, bundled data sample, then a fresh reconstructor per selection); --full "
                    "takes the scene's [data] and [training] sections (the paper: 128x128, batch 64, "
                    "100 epochs). The learned selection is compared with uniform, random and full "
                    "(table1.csv, reconstruction.csv, printed).")
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
    p.add_argument("--convolution", choices=("circular", "linear"), default=None,
                   help="forward model (quick default: linear)")
    p.add_argument("--kernel-stride", type=int, default=None, metavar="S",
                   help="one scene pixel = S PSF pixels (quick default: 2)")
    p.add_argument("--target", choices=("scene", "envelope"), default=None,
                   help="reconstruction target: the image, or the full array's envelope image "
                        "(quick default: envelope)")
    p.add_argument("--noise-std", type=float, default=None, metavar="S",
                   help="complex Gaussian noise on the measurements (quick default: 0.01)")
    p.add_argument("--balance", choices=("none", "initial"), default=None,
                   help="divide the PSF and data terms by their start values (quick default: initial)")
    p.add_argument("--psf-warmup", type=int, default=None, metavar="N",
                   help="PSF-only steps before the joint phase (quick default: 300)")
    p.add_argument("--recon-steps", type=int, default=None, metavar="N",
                   help="train a fresh reconstructor N steps for every selection before the "
                        "reconstruction metrics (quick default: 120; 0: fine-tune copies instead)")
    p.add_argument("--full", action="store_true", help="the paper's configuration (the scene's sections)")
    p.add_argument("--out", default="results/train", metavar="DIR", help="output folder (default results/train)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="torch device (default cpu)")
    p.add_argument("--seed", type=int, default=None, metavar="S", help="random seed (default 0)")
    p.add_argument("--resume", action="store_true", help="continue the checkpoint in --out")
    p.add_argument("--force", action="store_true",
                   help="replace the training already in --out (without it, or --resume, a folder holding "
                        "a checkpoint, mask or tables of a training is refused)")
    p.add_argument("--threads", type=int, default=None, metavar="N",
                   help="torch CPU threads (default: 1 in the quick profile, torch's default with --full)")
    p.add_argument("--no-figures", action="store_true", help="write tables only")
    p.set_defaults(func=run)


def run(args) -> int:
    import torch

    from arraysel.e2e.pipeline import OUTPUT_FILES, check_out_folder, run_training
    from arraysel.errors import ParameterError
    from arraysel.io.outputs import check_outputs, folder_files, scene_input

    # every output problem before any work: the folder, its files, a scene file among them,
    # a finished training without --resume / --force
    check_outputs(folder_files("--out", args.out, OUTPUT_FILES), folders=[("--out", args.out)],
                  inputs=[("--scene", scene_input(args.scene))])
    check_out_folder(args.out, resume=args.resume, force=args.force)
    if args.device == "cuda" and not torch.cuda.is_available():
        raise ParameterError("--device cuda was given but torch sees no CUDA device")
    run_training(args.scene, out_dir=args.out, full=args.full, device=args.device, resume=args.resume,
                 force=args.force,
                 figures=not args.no_figures, dataset=args.dataset, source=args.source,
                 epochs=args.epochs, steps=args.steps, batch_size=args.batch_size,
                 image_size=args.image_size, base_channels=args.channels,
                 finetune_steps=args.finetune_steps, n_test=args.n_test, scatterers=args.scatterers,
                 seed=args.seed, threads=args.threads, convolution=args.convolution,
                 kernel_stride=args.kernel_stride, target=args.target, noise_std=args.noise_std,
                 balance=args.balance, psf_warmup=args.psf_warmup, recon_steps=args.recon_steps)
    return 0
