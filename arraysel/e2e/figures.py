"""Fig. 3-style figures of an end-to-end run.

Every ``fig_*`` function returns a :class:`matplotlib.figure.Figure` (built
without pyplot, so no backend is chosen or changed: ``matplotlib.use`` is
never called), in the one figure style of :mod:`arraysel.report.plots` (its
fonts, dpi, dB range, mm axes and colour maps); :func:`save_figure` (that of
:mod:`arraysel.report.plots`) writes one as a PNG atomically and
:func:`write_figures` writes all of a run's.
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np
import torch

from arraysel.report.plots import (IMAGE_CMAP, figure as _figure, mask_strip, profile_lines, psf_image,
                                   save_figure, styled)

__all__ = ["fig_mask", "fig_psf", "fig_images", "fig_loss", "save_figure", "write_figures"]


@styled
def fig_mask(masks: dict[str, list[int]], n_elements: int):
    """Active elements of each selection (one row per selection, the full array left out;
    the learned one first, the uniform one right below it)."""
    order = [n for n in ("learned", "uniform") if n in masks] + [n for n in masks
                                                               if n not in ("learned", "uniform")]
    masks = {n: masks[n] for n in order}
    names = [n for n in masks if len(masks[n]) < n_elements] or list(masks)
    grid = np.zeros((len(names), n_elements))
    for r, name in enumerate(names):
        grid[r, masks[name]] = 1
    fig = _figure((max(6, n_elements / 8), 0.5 + 0.45 * len(names)))
    ax = fig.subplots()
    mask_strip(ax, [f"{n} ({len(masks[n])})" for n in names], grid)
    ax.set_xticks(range(0, n_elements, max(1, n_elements // 16)))
    ax.set_xlabel("element (0-based)")
    ax.set_title("active elements (black)")
    return fig


@styled
def fig_psf(kernels: dict[str, np.ndarray], kernel_ref: np.ndarray, pitch: float):
    """Learned and reference PSF in dB (:data:`~arraysel.report.plots.DYN_RANGE_DB` range, each of its
    own peak) and lateral / axial profiles through each selection's peak."""
    fig = _figure((11, 9))
    axes = fig.subplots(2, 2)
    im = None
    for ax, k, title in ((axes[0, 0], kernels["learned"], "learned selection"),
                         (axes[0, 1], kernel_ref, "reference (full array)")):
        im = psf_image(ax, k, pitch, title=f"PSF, {title} (dB)")
    fig.colorbar(im, ax=axes[0, :], label="dB", shrink=0.8)
    profile_lines(axes[1, 0], axes[1, 1], kernels, pitch, bold=("learned", "full"))
    for ax in axes[1]:
        ax.grid(True)
    return fig


@styled
@torch.no_grad()
def fig_images(trainer, masks: dict[str, list[int]], recons: dict[str, Any], images: torch.Tensor,
               n_elements: int, n_show: int = 3, names: list[str] | None = None):
    """For each selection (one row each): ground truth, blurred measurement ``|Y|`` and
    reconstruction of ``n_show`` held-out images side by side, PSNR (dB) in each title.

    The scenes are the first ones :meth:`~arraysel.e2e.trainer.E2ETrainer.evaluate` used
    (generator seeded ``config.seed + 1``), without the measurement noise of the
    evaluation (these are single images, the tables hold the averages).
    """
    from arraysel.e2e.recon import psnr
    from arraysel.e2e.trainer import blurred_image

    n_show = min(n_show, len(images))
    names = [m for m in (names or masks) if m in masks]
    gen = torch.Generator().manual_seed(trainer.config.seed + 1)
    i_s, i_ref = trainer.scenes(images[:n_show], gen)
    fig = _figure((2.0 * 3 * n_show, 2.2 * len(names)))
    axes = np.atleast_2d(fig.subplots(len(names), 3 * n_show, squeeze=False))
    for r, name in enumerate(names):
        w = torch.zeros(n_elements)
        w[masks[name]] = 1.0
        op = trainer.operator(trainer._kernel(w.to(trainer.device)))
        y = op.A(i_s)
        model = recons.get(name, trainer.reconstructor)
        was = model.training
        model.eval()
        i_hat = trainer.reconstruct(model, y, op).clamp(0, 1)
        model.train(was)
        ref = i_ref.to(i_hat.dtype)
        blur = blurred_image(y, ref).clamp(0, 1)
        for c in range(n_show):
            for j, (label, img) in enumerate((("truth", ref), ("blurred |Y|", blur), ("recon", i_hat))):
                ax = axes[r, 3 * c + j]
                ax.imshow(img[c, 0].float().cpu().numpy(), cmap=IMAGE_CMAP, vmin=0, vmax=1)
                ax.set_xticks([])
                ax.set_yticks([])
                if j == 0:
                    ax.set_title("ground truth")
                else:
                    p = float(psnr(img[c:c + 1].float(), ref[c:c + 1].float()))
                    ax.set_title(f"{label} {p:.1f} dB")
                if c == 0 and j == 0:
                    ax.set_ylabel(name)
    fig.suptitle("held-out scenes: ground truth | blurred measurement | reconstruction (PSNR)")
    return fig


@styled
def fig_loss(history: list[dict[str, float]]):
    """Loss terms per training step (log scale)."""
    fig = _figure((8, 4.5))
    ax = fig.subplots()
    if history:
        steps = np.arange(1, len(history) + 1)
        keys = list(dict.fromkeys(k for h in history for k in h if k != "tau"))
        for key in keys:
            v = np.array([h.get(key, np.nan) for h in history], dtype=float)
            ok = np.isfinite(v)
            if ok.any() and np.all(v[ok] > 0):
                ax.semilogy(steps, v, lw=1.5 if key == "total" else 0.8, label=key)
        ax.legend(ncol=4)
    ax.set_xlabel("step")
    ax.set_ylabel("loss term")
    ax.grid(True)
    ax.set_title("training loss terms (unweighted; total is weighted and balanced)")
    return fig


def write_figures(out_dir: str, *, trainer, masks, recons, kernels, kernel_ref, pitch, n_elements,
                  images, table=None, reconstruction=None) -> list[str]:
    """Write every figure of a run as PNG files in ``out_dir``; returns their file names."""
    kern = {name: kernels[i] for i, name in enumerate(masks)}
    figs = {"fig_mask.png": fig_mask(masks, n_elements),
            "fig_psf.png": fig_psf(kern, kernel_ref, pitch),
            "fig_images.png": fig_images(trainer, masks, recons, images, n_elements),
            "fig_loss.png": fig_loss(trainer.history)}
    for name, fig in figs.items():
        save_figure(fig, os.path.join(out_dir, name))
    return list(figs)
