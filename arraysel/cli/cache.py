"""``arraysel cache path|info|clear``: where the precomputation cache is, what it holds, removing it."""
from __future__ import annotations

from arraysel.errors import ParameterError


def add_parser(subparsers) -> None:
    p = subparsers.add_parser(
        "cache", help="show or clear the on-disk cache of precomputed PSF bases",
        description="The PSF fast path precomputes a basis per scene (about 1 GB for the paper scene; the "
                    "first build announces its estimated time, which follows the measured time of the "
                    "latest build in the folder) and keeps it in a cache folder: $ARRAYSEL_CACHE when set "
                    "('off' disables the cache), else the platform's user cache folder. "
                    "'path' prints the folder, 'info' lists what it holds with sizes and state, "
                    "'clear' removes what the cache wrote there (entries are rebuilt when next needed). "
                    "Files and folders the cache did not write are listed as foreign and never removed.")
    p.add_argument("action", choices=("path", "info", "clear"), help="what to do")
    p.set_defaults(func=run)


def run(args) -> int:
    from arraysel.io.cache import _fmt_bytes, cache_dir, clear, list_entries

    folder = cache_dir()
    if folder is None:
        if args.action == "path":
            print("off")
            return 0
        raise ParameterError("the cache is off (ARRAYSEL_CACHE=off): there is nothing to show or clear")
    if args.action == "path":
        print(folder)
    elif args.action == "info":
        entries = list_entries(folder)
        ours = [e for e in entries if e["owner"] == "cache"]
        foreign = len(entries) - len(ours)
        print(f"cache folder: {folder}")
        print(f"{len(ours)} cache item(s), {_fmt_bytes(sum(e['bytes'] for e in ours))} in all"
              + (f"; {foreign} foreign item(s) the cache did not write (never removed)" if foreign else ""))
        for e in entries:
            when = f", created {e['created']}" if e["created"] else ""
            when += f", built in {e['build_seconds']:.0f} s" if e.get("build_seconds") else ""
            print(f"  {e['name']}  {_fmt_bytes(e['bytes'])}  {e['status']}{when}")
    else:
        n, freed = clear(folder)
        left = list_entries(folder)
        foreign = sum(e["owner"] != "cache" for e in left)
        busy = len(left) - foreign
        print(f"removed {n} item(s), {_fmt_bytes(freed)}, from {folder}"
              + (f"; left {foreign} foreign item(s) the cache did not write" if foreign else "")
              + (f"; left {busy} item(s) in use by a running build" if busy else ""))
    return 0
