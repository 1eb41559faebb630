"""What a trained (or training) end-to-end selection is worth: the learned selection, a head
fine-tuned for a fixed selection, and the reconstruction metrics on held-out images.

:class:`E2EEvaluation` is the part of :class:`~arraysel.e2e.trainer.E2ETrainer` that runs after
(or between) the training steps; it reads the trainer's selection module, reconstructor,
operators, scenes, noise, batches, settings and generator.
"""
from __future__ import annotations

from typing import Any, Mapping

import torch
import torch.nn as nn
from tqdm.auto import tqdm

from arraysel.e2e.recon import mse, psnr, ssim
from arraysel.errors import ParameterError, SelectionError, check_number
from arraysel.objective.losses import l_rec
from arraysel.selection import masks_from_indices

__all__ = ["E2EEvaluation", "blurred_image", "mask_to_weights", "as_images"]


def mask_to_weights(mask: Any, n_elements: int, device: torch.device | str | None = None
                    ) -> torch.Tensor:
    """Turn a mask into ``(Ne,)`` float weights.

    ``mask``: a sequence/tensor of integer element indices (distinct, in
    ``[0, Ne)``; checked and converted by :func:`arraysel.selection.masks_from_indices`),
    or a bool/float tensor of length ``Ne`` (used as is, so a gradient flows through it).
    """
    t = torch.as_tensor(mask)
    if t.dtype == torch.bool or t.is_floating_point():
        if t.shape != (n_elements,):
            raise SelectionError(f"a weight mask must have shape ({n_elements},), got {tuple(t.shape)}")
        return t.to(device=device, dtype=torch.float32)
    # element indices: validated and converted by the one home, arraysel.selection
    w = masks_from_indices([t.flatten().long().tolist()], n_elements)[0]
    return torch.as_tensor(w, dtype=torch.float32, device=device)


def as_images(data: Any) -> torch.Tensor:
    if isinstance(data, (tuple, list)):
        data = data[0]
    x = torch.as_tensor(data)
    if x.ndim == 3:
        x = x[:, None]
    if x.ndim != 4 or x.shape[1] != 1 or x.shape[0] < 1:
        raise ParameterError(f"images must be (N, 1, H, W) (or an (images, labels) pair), "
                             f"got {tuple(x.shape)}")
    return x.float()


class E2EEvaluation:
    """The learned selection and its evaluation (see the module); mixed into the trainer."""

    @torch.no_grad()
    def learned_weights(self) -> torch.Tensor:
        """The learned selection as ``(Ne,)`` 0/1 weights (selection in eval mode)."""
        was = self.selection.training
        self.selection.eval()
        try:
            P, _ = self.selection(self.tau(), None)
        finally:
            self.selection.train(was)
        return (P.sum(1) > 0.5).float()

    def learned_indices(self) -> torch.Tensor:
        """Sorted indices ``(k,)`` of the learned active elements."""
        return torch.nonzero(self.learned_weights()).flatten().cpu()

    def _mask_weights(self, mask: Any) -> torch.Tensor:
        ne = self.learned_weights().numel()
        return mask_to_weights(mask, ne, self.device)

    def finetune_head(self, steps: int, *, mask: Any = None, lr: float | None = None,
                      include_ista: bool = False, reconstructor: nn.Module | None = None
                      ) -> list[float]:
        """Train the head alone (and the ISTA parameters with ``include_ista``) on ``L_rec``.

        The selection is frozen: ``mask=None`` uses the learned selection,
        otherwise ``mask`` (indices or ``(Ne,)`` weights, e.g. a baseline).
        ``reconstructor`` (default: the trainer's own) is the model trained;
        pass ``copy.deepcopy(trainer.reconstructor)`` to keep the original.
        Uses a fresh Adam (``lr`` default ``config.lr_head``, and
        ``config.lr_ista`` for the ISTA parameters); batches and noise come
        from the trainer's generator. With a freshly initialised
        ``reconstructor`` and ``include_ista=True`` this trains a
        reconstructor from scratch for a fixed selection (the baselines'
        reconstructors in :func:`arraysel.e2e.pipeline.run_training`).
        Returns the loss per step.
        """
        steps = check_number("steps", steps, lo=0, integer=True)
        recon = self.reconstructor if reconstructor is None else reconstructor.to(self.device)
        with torch.no_grad():
            w = self.learned_weights() if mask is None else self._mask_weights(mask)
            op = self.operator(self._kernel(w.to(self.device)).detach())
        params = list(recon.head.parameters()) if hasattr(recon, "head") else list(recon.parameters())
        groups = [{"params": params, "lr": self.config.lr_head if lr is None else lr}]
        if include_ista and hasattr(recon, "ista"):
            ista = list(recon.ista.parameters())
            groups.append({"params": ista, "lr": self.config.lr_ista if lr is None else lr})
            params = params + ista
        trainable = {id(p) for p in params}
        frozen = [p for p in recon.parameters() if id(p) not in trainable and p.requires_grad]
        for p in frozen:
            p.requires_grad_(False)
        opt = torch.optim.Adam(groups)
        losses = []
        recon.train()
        try:
            for _ in tqdm(range(steps), desc="finetune", disable=None if self.config.progress else True):
                i_s, i_ref = self.scenes(self._next_batch(), self.generator)
                i_hat = self.reconstruct(recon, self._noise(op.A(i_s), self.generator), op)
                loss = l_rec(i_hat, i_ref.to(i_hat.dtype))
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
        finally:
            for p in frozen:
                p.requires_grad_(True)
        return losses

    @torch.no_grad()
    def evaluate(self, images: Any, masks: Mapping[str, Any] | None = None, *,
                 batch_size: int = 64, clamp: bool = True, seed: int | None = None,
                 reconstructors: Mapping[str, nn.Module] | None = None, blurred: bool = False
                 ) -> dict[str, dict[str, Any]]:
        """MSE, PSNR (dB, data range 1) and SSIM on held-out images.

        Returns ``{name: {'mse', 'psnr', 'ssim': float, 'indices': list of int}}``.
        With ``blurred=True`` each row also holds ``'mse_blurred'``,
        ``'psnr_blurred'``, ``'ssim_blurred'``: the same metrics of the
        measurement's magnitude ``|Y|`` (the input of the reconstructor) as an
        image, scaled per image by its least-squares gain to ``I_ref``
        (:func:`blurred_image`) and clamped like ``I_hat``.

        Rows: ``'learned'`` (the learned selection) and one per entry of
        ``masks`` (name -> indices or ``(Ne,)`` weights). Each selection's
        kernel comes from ``kernel_fn``; the reconstruction uses the trainer's
        reconstructor, or ``reconstructors[name]`` when given (e.g. one
        fine-tuned for that mask). ``I_hat`` is clamped to ``[0, 1]`` before
        the metrics unless ``clamp=False``. Scenes and noise use a generator
        seeded with ``seed`` (default ``config.seed + 1``), the same for every
        row, so all masks see the same scenes.
        """
        imgs = as_images(images)
        bs = check_number("batch_size", batch_size, lo=1, integer=True)
        rows = {"learned": self.learned_weights()}
        for name, m in (masks or {}).items():
            if name == "learned":
                raise ParameterError("mask name 'learned' is reserved for the learned selection")
            rows[name] = self._mask_weights(m)
        out = {}
        for name, w in rows.items():
            recon = (reconstructors or {}).get(name, self.reconstructor)
            was = recon.training
            recon.eval()
            gen = torch.Generator().manual_seed(self.config.seed + 1 if seed is None else seed)
            op = self.operator(self._kernel(w.to(self.device)))
            vals: dict[str, list] = {}
            for start in range(0, len(imgs), bs):
                i_s, i_ref = self.scenes(imgs[start:start + bs], gen)
                y = self._noise(op.A(i_s), gen)
                i_hat = self.reconstruct(recon, y, op)
                i_ref = i_ref.to(i_hat.dtype)
                pairs = [("", i_hat)]
                if blurred:
                    pairs.append(("_blurred", blurred_image(y, i_ref)))
                for suffix, img in pairs:
                    if clamp:
                        img = img.clamp(0, 1)
                    for key, fn in (("mse", mse), ("psnr", psnr), ("ssim", ssim)):
                        vals.setdefault(key + suffix, []).append(fn(img, i_ref, reduction="none"))
            recon.train(was)
            out[name] = {k: float(torch.cat(v).mean()) for k, v in vals.items()}
            out[name]["indices"] = torch.nonzero(w).flatten().cpu().tolist()
        return out


def blurred_image(y: torch.Tensor, i_ref: torch.Tensor) -> torch.Tensor:
    """``g |y|`` with the per-image gain ``g = <|y|, I_ref> / <|y|, |y|>`` (least squares).

    The measurement ``Y = kappa (*) I_s`` of a unit-norm kernel has an
    arbitrary scale; this gain gives the plain blurred image its best fit to
    the target before it is scored against it.
    """
    m = y.abs().to(i_ref.dtype)
    num = (m * i_ref).flatten(1).sum(1)
    den = (m * m).flatten(1).sum(1).clamp_min(torch.finfo(m.dtype).tiny)
    return m * (num / den).view(-1, *([1] * (m.dim() - 1)))
