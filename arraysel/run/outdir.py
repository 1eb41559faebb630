"""The output folder of ``arraysel compare``: which files are results, whether a folder may be
written (``--resume`` / ``--force``), and whether a resumed run matches the one on disk."""
from __future__ import annotations

import json
import os
from pathlib import Path

from arraysel.errors import ParameterError, error_text as _error_text
from arraysel.io.atomic import check_writable

__all__ = ["RESULT_FILES", "RESUME_FIELDS", "check_out_dir", "check_resume", "remove_results"]

#: files ``compare`` writes in its folder (``--force`` removes these and nothing else)
RESULT_FILES = ("runs.csv", "table1.csv", "stats.csv", "trace.csv", "trace_nevergrad.csv", "ioh", "run.json",
                "masks.png", "psfs.png", "profiles.png", "trace.png", "anytime.png")
#: fields of ``run.json`` that a resumed run must share with the new one
RESUME_FIELDS = ("scene", "n_elements", "k", "dtype", "budget")


def check_out_dir(out: str | os.PathLike, *, resume: bool = False, force: bool = False) -> dict | None:
    """Check ``out`` before any work: a folder (or creatable), writable, and not holding the
    results of another compare run unless ``resume`` (continue it) or ``force`` (replace it).

    Returns the old ``run.json`` content when resuming (``None`` otherwise, or when there is
    nothing to resume). Raises :class:`ParameterError` with a one-line message."""
    out = Path(out)
    if resume and force:
        raise ParameterError("--resume and --force exclude each other: --resume continues the run in --out, "
                             "--force replaces it")
    if out.exists() and not out.is_dir():
        raise ParameterError(f"--out {str(out)!r} is a file, not a folder")
    check_writable(out / "run.json", "--out")
    held = [n for n in ("runs.csv", "run.json", "table1.csv") if (out / n).exists()]
    if not held:
        return None
    meta = None
    if (out / "run.json").exists():
        try:
            meta = json.loads((out / "run.json").read_bytes().decode("utf-8"))
            if not isinstance(meta, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            if resume:
                raise ParameterError(f"--resume: {out / 'run.json'} is damaged ({_error_text(exc)}); rerun "
                                     f"with --force to start over, or choose another --out") from None
            meta = None
    if resume:
        if meta is None:
            raise ParameterError(f"--resume: {out} has no run.json describing its runs; rerun with --force to "
                                 f"start over, or choose another --out")
        return meta
    if force:
        return None
    status = (meta or {}).get("status", "unknown")
    raise ParameterError(f"--out {str(out)!r} already holds the results of a compare run (status: {status}); "
                         f"rerun with --resume to finish it, with --force to replace it, or choose another --out")


def _plain(value):
    """``value`` as ``run.json`` stores it (JSON round trip, ``default=str``)."""
    return json.loads(json.dumps(value, default=str))


def check_resume(old: dict, now: dict, out) -> None:
    """Refuse to resume when a field of :data:`RESUME_FIELDS` differs between ``old`` (run.json)
    and ``now``; the message names the field and both values (the first differing key of a
    scene)."""
    for field in RESUME_FIELDS:
        if field not in now:
            continue
        a, b = old.get(field), _plain(now[field])
        if a == b:
            continue
        detail = f"{a!r} in run.json, {b!r} now"
        if isinstance(a, dict) and isinstance(b, dict):
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            if keys:
                detail = f"{field}.{keys[0]} is {a.get(keys[0])!r} in run.json, {b.get(keys[0])!r} now"
        raise ParameterError(f"--resume: the runs in {out} were made with a different {field} ({detail}); "
                             f"rerun with --force to start over, or choose another --out")


def remove_results(out: str | os.PathLike) -> None:
    """Remove the files of :data:`RESULT_FILES` from ``out`` (``--force``)."""
    import shutil

    for name in RESULT_FILES:
        path = Path(out) / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
            continue
        try:
            path.unlink()
        except FileNotFoundError:
            pass
