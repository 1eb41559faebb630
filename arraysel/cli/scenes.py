"""``arraysel scenes [NAME] [--show]``: the built-in scenes, and a scene's resolved keys.

Without NAME: one line per built-in scene (probe, elements, k, field points,
description). With NAME (a built-in scene or a .toml path): every key of the
scene schema with its value, where it comes from (``scene``: set by the scene
or its base; ``default``: the schema's default) and, for keys given with a
unit, the value in the key's own unit. ``--json`` prints the same as JSON.
"""
from __future__ import annotations

import json

from arraysel.scenes.schema import SCHEMA, builtin_scenes, load_scene


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "scenes", help="list the built-in scenes, or show a scene's resolved keys",
        description="List the built-in scenes; with a NAME (or a .toml path), show every scene key with "
                    "its value, whether the scene sets it or the default applies, and lengths in their "
                    "resolved units (pixels, wavelengths, metres).")
    p.add_argument("name", nargs="?", metavar="NAME", help="a built-in scene or a scene file (.toml)")
    p.add_argument("--show", action="store_true",
                   help="show the resolved keys (implied by NAME; with no NAME: of every built-in scene)")
    p.add_argument("--all", action="store_true", help="also list keys without a value (no default)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)


def _fmt(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _unit_note(section: str, key: str, res) -> str:
    if res is None:
        return ""
    spec = SCHEMA[section][key]
    if spec.kind == "points":
        return "= " + ", ".join(f"({x * 1e3:.4g}, {z * 1e3:.4g}) mm" for x, z in res)
    unit = {"px": "px", "wl": "wavelengths", "m": "m"}[spec.unit]
    return f"= {_fmt(res)} {unit}"


def _summary(name: str) -> dict:
    sc = load_scene(name)
    pts = sc.points()
    probe = sc.probe()
    return {"name": name, "probe": probe.name, "n_elements": probe.n_elements, "k": sc.k,
            "points_mm": [[round(x * 1e3, 4), round(z * 1e3, 4)] for x, z in pts],
            "description": sc.description}


def _show(name: str, show_all: bool) -> dict:
    sc = load_scene(name)
    out = {"name": sc.name, "description": sc.description, "sections": {}}
    for sec, rows in sc.resolved().items():
        keep = {k: v for k, v in rows.items() if show_all or v[0] is not None}
        if keep:
            out["sections"][sec] = {k: {"value": v, "resolved": r, "source": src, "help": SCHEMA[sec][k].help}
                                    for k, (v, r, src) in keep.items()}
    return out


def _print_show(data: dict) -> None:
    print(f"# scene {data['name']}: {data['description']}")
    print("# key = value  # source (scene: set by the scene or its base; default: the schema's default;")
    print("#                derived: from other keys), then the value in the key's own unit")
    for sec, rows in data["sections"].items():
        print(f"\n[{sec}]")
        width = max(len(f"{k} = {_fmt(r['value'])}") for k, r in rows.items())
        for k, r in rows.items():
            left = f"{k} = {_fmt(r['value'])}" if r["value"] is not None else f"# {k} (not set)"
            note = _unit_note(sec, k, r["resolved"])
            extra = f"  {note}" if note else ""
            print(f"{left.ljust(width)}  # {r['source']}{extra}")


def run(args) -> int:
    if args.name is None and not args.show:
        rows = [_summary(n) for n in builtin_scenes()]
        if args.json:
            print(json.dumps(rows, indent=2))
            return 0
        head = ("name", "probe", "Ne", "k", "points (x, z) mm")
        table = [(r["name"], r["probe"], str(r["n_elements"]), str(r["k"]),
                  " ".join(f"({x:g}, {z:g})" for x, z in r["points_mm"])) for r in rows]
        widths = [max(len(t[i]) for t in table + [head]) for i in range(len(head))]
        print("  ".join(h.ljust(w) for h, w in zip(head, widths)) + "  description")
        for t, r in zip(table, rows):
            print("  ".join(x.ljust(w) for x, w in zip(t, widths)) + "  " + r["description"])
        print("\nshow a scene's resolved keys and defaults: arraysel scenes NAME")
        return 0
    names = [args.name] if args.name is not None else builtin_scenes()
    shown = [_show(n, args.all) for n in names]
    if args.json:
        print(json.dumps(shown if args.name is None else shown[0], indent=2, default=list))
        return 0
    for i, data in enumerate(shown):
        if i:
            print()
        _print_show(data)
    return 0
