"""Lobe metrics of the two-way beam pattern of selections: a cheap, differentiable proxy of the
per-beam PSF metrics of a steered sector (``docs/beampattern.md``).

:class:`BeamPatternScorer` runs :class:`~arraysel.physics.beampattern.BeamPattern` and scores the
pattern with :func:`~arraysel.objective.lobes.lobe_metrics` in the u-v frame:

* the main lobe is found around the shift (0, 0) (every beam's own direction) with the rule given
  (default: nulls along 32 rays, capped at 3 times the -6 dB radius; the broadband pattern's
  nulls are shallow, so the cap usually decides);
* ``PSL_dB``: the worst beam of the sector: the largest power outside the main lobe times the
  pattern's ``peak_weight`` (the largest view of that shift over the sector's beams, each relative
  to its own peak, with the element factor);
* ``ISLR_dB``: the mean over the sector's beams: sums weighted by ``mean_weight``;
* ``GLL_dB``: the largest power within the main lobe's radius of the grating lobes that the
  lattice of the selection's transmit or receive elements predicts over the band
  (:meth:`~arraysel.physics.beampattern.BeamPattern.grating_directions`);
* ``width_u_6dB``, ``width_v_6dB``: the -6 dB widths of the main lobe in u and v.

:meth:`BeamPatternScorer.search_terms` reads a sector scene's search terms on a pattern, under the
Table-1 names (``docs/sector.md``): ``L_SLR_q`` ``10^(PSL/20)``, ``L_SLR_i`` ``10^(ISLR/10)``,
``L_contrast`` the mean side-lobe power over the mean main-lobe power (each weighted by
``mean_weight``), ``L_PSF`` the scale-invariant MSE of the amplitude pattern against the full
array's, ``L_SLR`` and ``Mean`` as in Table 1; and the pattern's lobe metrics as
:data:`SEARCH_COLUMNS`.
"""
from __future__ import annotations

import math
from typing import Iterable

import torch
from torch import Tensor

from arraysel.errors import ParameterError
from arraysel.objective.lobe_regions import MainLobeRule, segment_distance
from arraysel.objective.lobes import LOBE_TERMS, lobe_metrics, main_lobe_regions
from arraysel.objective.metrics import METRIC_NAMES
from arraysel.physics.beampattern import BeamPattern

__all__ = ["BEAM_TERMS", "BeamPatternScorer", "SEARCH_COLUMNS", "SEARCH_NAMES"]

#: every name :meth:`BeamPatternScorer.metrics` returns
BEAM_TERMS: tuple[str, ...] = LOBE_TERMS["uv"]
#: the beam pattern's lobe metrics among :meth:`BeamPatternScorer.search_terms` (a sector scene's
#: extra columns)
SEARCH_COLUMNS = ("bp_PSL_dB", "bp_ISLR_dB", "bp_width_u_6dB", "bp_width_v_6dB")
#: every name :meth:`BeamPatternScorer.search_terms` returns
SEARCH_NAMES: tuple[str, ...] = tuple(METRIC_NAMES) + SEARCH_COLUMNS
_NAME = "pattern"
_TINY = 1e-30


class BeamPatternScorer:
    """Per-beam lobe metrics of a :class:`BeamPattern` (module docstring).

    ``rule`` (default ``MainLobeRule(n_rays=32, max_radius=...)``, the rays walked first to 4 times
    the lowest band frequency's null spacing ``lambda / D``, further where undecided).
    """

    def __init__(self, pattern: BeamPattern, rule: MainLobeRule | None = None):
        if not isinstance(pattern, BeamPattern):
            raise ParameterError(f"pattern must be a BeamPattern, got {type(pattern).__name__}")
        self.pattern = pattern
        if rule is None:
            d = max(max(pattern.aperture), 1e-12)
            rule = MainLobeRule(n_rays=32, max_radius=4 * float(pattern.wavelengths.max()) / d)
        self.rule = rule
        self._maps: dict = {}
        self._uv = pattern.coords[..., :2].reshape(-1, 2).to(pattern.device)

    def _grating_maps(self, tx, rx) -> list:
        out = []
        for seg in self.pattern.grating_directions(tx, rx):
            key = id(seg)
            if key not in self._maps:
                h, w = self.pattern.coverage.shape
                dist = (torch.full((h, w), math.inf, dtype=torch.float64, device=self._uv.device)
                        if seg.shape[0] == 0 else segment_distance(self._uv, seg.to(self._uv.device)).reshape(h, w))
                self._maps[key] = (seg, {_NAME: dist})
            out.append(self._maps[key][1])
        return out

    def metrics(self, tx, rx=None, terms: Iterable[str] | None = None) -> dict[str, Tensor]:
        """``{name: (B,)}`` for transmit weights ``tx`` (B, Ne) and receive weights ``rx`` (None:
        the same): ``terms`` among :data:`BEAM_TERMS` (default all; ``GLL_dB`` needs a lattice
        layout). ``PSL_dB``, ``ISLR_dB`` and ``GLL_dB`` are differentiable in the weights."""
        p = self.pattern
        want = tuple(BEAM_TERMS if terms is None else ([terms] if isinstance(terms, str) else terms))
        if "GLL_dB" in want and p.path != "grid":
            raise ParameterError("GLL_dB needs elements on a lattice (this pattern uses the explicit sum)")
        img = p.pattern(tx, rx)
        maps = self._grating_maps(tx, rx) if "GLL_dB" in want else None
        return lobe_metrics({_NAME: img}, {_NAME: p.coords}, target=(0.0, 0.0, 0.0), rule=self.rule,
                            weights={_NAME: p.mean_weight}, peak_weights={_NAME: p.peak_weight},
                            power=p.combine == "energy", frame="uv", terms=want, grating_maps=maps)

    __call__ = metrics

    def search_terms(self, img: Tensor, reference: Tensor, terms: Iterable[str] | None = None) -> dict[str, Tensor]:
        """A sector scene's search terms ``{name: (B,)}`` (module docstring) of power patterns ``img``
        ``(B, Hv, Hu)`` against the full array's ``reference`` ``(Hv, Hu)``, differentiable in
        ``img``; the ``bp_`` metrics without gradient. ``terms`` limits them (default
        :data:`SEARCH_NAMES`)."""
        p = self.pattern
        planes, coords = {_NAME: img}, {_NAME: p.coords}
        reg = main_lobe_regions({_NAME: img.detach()}, coords, target=(0.0, 0.0, 0.0), rule=self.rule,
                                power=True, frame="uv")
        m = lobe_metrics(planes, coords, target=(0.0, 0.0, 0.0), rule=self.rule, regions=reg,
                         weights={_NAME: p.mean_weight}, peak_weights={_NAME: p.peak_weight}, power=True,
                         frame="uv", terms=("PSL_dB", "ISLR_dB", "width_u_6dB", "width_v_6dB"))
        main = reg.main[_NAME].to(img.dtype)
        wt = p.mean_weight.to(img.dtype)
        side = (1 - main) * wt
        inner = main * wt
        contrast = ((img * side).sum((1, 2)) / side.sum((1, 2)).clamp(min=_TINY)) / (
            (img * inner).sum((1, 2)) / inner.sum((1, 2)).clamp(min=_TINY)).clamp(min=_TINY)
        amp = (img.clamp(min=0) + _TINY).sqrt()
        ref = reference.clamp(min=0).sqrt().to(img.dtype)
        a_ref = (amp * ref * wt).sum((1, 2)) / (amp * amp * wt).sum((1, 2)).clamp(min=_TINY)
        l_psf = ((a_ref[:, None, None] * amp - ref) ** 2 * wt).sum((1, 2)) / (ref * ref * wt).sum()
        q = 10.0 ** (m["PSL_dB"] / 20.0)
        i = 10.0 ** (m["ISLR_dB"] / 10.0)
        out = {"L_PSF": l_psf, "L_contrast": contrast, "L_SLR_q": q, "L_SLR_i": i, "L_SLR": (q + i) / 2,
               "Mean": (l_psf + contrast + q + i) / 4}
        out.update({f"bp_{k}": v.detach() for k, v in m.items()})
        return out if terms is None else {k: out[k] for k in terms}
