"""PSF kernels and planes as netCDF-4 (HDF5) files, with their coordinates, units and scene.

``arraysel psf --out psf.nc`` and ``arraysel evaluate --psf-out psfs.nc`` write them; any netCDF
reader opens them (``xarray.open_dataset``, ``ncdump``, MATLAB's ``ncread``); :func:`open_psf`
gives an :class:`xarray.Dataset` with the complex arrays joined. Needs the ``netcdf`` extra
(``pip install 'arraysel[netcdf]'``: xarray, h5netcdf, h5py).

Layout (``docs/formats.md``):

* a 1-D scene (linear or convex probe): dimensions ``z`` and ``x``, the PSF window around its
  peak, with coordinates ``x`` and ``z`` in metres from the peak; a scene with several field
  points adds the dimension ``point`` (coordinates ``point_x``, ``point_z``: the scatterers);
* a 3-D scene (matrix probe): per plane ``P`` (``xy``, ``xz``, ``yz``) the dimensions ``P_row``,
  ``P_col`` and the 2-D coordinates ``P_x``, ``P_y``, ``P_z``: every pixel's position in metres;
* ``evaluate`` adds the dimension ``selection`` (one per mask of the file, in order);
* complex values are two float variables, ``NAME_real`` and ``NAME_imag`` (netCDF has no complex
  type; every reader takes them): ``psf`` (the selection's kernel, unit L2 norm, as the metrics
  see it) and ``psf_ref`` (the full array's), ``psf_P`` / ``psf_ref_P`` for a plane;
* ``elements``: the active elements (0-based), the metrics as variables (dimensionless; ``PSL_dB``
  in dB, the -6 dB widths in metres);
* global attributes: the scene's name and description, probe, elements, k, pixel pitch and
  wavelength (m), the whole scene as JSON (``scene_json``), the arraysel version.

The file is written in pieces (``evaluate`` streams any number of masks, memory stays bounded)
with ``h5netcdf``, the HDF5 library xarray's own ``engine="h5netcdf"`` uses, into a temporary
file that is renamed into place when complete.
"""
from __future__ import annotations

import json
import os
from typing import Any, Mapping

import numpy as np

from arraysel.errors import ParameterError

__all__ = ["SUFFIXES", "is_netcdf", "require", "PsfFile", "open_psf", "kernel_layout", "planes_layout",
           "scene_attrs"]

#: file name endings written as netCDF (any other ending: .npz)
SUFFIXES = (".nc", ".nc4", ".h5", ".hdf5")
#: the install command of the writer's packages
INSTALL = "pip install 'arraysel[netcdf]'"
#: units of the metrics written next to the kernels (the others are dimensionless)
_UNITS = {"PSL_dB": "dB", "width_x_6dB": "m", "width_y_6dB": "m"}


def is_netcdf(path) -> bool:
    """``path`` names a netCDF file (:data:`SUFFIXES`)."""
    return str(path).lower().endswith(SUFFIXES)


def require(what: str) -> None:
    """Raise :class:`ParameterError` with the pip command when the writer's packages are missing."""
    import importlib.util

    missing = [m for m in ("xarray", "h5netcdf", "h5py") if importlib.util.find_spec(m) is None]
    if missing:
        raise ParameterError(f"{what}: a netCDF file needs {', '.join(missing)}, which "
                             f"{'is' if len(missing) == 1 else 'are'} not installed; install it with: {INSTALL} "
                             f"(or write .npz)")


#: a layout: ``{name: (dims, values, attrs)}`` for the coordinates and fixed variables, and the
#: kernels' ``(name, dims)`` (without ``selection``)
Layout = dict


def kernel_layout(ref: np.ndarray, pitch: float, points: list | None = None) -> Layout:
    """The layout of a 1-D scene's kernels: ``ref`` the full array's, ``(window, window)`` or
    ``(P, window, window)``; ``pitch`` the pixel size (m); ``points`` the field points ``(x, z)``."""
    ref = np.asarray(ref)
    rows, cols = ref.shape[-2:]
    dims = (("point",) if ref.ndim == 3 else ()) + ("z", "x")
    coords = {
        "x": (("x",), (np.arange(cols) - cols // 2) * float(pitch),
              {"units": "m", "long_name": "lateral distance from the PSF peak"}),
        "z": (("z",), (np.arange(rows) - rows // 2) * float(pitch),
              {"units": "m", "long_name": "axial distance from the PSF peak (down)"}),
    }
    if ref.ndim == 3 and points:
        coords["point_x"] = (("point",), np.array([p[0] for p in points], dtype=np.float64),
                             {"units": "m", "long_name": "lateral position of the field point"})
        coords["point_z"] = (("point",), np.array([p[1] for p in points], dtype=np.float64),
                             {"units": "m", "long_name": "depth of the field point"})
    return {"coords": coords, "kernels": [("psf", dims, ref)]}


def planes_layout(ref_planes: Mapping[str, np.ndarray], coords: Mapping[str, np.ndarray]) -> Layout:
    """The layout of a 3-D scene's planes: ``ref_planes[P]`` the full array's plane ``(rows,
    cols)``, ``coords[P]`` its pixels' positions ``(rows, cols, 3)`` (x, y, z in m)."""
    out: dict[str, Any] = {}
    kernels = []
    for p, ref in ref_planes.items():
        dims = (f"{p}_row", f"{p}_col")
        xyz = np.asarray(coords[p], dtype=np.float64)
        for i, axis in enumerate("xyz"):
            out[f"{p}_{axis}"] = (dims, xyz[..., i], {"units": "m", "long_name": f"{axis} of the {p} plane's pixels"})
        kernels.append((f"psf_{p}", dims, np.asarray(ref)))
    return {"coords": out, "kernels": kernels}


class PsfFile:
    """A netCDF file of kernels written in pieces: ``n`` selections (``None``: one, without the
    ``selection`` dimension) of the ``layout``'s kernels, their elements and metrics, and the
    full array's kernels (``psf_ref``). Published by :meth:`commit`; left without it (an
    exception), the target keeps its old content."""

    def __init__(self, path, layout: Layout, *, n: int | None, k: int, attrs: Mapping[str, Any],
                 metrics: tuple[str, ...] = ()):
        require(str(path))
        import h5netcdf.legacyapi as nc

        from arraysel.io.atomic import AtomicFile

        self._atomic = AtomicFile(path)
        self.n, self.done, self.layout = n, 0, layout
        self.f = nc.Dataset(self._atomic.tmp, "w")
        self._open = True
        try:
            self._define(layout, n, k, attrs, metrics)
        except BaseException:
            self.discard()
            raise

    def _define(self, layout: Layout, n: int | None, k: int, attrs, metrics) -> None:
        f = self.f
        sel = () if n is None else ("selection",)
        if n is not None:
            f.createDimension("selection", n)
            v = f.createVariable("selection", "i8", ("selection",))
            v[:] = np.arange(n)
            v.long_name = "the selection's line in the mask file (0-based, comments and blank lines not counted)"
        for name, (dims, values, _) in layout["coords"].items():
            for d, size in zip(dims, np.shape(values)):
                if d not in f.dimensions:
                    f.createDimension(d, size)
        f.createDimension("k", k)
        for name, (dims, values, vattrs) in layout["coords"].items():
            self._put(name, dims, np.asarray(values, dtype=np.float64), vattrs)
        for name, dims, ref in layout["kernels"]:
            for d, size in zip(dims, ref.shape):
                if d not in f.dimensions:
                    f.createDimension(d, size)
            part = "f4" if ref.dtype in (np.complex64, np.float32) else "f8"
            for suffix, what in (("real", "real"), ("imag", "imaginary")):
                ref_name = name.replace("psf", "psf_ref", 1)
                self._put(f"{ref_name}_{suffix}", dims, getattr(ref, suffix),
                          {"long_name": f"{what} part of the full array's kernel", "units": "1"})
                v = f.createVariable(f"{name}_{suffix}", part, sel + dims)
                v.long_name = f"{what} part of the selection's kernel (unit L2 norm)"
                v.units = "1"
        v = f.createVariable("elements", "i4", sel + ("k",))
        v.long_name = "active elements (0-based)"
        for m in metrics:
            v = f.createVariable(m, "f8", sel)
            v.units = _UNITS.get(m, "1")
        for key, value in attrs.items():
            f.setncattr(key, _attr(value))

    def _put(self, name: str, dims, values: np.ndarray, attrs: Mapping[str, str]) -> None:
        v = self.f.createVariable(name, values.dtype.str.lstrip("<>=|"), dims)
        v[...] = values
        for key, value in attrs.items():
            v.setncattr(key, value)

    def write(self, kernels: Mapping[str, np.ndarray], elements, metrics: Mapping[str, Any]) -> None:
        """The next selections: ``kernels[name]`` ``(B, ...)`` complex for each kernel of the
        layout (one selection without a leading B when ``n`` is None), their ``elements`` ``(B,
        k)`` and ``metrics[name]`` ``(B,)``."""
        if self.n is None:
            where: Any = Ellipsis
            count = 1
        else:
            count = len(np.asarray(elements))
            where = slice(self.done, self.done + count)
        for name, _dims, _ref in self.layout["kernels"]:
            value = np.asarray(kernels[name])
            self.f.variables[f"{name}_real"][where] = value.real
            self.f.variables[f"{name}_imag"][where] = value.imag
        self.f.variables["elements"][where] = np.asarray(elements, dtype=np.int32)
        for m, value in metrics.items():
            self.f.variables[m][where] = np.asarray(value, dtype=np.float64)
        self.done += count

    def _close(self) -> None:
        if self._open:
            self._open = False
            self.f.close()

    def commit(self) -> None:
        if self.n is not None and self.done != self.n:
            raise ParameterError(f"{self._atomic.path}: {self.done} of {self.n} selections written")
        self._close()
        self._atomic.commit()

    def discard(self) -> None:
        try:
            self._close()
        except Exception:  # closing a half-written file: the temporary file goes anyway
            pass
        self._atomic.discard()

    def __enter__(self) -> "PsfFile":
        return self

    def __exit__(self, *exc) -> bool:
        if not self._atomic.committed:
            self.discard()
        return False


def scene_attrs(scene, title: str) -> dict[str, Any]:
    """The global attributes of a file of ``scene``'s kernels (see the module)."""
    from arraysel import __version__

    probe = scene.probe()
    return {"title": title, "scene": scene.name, "scene_description": scene.description,
            "probe": str(getattr(probe, "name", "")), "n_elements": int(probe.n_elements), "k": int(scene.k),
            "pixel_pitch_m": float(scene.pixel), "wavelength_m": float(scene.wavelength),
            "scene_json": json.dumps(scene.to_dict(), default=str), "source": f"arraysel {__version__}"}


def _attr(value):
    """A global attribute netCDF takes: numbers and text as they are, lists as arrays, the rest as JSON."""
    if isinstance(value, (bool, np.bool_)):
        return int(value)
    if isinstance(value, (int, float, str, np.integer, np.floating)):
        return value
    if isinstance(value, (list, tuple)) and value and all(isinstance(v, (int, np.integer)) for v in value):
        return np.asarray(value, dtype=np.int64)
    return json.dumps(value, default=str)


def open_psf(path):
    """The netCDF file ``path`` (written by ``arraysel psf`` or ``evaluate``) as an
    :class:`xarray.Dataset` with each ``NAME_real`` / ``NAME_imag`` pair joined into the complex
    variable ``NAME``; read into memory, the file is closed."""
    require(str(path))
    import xarray as xr

    if not os.path.isfile(path):
        raise ParameterError(f"{str(path)!r} is not a file")
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        ds = ds.load()
    for name in [n[:-5] for n in ds.data_vars if n.endswith("_real") and f"{n[:-5]}_imag" in ds]:
        joined = ds[f"{name}_real"] + 1j * ds[f"{name}_imag"]
        joined.attrs = {**ds[f"{name}_real"].attrs, "long_name": ds[f"{name}_real"].attrs.get(
            "long_name", name).replace("real part of ", "")}
        ds = ds.drop_vars([f"{name}_real", f"{name}_imag"]).assign({name: joined})
    return ds
