"""Fig. 3-style figures of an end-to-end run (matplotlib, Agg backend, atomic PNG writes)."""
from __future__ import annotations

import io
import os
from typing import Any

import numpy as np
import torch

from arraysel.io.masks import atomic_write_bytes

DYN_RANGE_DB = 40.0


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str) -> None:
    plt = _plt()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def _db(k: np.ndarray) -> np.ndarray:
    a = np.abs(k)
    return 20 * np.log10(a / max(a.max(), 1e-30) + 1e-12)


def fig_mask(path: str, masks: dict[str, list[int]], n_elements: int) -> None:
    """Active elements of each selection (one row per selection, the full array left out)."""
    plt = _plt()
    names = [n for n in masks if len(masks[n]) < n_elements] or list(masks)
    grid = np.zeros((len(names), n_elements))
    for r, name in enumerate(names):
        grid[r, masks[name]] = 1
    fig, ax = plt.subplots(figsize=(max(6, n_elements / 8), 0.5 + 0.45 * len(names)))
    ax.imshow(grid, cmap="Greys", vmin=0, vmax=1, aspect="auto", interpolation="nearest")
    ax.set_yticks(range(len(names)), [f"{n} ({len(masks[n])})" for n in names])
    ax.set_xticks(range(0, n_elements, max(1, n_elements // 16)))
    ax.set_xlabel("element (0-based)")
    ax.set_title("active elements (black)")
    _save(fig, path)


def fig_psf(path: str, kernels: dict[str, np.ndarray], kernel_ref: np.ndarray, pitch: float) -> None:
    """Learned and reference PSF in dB (40 dB range) and lateral / axial profiles through the peak."""
    plt = _plt()
    n = kernel_ref.shape[0]
    ext = np.array([-n / 2, n / 2, n / 2, -n / 2]) * pitch * 1e3
    fig, axes = plt.subplots(2, 2, figsize=(11, 9))
    for ax, k, title in ((axes[0, 0], kernels["learned"], "learned selection"),
                         (axes[0, 1], kernel_ref, "reference (full array)")):
        im = ax.imshow(_db(k), vmin=-DYN_RANGE_DB, vmax=0, cmap="gray", extent=ext)
        ax.set_title(f"PSF, {title} (dB)")
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z - z_peak (mm)")
    fig.colorbar(im, ax=axes[0, :], label="dB", shrink=0.8)
    coord = (np.arange(n) - n // 2) * pitch * 1e3
    for name, k in kernels.items():
        a = np.abs(k)
        i, j = np.unravel_index(np.argmax(a), a.shape)
        style = "-" if name in ("learned", "full") else "--"
        axes[1, 0].plot(coord, _db(a[i, :]), style, label=name, lw=1.2)
        axes[1, 1].plot(coord, _db(a[:, j]), style, label=name, lw=1.2)
    for ax, what in ((axes[1, 0], "lateral (x) profile"), (axes[1, 1], "axial (z) profile")):
        ax.set_ylim(-DYN_RANGE_DB - 20, 2)
        ax.set_xlabel("distance from the peak (mm)")
        ax.set_ylabel("dB")
        ax.set_title(f"{what} through the peak")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    _save(fig, path)


@torch.no_grad()
def fig_images(path: str, trainer, masks: dict[str, list[int]], recons: dict[str, Any],
               images: torch.Tensor, n_elements: int, n_show: int = 4) -> None:
    """Ground truth, scatterer map, blurred |Y| and reconstructions of a few held-out images."""
    from arraysel.e2e.recon import psnr
    from arraysel.e2e.trainer import blurred_image

    plt = _plt()
    n_show = min(n_show, len(images))
    gen = torch.Generator().manual_seed(trainer.config.seed + 1)  # the first scenes evaluate() used
    i_s, i_ref = trainer.scene_fn(images[:n_show].to(trainer.device), gen)
    rows = [("ground truth", i_ref, None), ("scatterer map |I_s|", i_s.abs(), None)]
    for name in [m for m in ("learned", "uniform", "full") if m in masks]:
        w = torch.zeros(n_elements)
        w[masks[name]] = 1.0
        op = trainer.operator(trainer._kernel(w.to(trainer.device)))
        y = op.A(i_s)
        model = recons.get(name, trainer.reconstructor)
        was = model.training
        model.eval()
        i_hat = model(y, op).clamp(0, 1)
        model.train(was)
        if name == "learned":
            rows.append(("blurred |Y| (learned)", blurred_image(y, i_ref.to(i_hat.dtype)).clamp(0, 1), i_ref))
        rows.append((f"reconstruction ({name})", i_hat, i_ref))
    fig, axes = plt.subplots(len(rows), n_show, figsize=(2.2 * n_show, 2.2 * len(rows)), squeeze=False)
    for r, (label, batch, ref) in enumerate(rows):
        for c in range(n_show):
            ax = axes[r, c]
            img = batch[c, 0].detach().float().cpu().numpy()
            ax.imshow(img, cmap="gray", vmin=0, vmax=float(img.max()) or 1.0 if r == 1 else 1.0)
            ax.set_xticks([])
            ax.set_yticks([])
            if ref is not None:
                p = float(psnr(batch[c:c + 1].float(), ref[c:c + 1].float()))
                ax.set_title(f"{p:.1f} dB", fontsize=8)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    _save(fig, path)


def fig_loss(path: str, history: list[dict[str, float]]) -> None:
    """Loss terms per training step (log scale)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    if history:
        steps = np.arange(1, len(history) + 1)
        for key in [k for k in history[0] if k != "tau"]:
            v = np.array([h.get(key, np.nan) for h in history], dtype=float)
            if np.all(v[np.isfinite(v)] > 0):
                ax.semilogy(steps, v, lw=1.5 if key == "total" else 0.8, label=key)
        ax.legend(fontsize=8, ncol=4)
    ax.set_xlabel("step")
    ax.set_ylabel("loss term")
    ax.grid(alpha=0.3)
    ax.set_title("training loss terms (unweighted; total is weighted)")
    _save(fig, path)


def write_figures(out_dir: str, *, trainer, masks, recons, kernels, kernel_ref, pitch, n_elements,
                  images, table=None, reconstruction=None) -> list[str]:
    """Write every figure of a run; returns their file names."""
    kern = {name: kernels[i] for i, name in enumerate(masks)}
    fig_mask(os.path.join(out_dir, "fig_mask.png"), masks, n_elements)
    fig_psf(os.path.join(out_dir, "fig_psf.png"), kern, kernel_ref, pitch)
    fig_images(os.path.join(out_dir, "fig_images.png"), trainer, masks, recons, images, n_elements)
    fig_loss(os.path.join(out_dir, "fig_loss.png"), trainer.history)
    return ["fig_mask.png", "fig_psf.png", "fig_images.png", "fig_loss.png"]
