"""What a scanner allows a selection to be: channel groups, forced elements, symmetry.

A :class:`Constraints` object states, for one probe of ``n_elements`` elements and a selection
of ``k`` of them:

* **channel groups** (``groups``: one group number per element, a partition of the elements):
  a selection holds exactly one element of every group (``group_mode = "exactly-one"``) or at
  most one (``"at-most-one"``); with ``group_counts`` (``exactly-one`` only) group ``g`` holds
  exactly ``group_counts[g]`` elements: the quota of separate transmit and receive apertures
  (:func:`aperture_constraints`, ``docs/apertures.md``). :func:`mux_groups` gives the group map
  of a multiplexer rule (``mux-1024-4``: four banks of 256 elements, scanner channel ``c``
  reaches element ``c`` of each bank), :func:`read_group_csv` reads one from a CSV file
  (``element,group``);
* **forced elements**: ``forced_on`` elements are always selected, ``forced_off`` ones never
  (dead elements, unconnected rows);
* **symmetry** (``"x"``: mirror in x, the image of (x, y) is (-x, y); ``"y"``; ``"xy"``: both,
  four-fold): an element is selected exactly when its mirror images are (from the element
  positions, so any probe whose centres are symmetric).

Every built-in selector respects them by construction. The runner hands a selector the
*reduced* problem (:class:`arraysel.selectors.constrained.ConstrainedObjective`): its elements
are the free **units** (an element, or with symmetry the orbit of an element under the mirrors),
forced elements are added when a selection is scored, and only the channel groups remain for the
selector to honour (:attr:`Constraints.reduced`; the search helpers :meth:`random_masks`,
:meth:`swap_pairs`, :meth:`random_swap_pairs`, :meth:`random_swaps`, :meth:`crossover`,
:meth:`project`). :meth:`check` names the constraint a selection breaks
(:class:`ConstraintError`); ``docs/constraints.md`` describes the rules.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from arraysel.errors import ParameterError, SelectionError
from arraysel.groupmaps import group_map, mirror_orbits, mux_groups, read_group_csv

__all__ = ["Constraints", "ConstraintError", "GROUP_MODES", "SYMMETRIES", "mux_groups", "read_group_csv",
           "group_map", "mirror_orbits", "constraints_of", "group_constraints", "refuse_groups",
           "aperture_constraints"]

GROUP_MODES = ("exactly-one", "at-most-one")
SYMMETRIES = ("none", "x", "y", "xy")


class ConstraintError(SelectionError):
    """A selection breaks a constraint; ``constraint`` names it (``k``, ``forced_on``,
    ``forced_off``, ``groups`` or ``symmetry``)."""

    def __init__(self, constraint: str, message: str):
        super().__init__(f"the selection breaks the constraint {constraint}: {message}")
        self.constraint = constraint


def _indices(name: str, values: Any, n: int) -> tuple[int, ...]:
    vals = np.asarray(list(values) if values is not None else [], dtype=np.float64).reshape(-1)
    if vals.size and (not np.all(vals == np.round(vals)) or vals.min() < 0 or vals.max() >= n):
        raise ParameterError(f"constraints.{name} must be element indices in [0, {n - 1}], got {values!r}")
    return tuple(sorted(set(int(v) for v in vals)))


# ---------------------------------------------------------------------------
# the constraints
# ---------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Constraints:
    """The constraints on a selection of ``k`` of ``n_elements`` elements (module docstring).

    ``groups``: one group number per element or None; ``group_mode``: ``exactly-one`` or
    ``at-most-one``; ``group_counts``: with ``exactly-one``, the number of elements each group
    holds (indexed by group number; None: one each); ``forced_on`` / ``forced_off``: element
    indices; ``symmetry``: ``none``, ``x``, ``y`` or ``xy`` (needs ``positions``, (Ne, 2 or 3) element centres); ``source``: the
    group rule's name for messages. Forced sets are closed under the symmetry (the mirror image
    of a dead element is off too). Every inconsistency is a :class:`ParameterError` naming it.
    """

    n_elements: int
    k: int
    groups: Any = None
    group_mode: str = "exactly-one"
    forced_on: tuple = ()
    forced_off: tuple = ()
    symmetry: str = "none"
    positions: Any = field(default=None, repr=False)
    source: str = ""
    group_counts: Any = None

    def __post_init__(self) -> None:
        n, k = int(self.n_elements), int(self.k)
        if n < 1 or not 0 <= k <= n:
            raise ParameterError(f"constraints: k = {k} must be in [0, {n}]")
        set_ = functools.partial(object.__setattr__, self)
        set_("n_elements", n)
        set_("k", k)
        if self.group_mode not in GROUP_MODES:
            raise ParameterError(f"constraints.mode = {self.group_mode!r}; allowed: {', '.join(GROUP_MODES)}")
        if self.symmetry not in SYMMETRIES:
            raise ParameterError(f"constraints.symmetry = {self.symmetry!r}; allowed: {', '.join(SYMMETRIES)}")
        if not self.source and isinstance(self.groups, (str, Path)):
            set_("source", str(self.groups))
        groups = None if self.groups is None else group_map(self.groups, n)
        set_("groups", groups)
        set_("counts", None if groups is None else _group_counts(self.group_counts, groups, self.group_mode))
        on, off = _indices("forced_on", self.forced_on, n), _indices("forced_off", self.forced_off, n)
        if self.symmetry != "none":
            if groups is not None:
                raise ParameterError("constraints: symmetry together with channel groups is not supported; "
                                     "give one of constraints.groups and constraints.symmetry")
            if self.positions is None:
                raise ParameterError("constraints.symmetry needs the element positions")
            orbits = mirror_orbits(self.positions, self.symmetry)
            on = tuple(sorted(set(orbits[list(on)].reshape(-1).tolist())))
            off = tuple(sorted(set(orbits[list(off)].reshape(-1).tolist())))
        else:
            orbits = np.arange(n)[:, None]
        both = sorted(set(on) & set(off))
        if both:
            raise ParameterError(f"constraints: elements {both[:10]} are forced both on and off"
                                 + (" (with their mirror images)" if self.symmetry != "none" else ""))
        set_("forced_on", on)
        set_("forced_off", off)
        set_("orbits", orbits)
        self._derive()

    def _derive(self) -> None:
        """The free units, the open groups and the number of units a selection takes."""
        n, set_ = self.n_elements, functools.partial(object.__setattr__, self)
        state = np.zeros(n, dtype=np.int8)  # 0 free, 1 on, -1 off
        state[list(self.forced_on)] = 1
        state[list(self.forced_off)] = -1
        need = self.k - len(self.forced_on)
        if need < 0:
            raise ParameterError(f"constraints: {len(self.forced_on)} elements forced on, more than k = {self.k}")
        unit_groups = None
        set_("unit_group_counts", None)
        if self.groups is not None:
            gids, inv = np.unique(self.groups, return_inverse=True)
            cap = self.counts[gids]
            on_count = np.bincount(inv[list(self.forced_on)], minlength=gids.size)
            if (on_count > cap).any():
                g = np.flatnonzero(on_count > cap)[0]
                raise ParameterError(f"constraints: group {int(gids[g])} has {int(on_count[g])} elements forced on; "
                                     f"a group holds at most {_number(cap[g])}")
            closed = on_count[inv] >= cap[inv]
            state[closed & (state == 0)] = -1  # the rest of a full group (forced elements) cannot be chosen
            open_g = np.flatnonzero(on_count < cap)
            left = cap - on_count
            free_count = np.bincount(inv[state == 0], minlength=gids.size)
            if self.group_mode == "exactly-one":
                empty = open_g[free_count[open_g] < left[open_g]]
                if empty.size:
                    g = empty[0]
                    what = "every element" if free_count[g] == 0 else "too many elements"
                    raise ParameterError(f"constraints: group {int(gids[g])} has {what} forced off; "
                                         f"'exactly-one' needs {_number(left[g])} of them (use mode = 'at-most-one')")
                if need != int(left[open_g].sum()):
                    raise ParameterError(f"constraints: 'exactly-one' of {gids.size} groups selects "
                                         f"{int(cap.sum())} elements; selection.k = {self.k}")
            elif need > int((free_count[open_g] > 0).sum()):
                raise ParameterError(f"constraints: k = {self.k} is more than the {gids.size} groups allow "
                                     f"(at most one element each)")
            renum = np.full(gids.size, -1, dtype=np.int64)
            renum[open_g] = np.arange(open_g.size)
            unit_groups = renum[inv[state == 0]]
            set_("unit_group_counts", left[open_g].astype(np.int64))
        units = self.orbits[state == 0]
        if units.size:
            units = np.unique(np.sort(units, axis=1), axis=0)
        sizes = np.array([np.unique(u).size for u in units]) if len(units) else np.array([1])
        if sizes.min() != sizes.max():
            raise ParameterError(f"constraints.symmetry = {self.symmetry!r}: elements on a mirror line have "
                                 f"fewer images than the rest (an odd number of rows or columns); force the "
                                 f"elements on the mirror lines off or on")
        size = int(sizes[0])
        units = [np.unique(u) for u in units]
        if need % size:
            raise ParameterError(f"constraints.symmetry = {self.symmetry!r}: k - forced_on = {need} is not a "
                                 f"multiple of {size} (the elements a mirror image set holds)")
        if need // size > len(units):
            raise ParameterError(f"constraints: k = {self.k} needs {need // size} free element sets, "
                                 f"only {len(units)} are left")
        set_("units", units)
        set_("unit_size", size)
        set_("k_units", need // size)
        set_("unit_groups", unit_groups)
        unit_of = np.full(n, -1, dtype=np.int64)
        for i, u in enumerate(units):
            unit_of[u] = i
        set_("unit_of", unit_of)

    # -- properties -------------------------------------------------------------------------
    @property
    def trivial(self) -> bool:
        """No constraint at all (the reduced problem is the problem)."""
        return self.groups is None and not self.forced_on and not self.forced_off and self.symmetry == "none"

    @property
    def simple(self) -> bool:
        """Only channel groups (or nothing): the reduced problem is this one."""
        return not self.forced_on and not self.forced_off and self.symmetry == "none"

    @functools.cached_property
    def reduced(self) -> "Constraints | None":
        """The constraints a selector of the reduced problem honours: the channel groups over the
        free units (None without groups)."""
        if self.unit_groups is None:
            return None
        if self.simple:
            return self
        return Constraints(len(self.units), self.k_units, self.unit_groups, self.group_mode, source=self.source,
                           group_counts=self.unit_group_counts)

    def describe(self) -> str:
        """One line: what is constrained."""
        parts = []
        if self.groups is not None:
            counts = "" if (self.counts == 1).all() else f", counts {self.counts.tolist()[:8]}"
            parts.append(f"groups {self.source or 'map'} ({np.unique(self.groups).size}, {self.group_mode}{counts})")
        if self.forced_on:
            parts.append(f"{len(self.forced_on)} forced on")
        if self.forced_off:
            parts.append(f"{len(self.forced_off)} forced off")
        if self.symmetry != "none":
            parts.append(f"symmetry {self.symmetry}")
        return ", ".join(parts) or "none"

    # -- reduced <-> elements ---------------------------------------------------------------
    def expand(self, unit_masks: np.ndarray) -> np.ndarray:
        """Element masks ``(B, Ne)`` of unit masks ``(B, n_units)`` (forced elements added)."""
        u = np.asarray(unit_masks, dtype=bool)
        flat = u.reshape(-1, u.shape[-1])
        ext = np.concatenate([flat, np.zeros((flat.shape[0], 1), dtype=bool)], axis=1)
        out = ext[:, self.unit_of]  # unit_of = -1 picks the appended False
        out[:, list(self.forced_on)] = True
        return out.reshape(u.shape[:-1] + (self.n_elements,))

    def expand_indices(self, units) -> list[int]:
        """The elements of a selection of units (forced elements added), sorted."""
        m = np.zeros(len(self.units), dtype=bool)
        m[np.asarray(list(units), dtype=np.int64)] = True
        return [int(i) for i in np.flatnonzero(self.expand(m))]

    def reduce_indices(self, elements) -> list[int]:
        """The units of a feasible element selection (checked)."""
        mask = self._mask(elements)
        self.check(mask)
        return sorted(set(int(self.unit_of[e]) for e in np.flatnonzero(mask) if self.unit_of[e] >= 0))

    def _mask(self, selection) -> np.ndarray:
        a = np.asarray(selection)
        if a.dtype == bool and a.shape == (self.n_elements,):
            return a
        m = np.zeros(self.n_elements, dtype=bool)
        m[a.astype(np.int64).reshape(-1)] = True
        return m

    # -- checks -----------------------------------------------------------------------------
    def check(self, selection) -> None:
        """Raise :class:`ConstraintError` naming the first constraint ``selection`` (element
        indices or a boolean mask) breaks."""
        m = self._mask(selection)
        if int(m.sum()) != self.k:
            raise ConstraintError("k", f"{int(m.sum())} elements selected, the scene asks for {self.k}")
        off = [e for e in self.forced_off if m[e]]
        if off:
            raise ConstraintError("forced_off", f"elements {off[:10]} are forced off but selected")
        on = [e for e in self.forced_on if not m[e]]
        if on:
            raise ConstraintError("forced_on", f"elements {on[:10]} are forced on but not selected")
        if self.groups is not None:
            count = np.bincount(self.groups[m], minlength=int(self.groups.max()) + 1)
            cap = self.counts
            many = np.flatnonzero(count > cap)
            if many.size:
                g = int(many[0])
                held = np.flatnonzero(m & (self.groups == g)).tolist()
                raise ConstraintError("groups", f"group {g} of {self.source or 'the group map'} holds "
                                      f"{int(count[g])} selected elements {held[:10]}; "
                                      f"at most {_number(cap[g])} {'is' if cap[g] == 1 else 'are'} allowed")
            if self.group_mode == "exactly-one":
                present = np.unique(self.groups)
                none = present[count[present] < cap[present]]
                if none.size:
                    g = int(none[0])
                    held = "no selected element" if count[g] == 0 else f"{int(count[g])} selected elements"
                    raise ConstraintError("groups", f"group {g} of {self.source or 'the group map'} "
                                          f"holds {held}; exactly {_number(cap[g])} {'is' if cap[g] == 1 else 'are'} "
                                          f"required")
        if self.symmetry != "none":
            bad = np.flatnonzero((m[self.orbits] != m[:, None]).any(axis=1))
            if bad.size:
                e = int(bad[0])
                raise ConstraintError("symmetry", f"element {e} is {'on' if m[e] else 'off'} but its mirror "
                                      f"images {self.orbits[e].tolist()} are not all {'on' if m[e] else 'off'} "
                                      f"(symmetry {self.symmetry!r})")

    def feasible(self, selection) -> bool:
        """Whether ``selection`` (indices or a mask) meets every constraint."""
        try:
            self.check(selection)
        except ConstraintError:
            return False
        return True

    def feasible_rows(self, masks: np.ndarray) -> np.ndarray:
        """``(B,)`` booleans: which rows of ``masks`` ``(B, Ne)`` meet every constraint."""
        m = np.asarray(masks, dtype=bool).reshape(-1, self.n_elements)
        ok = m.sum(axis=1) == self.k
        if self.forced_off:
            ok &= ~m[:, list(self.forced_off)].any(axis=1)
        if self.forced_on:
            ok &= m[:, list(self.forced_on)].all(axis=1)
        if self.groups is not None:
            onehot = self._onehot
            count = m.astype(np.int32) @ onehot
            ok &= (count <= self.counts).all(axis=1)
            if self.group_mode == "exactly-one":
                present = onehot.sum(axis=0) > 0
                ok &= (count[:, present] == self.counts[present]).all(axis=1)
        if self.symmetry != "none":
            ok &= (m[:, self.orbits] == m[:, :, None]).all(axis=(1, 2))
        return ok

    @functools.cached_property
    def _onehot(self) -> np.ndarray:
        g = self.groups
        out = np.zeros((self.n_elements, int(g.max()) + 1), dtype=np.int32)
        out[np.arange(self.n_elements), g] = 1
        return out

    # -- choosing feasible selections ------------------------------------------------------
    @functools.cached_property
    def _segments(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The units ordered by group: (group of each unit, first position of each group, sizes)."""
        g = self.unit_groups
        sizes = np.bincount(g)
        return g, np.cumsum(sizes) - sizes, sizes

    def select_units(self, unit_scores: np.ndarray) -> np.ndarray:
        """Unit masks ``(B, n_units)`` of the feasible selections that prefer high ``unit_scores``
        ``(B, n_units)``: without groups the ``k_units`` highest; with groups the highest unit of
        every group (``exactly-one``), or of the ``k_units`` groups whose best is highest
        (``at-most-one``). Ties go to the lower index."""
        s = np.atleast_2d(np.asarray(unit_scores, dtype=np.float64))
        s = np.where(np.isfinite(s), s, -np.inf)
        b, n = s.shape
        out = np.zeros((b, n), dtype=bool)
        rows = np.arange(b)[:, None]
        if self.unit_groups is None:
            order = np.argsort(-s, axis=1, kind="stable")[:, :self.k_units]
            out[rows, order] = True
            return out
        g, first, _ = self._segments
        rank = np.empty_like(s)
        rank[rows, np.argsort(-s, axis=1, kind="stable")] = np.arange(n) / max(n, 1)
        order = np.argsort(g[None, :] + rank, axis=1, kind="stable")  # by group, then preference
        c = self.unit_group_counts
        if c is not None and (c != 1).any():  # quotas (exactly-one only): each group's c best
            out[rows, order[:, np.repeat(first, c) + _within(c)]] = True
            return out
        best = order[:, first]  # (B, G): each group's best
        if self.group_mode == "at-most-one":
            pick = np.argsort(np.take_along_axis(rank, best, axis=1), axis=1, kind="stable")[:, :self.k_units]
            best = np.take_along_axis(best, pick, axis=1)
        out[rows, best] = True
        return out

    def project(self, scores) -> list[int]:
        """The feasible selection (element indices) nearest a preference: ``scores`` (Ne,) over the
        elements, higher preferred (a mask of an unconstrained selection is one). A unit scores
        the mean of its elements; :meth:`select_units` picks the units; forced elements added."""
        s = np.asarray(scores, dtype=np.float64).reshape(self.n_elements)
        us = np.stack([s[u].mean() for u in self.units]) if self.units else np.zeros(0)
        return [int(i) for i in np.flatnonzero(self.expand(self.select_units(us[None])[0]))]

    def random_masks(self, rng: np.random.Generator, b: int) -> np.ndarray:
        """``(b, n_units)`` uniformly random feasible unit masks (with groups: a uniform element of
        every group, or of ``k_units`` uniform groups)."""
        return self.select_units(rng.random((int(b), len(self.units))))

    def swap_pairs(self, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every feasible one-in-one-out swap ``(out, into)`` of a unit mask: with groups the unit
        swapped in belongs to the group of the one swapped out (or, ``at-most-one``, to a group
        the selection leaves empty)."""
        m = np.asarray(mask, dtype=bool)
        on, off = np.flatnonzero(m), np.flatnonzero(~m)
        a, b = np.repeat(on, off.size), np.tile(off, on.size)
        keep = self.allowed_swaps(m, a, b)
        return a[keep], b[keep]

    def allowed_swaps(self, mask: np.ndarray, out: np.ndarray, into: np.ndarray) -> np.ndarray:
        """Which swaps ``(out[i], into[i])`` of the unit mask ``mask`` keep it feasible."""
        out, into = np.asarray(out, dtype=np.int64), np.asarray(into, dtype=np.int64)
        if self.unit_groups is None:
            return np.ones(out.size, dtype=bool)
        g = self.unit_groups
        keep = g[out] == g[into]
        if self.group_mode == "at-most-one":
            occupied = np.zeros(int(g.max()) + 1, dtype=bool)
            occupied[g[np.flatnonzero(mask)]] = True
            keep |= ~occupied[g[into]]
        return keep

    def random_swap_pairs(self, mask: np.ndarray, b: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``min(b, all)`` distinct random feasible swaps of a unit mask (:meth:`swap_pairs`)."""
        a, c = self.swap_pairs(mask)
        pick = rng.choice(a.size, size=min(int(b), a.size), replace=False)
        return a[pick], c[pick]

    def random_swaps(self, mask: np.ndarray, m: int, rng: np.random.Generator) -> np.ndarray:
        """``mask`` after ``m`` random feasible swaps, each of units no earlier swap touched."""
        out = np.asarray(mask, dtype=bool).copy()
        touched = np.zeros(out.size, dtype=bool)
        for _ in range(int(m)):
            a, b = self.swap_pairs(out)
            ok = ~touched[a] & ~touched[b]
            if not ok.any():
                break
            i = rng.choice(np.flatnonzero(ok))
            out[a[i]], out[b[i]] = False, True
            touched[[a[i], b[i]]] = True
        return out

    def crossover(self, p1: np.ndarray, p2: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """A feasible child of two feasible unit masks: what both parents hold first, then what one
        holds, in a random order (:meth:`select_units` of ``2 both + either + random / 2``): with
        ``exactly-one`` groups each group takes one parent's choice."""
        a, b = np.asarray(p1, dtype=bool), np.asarray(p2, dtype=bool)
        return self.select_units(2.0 * (a & b) + (a | b) + 0.5 * rng.random(a.size))[0]


def _group_counts(spec, groups: np.ndarray, mode: str) -> np.ndarray:
    """The number of elements each group number holds (array indexed by group number)."""
    size = int(groups.max()) + 1
    if spec is None:
        return np.ones(size, dtype=np.int64)
    c = np.asarray(spec).reshape(-1)
    if c.size != size or c.dtype.kind not in "iu" or (c < 1).any():
        raise ParameterError(f"constraints.group_counts must give a count >= 1 for each of the {size} group "
                             f"numbers, got {spec!r}")
    if mode != "exactly-one" and (c != 1).any():
        raise ParameterError("constraints.group_counts other than one need mode = 'exactly-one'")
    size_of = np.bincount(groups, minlength=size)
    bad = np.flatnonzero((size_of > 0) & (c > size_of))
    if bad.size:
        g = int(bad[0])
        raise ParameterError(f"constraints.group_counts: group {g} holds {int(size_of[g])} elements, fewer than "
                             f"its count {int(c[g])}")
    return c.astype(np.int64)


def _within(counts: np.ndarray) -> np.ndarray:
    """``0 .. c - 1`` for every count ``c``, concatenated."""
    return np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)


def _number(c) -> str:
    return "one" if int(c) == 1 else str(int(c))


def aperture_constraints(n_elements: int, k_tx: int, k_rx: int, each: Constraints | None = None,
                         n_events: int = 1) -> Constraints:
    """The quota of separate transmit and receive apertures on the virtual problem of
    ``2 n_elements`` units (transmit elements ``0 .. Ne - 1``, then the receive elements): exactly
    ``k_tx`` of the first ``Ne`` and ``k_rx`` of the rest (two groups with counts). With
    ``n_events`` > 1 (per-transmit apertures) the problem has ``(n_events + 1) Ne`` units: block
    ``n`` (units ``n Ne .. (n + 1) Ne - 1``) is transmit event ``n``'s aperture of ``k_tx``
    elements, the last block the receive aperture of ``k_rx``.

    ``each``: the scene's constraints, which each aperture meets on its own. Forced elements are
    forced in both apertures (a dead element neither transmits nor receives); ``exactly-one``
    channel groups are kept in each half (the two halves' groups replace the quota, so ``k_tx`` and
    ``k_rx`` must each be what the groups select). ``at-most-one`` groups and symmetry are refused
    with an error naming the key. ``docs/apertures.md``."""
    n = int(n_elements)
    for key, v in (("aperture.k_tx", k_tx), ("aperture.k_rx", k_rx)):
        if not 1 <= int(v) <= n:
            raise ParameterError(f"{key} = {v} is out of range; allowed: [1, {n}] (the probe has {n} elements)")
    if int(n_events) < 1:
        raise ParameterError(f"n_events = {n_events}: a transmit aperture needs at least one transmit event")
    blocks = int(n_events) + 1
    quota = [int(k_tx)] * (blocks - 1) + [int(k_rx)]
    k, size_all = sum(quota), blocks * n
    what = "apertures (transmit, receive)" if blocks == 2 else f"apertures ({blocks - 1} transmit events, receive)"
    if each is None or each.trivial:
        groups = np.repeat(np.arange(blocks, dtype=np.int64), n)
        return Constraints(size_all, k, groups=groups, group_counts=quota, source=what)
    if each.n_elements != n:
        raise ParameterError(f"constraints are for {each.n_elements} elements; the probe has {n}")
    if each.symmetry != "none":
        raise ParameterError(f"constraints.symmetry = {each.symmetry!r} together with aperture.mode = 'separate' is "
                             "not supported; allowed there: 'none'")
    on = [e + b * n for b in range(blocks) for e in each.forced_on]
    off = [e + b * n for b in range(blocks) for e in each.forced_off]
    if each.groups is None:
        groups, counts, source = np.repeat(np.arange(blocks, dtype=np.int64), n), quota, what
    else:
        if each.group_mode != "exactly-one":
            raise ParameterError(f"constraints.mode = {each.group_mode!r} together with aperture.mode = 'separate' "
                                 "is not supported; allowed there: 'exactly-one'")
        per = int(each.counts[np.unique(each.groups)].sum())
        for key, v in (("aperture.k_tx", k_tx), ("aperture.k_rx", k_rx)):
            if int(v) != per:
                raise ParameterError(f"{key} = {v}: the channel groups ({each.describe()}) select exactly {per} "
                                     f"elements in each aperture; allowed: {per}")
        size = int(each.groups.max()) + 1
        groups = np.concatenate([each.groups + b * size for b in range(blocks)])
        counts = np.concatenate([each.counts] * blocks)
        source = f"{each.source or 'groups'} in each aperture"
    return Constraints(size_all, k, groups=groups, group_counts=counts, forced_on=on, forced_off=off, source=source)


def constraints_of(objective) -> Constraints | None:
    """The objective's constraints (its ``constraints`` attribute), None when it has none or they
    constrain nothing."""
    c = getattr(objective, "constraints", None)
    return None if c is None or c.trivial else c


def group_constraints(objective) -> Constraints | None:
    """The channel groups a selector must honour on ``objective`` (the reduced problem the runner
    hands it), None without groups. Forced elements and symmetry are the runner's
    (:class:`arraysel.selectors.constrained.ConstrainedObjective`): an objective that still
    carries them was not reduced, and is refused."""
    c = constraints_of(objective)
    if c is None:
        return None
    if not c.simple:
        raise ParameterError(f"this objective has constraints ({c.describe()}) that only the runner's "
                             f"reduced problem resolves; run the selector through arraysel.run.Experiment")
    return c


def refuse_groups(objective, selector: str) -> None:
    """Raise :class:`ParameterError` when ``objective`` carries channel groups, which ``selector``
    cannot honour by construction (forced elements and symmetry it meets on the reduced problem)."""
    gc = group_constraints(objective)
    if gc is not None:
        raise ParameterError(f"selector {selector!r} cannot honour the constraint groups ({gc.describe()}); "
                             f"use swap, anneal, ils, lns, memetic, genetic, ste, gumbel, random, uniform or spiral")
