"""The settings of the swap engine: one frozen :class:`SwapSettings`, one set of defaults, presets.

The swap engine (:class:`~arraysel.selectors.localsearch.SwapSearch` and its elite-pool variant
:class:`~arraysel.selectors.elite.EliteSearch`) reads everything it may be told from a
:class:`SwapSettings`. Its defaults are the configuration that measured best at 20 s and 120 s a
run on the built-in scenes (``docs/selectors.md``, "The defaults of swap"); the selectors built
on the engine are presets of it:

* :data:`SWAP` (``swap``): the defaults;
* :data:`POLISH` (the ``polish`` option of every selector): no race, the descents start from the
  selection it is given;
* :data:`MEMETIC` (``memetic``): the defaults; a memetic search uses the descent settings only;
* :data:`ILS` (``ils``): the defaults' descents, its own rounds (a perturbation that grows up to
  8 swaps, a fresh random start after 40 rounds without a new best, no race).

The settings fall in five groups (:data:`GROUPS`): the descent, the model of the loss that
orders it, the second neighbourhoods a descent tries at a local optimum of swaps, the iterated
local search around the descents, and the race of the first descents.
:func:`swap_options` declares them as a selector's options, with a preset's values as the
defaults.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from arraysel.errors import ParameterError
from arraysel.selectors.contract import Option
from arraysel.selectors.lossmodel import model_options
from arraysel.selectors.moves import SHIFT_LEN, shift_options
from arraysel.selectors.starts import CHIRP_CANDIDATES

#: where fresh selections (restarts, extra starts) come from (``mixed``: chirped and random in turn)
FRESH_CHOICES = ("random", "chirp", "mixed")
#: chirped layouts a ``fresh = chirp`` restart scores (one call), keeping the best
FRESH_CHIRPS = 32
#: share of the budget an automatic race (``race_quota`` None) gives its turns: each turn an
#: equal part of it, split evenly among the descents still racing
RACE_SHARE = 1.0 / 3.0
#: selections a raced descent scores in the first turn without a limited budget (``race_quota``
#: None on an objective whose budget has no limit)
RACE_QUOTA = 500
#: share of the budget an automatic ``race_chirps`` (None) spends on a race's chirped layouts
RACE_CHIRP_SHARE = 0.1
#: chirped layouts an automatic ``race_chirps`` scores first for each chirped start, to learn
#: what one costs
RACE_CHIRP_PROBE = 16

__all__ = ["SwapSettings", "SWAP", "POLISH", "MEMETIC", "ILS", "GROUPS", "swap_options", "settings_from",
           "FRESH_CHOICES", "FRESH_CHIRPS", "RACE_SHARE", "RACE_QUOTA", "RACE_CHIRP_SHARE", "RACE_CHIRP_PROBE"]


@dataclass(frozen=True)
class SwapSettings:
    """Everything the swap engine may be told, checked on construction (a bad value raises
    :class:`~arraysel.errors.ParameterError` naming it). Each field is a selector option of the
    same name; :func:`swap_options` gives its meaning and range, ``docs/selectors.md`` the table.

    ``max_perturb`` at or below ``perturb`` keeps the perturbation at ``perturb`` swaps (a fixed
    strength). ``guide_shifts`` (no selector option) orders a guided descent's segment shifts by
    the model too (False: a random order).
    """

    # the descent
    mode: str = "first"
    chunk: int = 64
    lead: int = 0
    guide: float = 0.875
    scan: float = 0.125
    compound: int = 0
    # the model of the loss that orders it
    model: str | None = None
    refresh: int = 8
    gradient: str = "update"
    # second neighbourhoods at a local optimum of swaps
    shift: int = 6
    shift_len: int = SHIFT_LEN
    shift_scan: int = 512
    pairs: int = 0
    guide_shifts: bool = True
    # the iterated local search around the descents
    perturb: int = 2
    max_perturb: int = 2
    restart_after: int = 30
    fresh: str = "mixed"
    # the race of the first descents
    race: int = 16
    race_quota: int | None = None
    race_chirps: int | None = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            if f.name == "guide_shifts":
                object.__setattr__(self, f.name, bool(self.guide_shifts))
                continue
            value = getattr(self, f.name)
            object.__setattr__(self, f.name, SPECS[f.name].validate(f.name, value))

    def replace(self, **changes) -> "SwapSettings":
        """These settings with ``changes`` (checked; an unknown name raises, listing the known)."""
        unknown = sorted(set(changes) - set(FIELDS))
        if unknown:
            raise ParameterError(f"the swap engine has no setting {', '.join(unknown)}; its settings are: "
                                 f"{', '.join(FIELDS)}")
        return dataclasses.replace(self, **changes) if changes else self


def _option(type_, help_, **kw) -> tuple:
    return type_, help_, kw


#: every setting's type, meaning and range (its default: the field's, in :class:`SwapSettings`)
_TABLE = {
    "mode": _option(str, "first: move at the first chunk holding an improvement (random order, guided); best: "
                    "score all k(Ne-k) neighbours a move", choices=("first", "best")),
    "chunk": _option(int, "neighbours per objective call in first-improvement mode", lo=1),
    "lead": _option(int, "first mode: neighbours in the first chunk a descent scores from each selection, each "
                    "next chunk twice as many up to chunk (cheap steps while most chunks hold an improving swap; "
                    "0: chunk from the first)", lo=0),
    "guide": _option(float, "first share of each first-mode chunk taken in the order the model of the loss "
                     "predicts (adapts to where improvements come from; 0: random order)", lo=0.0, hi=1.0),
    "scan": _option(float, "fraction of the neighbourhood scored without improvement before a local optimum is "
                    "declared (first mode; 1: all of it)", lo=0.001, hi=1.0),
    "compound": _option(int, "first mode: a chunk whose best swap improves takes up to compound of its improving "
                        "swaps on distinct elements together, best first, when that scores better (the "
                        "prefixes scored in one call; 0 or 1: one swap a step)", lo=0),
    "pairs": _option(int, "two-swaps (two elements off, two on) scored at a local optimum of swaps and shifts, "
                     "the ones the quadratic model predicts best, in that order (0: none)", lo=0),
    "perturb": _option(int, "random swaps of a perturbation of the best (swap) or an elite (ils) selection "
                       "(swap: 0 restarts from a fresh selection, see fresh, at each local optimum)", lo=0),
    "max_perturb": _option(int, "most random swaps of a perturbation: the strength grows from perturb by one "
                           "after each perturbation without a new best (variable strength; perturb or less: "
                           "fixed)", lo=0),
    "restart_after": _option(int, "perturbations (rounds) in a row without a new best before a restart from a "
                             "fresh selection, see fresh (0: never restart)", lo=0),
    "fresh": _option(str, f"restarts and extra starts: random selections, chirp (the best of {FRESH_CHIRPS} "
                     "random chirped layouts each, scored in one call; a race's: the best distinct of one "
                     "call), or mixed (chirped and random in turn; a race: half of its extra starts chirped, "
                     "rounded up, the rest random)", choices=FRESH_CHOICES),
    "race": _option(int, "first descents raced by successive halving: the one from start and race - 1 from "
                    "fresh selections, the better half going on after each turn (1: no race)", lo=1),
    "race_quota": _option(int, "selections each raced descent scores in the first turn (doubled each turn); "
                          f"auto: the turns share {RACE_SHARE:.3g} of the budget, each an equal part split "
                          f"among its descents ({RACE_QUOTA} without a limited budget)", lo=1),
    "race_chirps": _option(int, "chirped layouts scored for each chirped extra start of a race (fresh = chirp "
                           "or mixed: the best distinct of race_chirps x their number, in one call; fewer leave "
                           "more of a short budget to the descents); auto: as many as "
                           f"{RACE_CHIRP_SHARE:.3g} of the budget allows, at most {CHIRP_CANDIDATES}", lo=1),
}
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(SwapSettings)}
#: every setting but ``guide_shifts`` as a selector option, with its default
SPECS: dict[str, Option] = {
    **{n: Option(t, _DEFAULTS[n], h, **kw) for n, (t, h, kw) in _TABLE.items()},
    **{n: dataclasses.replace(o, default=_DEFAULTS[n]) for n, o in {**model_options(), **shift_options()}.items()},
}

#: the names of the settings, in the order of :data:`GROUPS`
FIELDS = tuple(f.name for f in dataclasses.fields(SwapSettings))

#: the settings by group (the table of ``docs/selectors.md``); ``guide_shifts`` is no option
GROUPS = {
    "descent": ("mode", "chunk", "lead", "guide", "scan", "compound"),
    "model of the loss": ("model", "refresh", "gradient"),
    "second neighbourhoods": ("shift", "shift_len", "shift_scan", "pairs"),
    "iterated local search": ("perturb", "max_perturb", "restart_after", "fresh"),
    "race": ("race", "race_quota", "race_chirps"),
}

#: ``swap``: the measured best configuration (the defaults)
SWAP = SwapSettings()
#: the ``polish`` option: a polish improves the selection it is given, so it runs no race (a race
#: would spend a third of its budget on descents from other starts)
POLISH = SWAP.replace(race=1)
#: ``memetic``: its descents are the defaults' (it uses the descent settings only)
MEMETIC = SWAP
#: ``ils``: the defaults' descents; its rounds keep what it was built with: a perturbation growing
#: up to 8 swaps, a fresh random start after 40 rounds without a new best, and no race
ILS = SWAP.replace(max_perturb=8, restart_after=40, fresh="random", race=1)


def swap_options(settings: SwapSettings, names=None) -> dict[str, Option]:
    """The settings ``names`` (default: all but ``guide_shifts``, in the order of :data:`GROUPS`) as
    a selector's declared options, each with its value in ``settings`` as the default."""
    names = [n for group in GROUPS.values() for n in group] if names is None else list(names)
    unknown = [n for n in names if n not in SPECS]
    if unknown:
        raise ParameterError(f"the swap engine has no option {', '.join(unknown)}")
    return {n: dataclasses.replace(SPECS[n], default=getattr(settings, n)) for n in names}


def settings_from(preset: SwapSettings, options: dict) -> SwapSettings:
    """``preset`` with the values of ``options`` (a selector's options) that are settings."""
    return preset.replace(**{k: v for k, v in options.items() if k in FIELDS and k != "guide_shifts"})
