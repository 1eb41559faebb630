"""Memory of what the fast path precomputes, measured on the objective itself.

Lists every tensor held by ``Objective.psf.basis`` and by the stored
full-rank basis it is truncated from (``basis.finer``; tensors that share
storage are counted once): ``U``/``V`` the compressed pair images on the
window + margin region, ``strip_images`` the strips' pair images (and their
block factors ``strip_left``/``strip_right``), ``core_images`` the core's,
``certificates.pair_channels`` the pair I/Q signals of the certificates,
``certificates.block_envelopes_e``/``_band`` the sparse block matrices,
with shape, dtype and size, plus the
exact-path DAS plans cached by ``PSFModel`` after one exact evaluation.

Usage::

    python benchmarks/memory.py [--dtype float32|float64] [--no-exact]

The last output line is a JSON record {name: bytes}.
"""
from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _common as C  # noqa: E402


def tensor_bytes(t) -> int:
    import torch

    if t.layout == torch.sparse_csr:
        return sum(x.numel() * x.element_size() for x in (t.crow_indices(), t.col_indices(), t.values()))
    if t.layout == torch.sparse_coo:
        t = t.coalesce()
        return sum(x.numel() * x.element_size() for x in (t.indices(), t.values()))
    return t.numel() * t.element_size()


def describe(t) -> str:
    import torch

    if t.layout == torch.sparse_csr:
        return f"CSR {tuple(t.shape)}, nnz {t.values().numel()}, {t.values().dtype}"
    return f"{tuple(t.shape)} {t.dtype}"


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    p.add_argument("--no-exact", action="store_true", help="skip the exact-path DAS plan measurement")
    args = p.parse_args(argv)
    import torch

    from arraysel.objective.psf_objective import build_objective

    obj = build_objective("paper", dtype=torch.float32 if args.dtype == "float32" else torch.float64)
    fast = obj.psf.basis
    rows, record = [], {}
    seen = set()  # storages counted once: the run-time basis is a truncated view of the stored one
    views = ([("basis.finer", fast.finer)] if getattr(fast, "finer", None) is not None else []) + [("basis", fast)]
    views.append(("basis.layout", fast.layout))  # the regions, pairs and blocks (a part of the basis)
    views.append(("basis.certificates", fast.certificates))  # the pair channels and block matrices
    for prefix, obj_ in views:
        for name, val in sorted(vars(obj_).items()):
            if isinstance(val, torch.Tensor) and (val.numel() > 0 or val.layout != torch.strided):
                key = val.untyped_storage().data_ptr() if val.layout == torch.strided else id(val)
                if key in seen:
                    continue
                seen.add(key)
                b = tensor_bytes(val)
                rows.append([f"{prefix}.{name}", describe(val), f"{b / 2**20:.1f} MiB"])
                record[f"{prefix}.{name}"] = b
    total = sum(record.values())
    rows.append(["fast basis, total", "", f"{total / 2**20:.1f} MiB"])
    info = {k: getattr(fast, k) for k in ("rank", "rank_tail", "shape", "npix", "npix2")}
    info.update({k: getattr(fast.certificates, k) for k in ("window_samples", "max_run")})
    if not args.no_exact:
        obj.psf.kernels_exact(torch.ones(1, obj.n_elements))
        plan_b = 0
        for plan in obj.psf._plans.values():
            plan_b += sum(tensor_bytes(getattr(plan, k)) for k in ("i0", "w", "rot"))
        rows.append([f"exact-path DAS plans ({len(obj.psf._plans)} cached)", "i0, w, rot per pixel x element",
                     f"{plan_b / 2**20:.1f} MiB"])
        record["exact.das_plans"] = plan_b
    print(f"memory: paper scene, {args.dtype}; basis info {info}")
    print(C.table(rows, ["tensor", "shape / layout", "size"]))
    record["fast_total"] = total
    C.emit_json(record)


if __name__ == "__main__":
    main()
