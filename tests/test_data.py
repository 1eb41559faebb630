"""Tests of arraysel.e2e.data: IDX files, bundled samples, scatterer maps."""
from __future__ import annotations

import io
import logging
import urllib.error
from importlib import resources

import numpy as np
import pytest
import torch

from arraysel.e2e import data as D
from arraysel.e2e.data import (SceneMaker, find_idx_files, genscat, grid_coordinates, load_dataset,
                           load_idx, points_to_map, read_idx, reflectivity_map, write_idx)
from arraysel.errors import ParameterError


pytestmark = pytest.mark.usefixtures("one_thread")


def _raw_idx(arr: np.ndarray, code: int) -> bytes:
    """An IDX file built byte by byte, independently of write_idx."""
    head = bytes([0, 0, code, arr.ndim]) + b"".join(int(d).to_bytes(4, "big") for d in arr.shape)
    return head + arr.astype(arr.dtype.newbyteorder(">")).tobytes()


def _write_split(folder, split, n=5, seed=0, gz=False):
    rng = np.random.default_rng(seed)
    imgs = rng.integers(0, 256, size=(n, 28, 28), dtype=np.uint8)
    labs = rng.integers(0, 10, size=n, dtype=np.uint8)
    folder.mkdir(parents=True, exist_ok=True)
    suffix = ".gz" if gz else ""
    write_idx(folder / (D.IDX_FILES[split][0] + suffix), imgs)
    write_idx(folder / (D.IDX_FILES[split][1] + suffix), labs)
    return imgs, labs


@pytest.fixture(autouse=True)
def _no_env(monkeypatch):
    monkeypatch.delenv("ARRAYSEL_DATA", raising=False)


# -- IDX format ---------------------------------------------------------------

def test_read_idx_parses_handmade_header(tmp_path):
    arr = np.arange(2 * 3 * 4, dtype=np.uint8).reshape(2, 3, 4)
    p = tmp_path / "x-idx3-ubyte"
    p.write_bytes(_raw_idx(arr, 0x08))
    out = read_idx(p)
    assert out.shape == (2, 3, 4) and out.dtype == np.uint8
    np.testing.assert_array_equal(out, arr)
    ints = np.array([-5, 7, 2**30], dtype=np.int32)
    p.write_bytes(_raw_idx(ints, 0x0C))
    out = read_idx(p)
    assert out.dtype == np.int32 and out.dtype.byteorder in "=|<" or out.dtype.isnative
    np.testing.assert_array_equal(out, ints)


@pytest.mark.parametrize("dtype", [np.uint8, np.int8, np.int16, np.int32, np.float32, np.float64])
@pytest.mark.parametrize("gz", [False, True])
def test_idx_round_trip(tmp_path, dtype, gz):
    rng = np.random.default_rng(1)
    arr = (rng.normal(size=(3, 5, 2)) * 50).astype(dtype)
    p = tmp_path / ("a.idx" + (".gz" if gz else ""))
    write_idx(p, arr)
    if gz:
        assert p.read_bytes()[:2] == b"\x1f\x8b"
    out = read_idx(p)
    assert out.dtype == np.dtype(dtype) and out.shape == arr.shape
    np.testing.assert_array_equal(out, arr)


def test_read_idx_rejects_bad_files(tmp_path):
    p = tmp_path / "bad"
    p.write_bytes(b"\x01\x00\x08\x01" + (3).to_bytes(4, "big") + b"abc")
    with pytest.raises(ParameterError, match="magic"):
        read_idx(p)
    p.write_bytes(b"\x00\x00\x42\x01" + (3).to_bytes(4, "big") + b"abc")
    with pytest.raises(ParameterError, match="type code"):
        read_idx(p)
    p.write_bytes(b"\x00\x00\x08\x01" + (4).to_bytes(4, "big") + b"abc")
    with pytest.raises(ParameterError, match=r"shape \(4,\)"):
        read_idx(p)


# -- locating files -----------------------------------------------------------

@pytest.mark.parametrize("layout", ["mnist", "fashion", "MNIST/raw", "FashionMNIST/raw", "."])
def test_find_idx_files_layouts(tmp_path, layout):
    name = "fashion" if "ashion" in layout else "mnist"
    _write_split(tmp_path / layout, "test", gz=(layout == "."))
    imgs, labs = find_idx_files(name, "test", tmp_path)
    assert imgs.name.startswith("t10k-images") and labs.name.startswith("t10k-labels")


def test_env_var_gives_directory(tmp_path, monkeypatch):
    imgs, labs = _write_split(tmp_path / "fashion", "train", n=4)
    monkeypatch.setenv("ARRAYSEL_DATA", str(tmp_path))
    x, y = load_dataset("fashion", "train", source="idx")
    assert x.shape == (4, 1, 28, 28) and x.dtype == torch.float32
    assert y.dtype == torch.int64
    torch.testing.assert_close(x[:, 0], torch.from_numpy(imgs).float() / 255)
    np.testing.assert_array_equal(y.numpy(), labs)


def test_missing_files_error_names_files_and_directory(tmp_path):
    with pytest.raises(ParameterError) as exc:
        load_dataset("mnist", "test", source="idx", data_dir=tmp_path)
    msg = str(exc.value)
    assert "t10k-images-idx3-ubyte" in msg and "t10k-labels-idx1-ubyte" in msg
    assert str(tmp_path / "mnist") in msg
    with pytest.raises(ParameterError, match="ARRAYSEL_DATA"):
        load_idx("mnist", "train")


def test_download_failure_is_clear(tmp_path, monkeypatch):
    def refuse(url, timeout):
        assert timeout == 0.5
        raise urllib.error.URLError("network unreachable")

    monkeypatch.setattr(D.urllib.request, "urlopen", refuse)
    with pytest.raises(ParameterError) as exc:
        load_idx("mnist", "train", tmp_path, download=True, timeout=0.5)
    msg = str(exc.value)
    assert "train-images-idx3-ubyte" in msg and "download failed" in msg
    assert "network unreachable" in msg


def test_download_writes_files(tmp_path, monkeypatch):
    src = tmp_path / "mirror"
    _write_split(src, "train", gz=True)
    _write_split(src, "test", gz=True)
    seen = []

    def serve(url, timeout):
        seen.append(url)
        return io.BytesIO((src / url.rsplit("/", 1)[1]).read_bytes())

    monkeypatch.setattr(D.urllib.request, "urlopen", serve)
    x, y = load_dataset("mnist", "test", source="idx", data_dir=tmp_path / "d", download=True)
    assert x.shape == (5, 1, 28, 28) and len(seen) == 4
    assert sorted(p.name for p in (tmp_path / "d" / "mnist").iterdir()) == sorted(
        f + ".gz" for s in ("train", "test") for f in D.IDX_FILES[s])


def test_download_is_atomic_and_follows_umask(tmp_path, monkeypatch):
    """A payload that does not parse leaves nothing behind; kept files get the umask's mode."""
    import os

    src = tmp_path / "mirror"
    _write_split(src, "train", gz=True)
    _write_split(src, "test", gz=True)

    def corrupt(url, timeout):
        return io.BytesIO(b"not an idx file")

    monkeypatch.setattr(D.urllib.request, "urlopen", corrupt)
    with pytest.raises(ParameterError, match="download failed"):
        load_idx("mnist", "train", tmp_path / "bad", download=True)
    assert list((tmp_path / "bad" / "mnist").iterdir()) == []

    def serve(url, timeout):
        return io.BytesIO((src / url.rsplit("/", 1)[1]).read_bytes())

    monkeypatch.setattr(D.urllib.request, "urlopen", serve)
    old = os.umask(0o027)
    try:
        load_idx("mnist", "train", tmp_path / "d", download=True)
    finally:
        os.umask(old)
    for p in (tmp_path / "d" / "mnist").iterdir():
        assert p.stat().st_mode & 0o777 == 0o640, p


def test_no_download_without_flag(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise AssertionError("must not download")

    monkeypatch.setattr(D.urllib.request, "urlopen", boom)
    with pytest.raises(ParameterError):
        load_idx("mnist", "train", tmp_path)


# -- bundled samples and load_dataset --------------------------------------------

@pytest.mark.parametrize("name", ["mnist", "fashion"])
def test_bundled_samples(name):
    ref = resources.files("arraysel") / "data" / f"{name}_sample.npz"
    with resources.as_file(ref) as p:
        assert p.stat().st_size < 300_000
        with np.load(p) as z:
            assert "MIT" in str(z["license"])
    for split, n in (("train", 300), ("test", 100)):
        x, y = load_dataset(name, split, source="sample")
        assert x.shape == (n, 1, 28, 28) and x.dtype == torch.float32
        assert y.shape == (n,) and y.dtype == torch.int64
        assert 0 <= float(x.min()) and float(x.max()) <= 1 and float(x.max()) > 0.9
        assert torch.equal(torch.bincount(y, minlength=10), torch.full((10,), n // 10))
    tr, _ = load_dataset(name, "train", source="sample")
    te, _ = load_dataset(name, "test", source="sample")
    # train and test are disjoint
    a = {bytes(v) for v in (tr * 255).round().to(torch.uint8).numpy()}
    b = {bytes(v) for v in (te * 255).round().to(torch.uint8).numpy()}
    assert not a & b


def test_auto_falls_back_to_sample_and_says_so(tmp_path, caplog):
    with caplog.at_level(logging.WARNING, logger="arraysel.e2e.data"):
        x, _ = load_dataset("mnist", "test", source="auto", data_dir=tmp_path, limit=7)
    assert x.shape == (7, 1, 28, 28)
    assert "bundled mnist sample" in caplog.text and "t10k-images-idx3-ubyte" in caplog.text


def test_auto_prefers_idx(tmp_path, caplog):
    _write_split(tmp_path / "mnist", "test", n=3)
    with caplog.at_level(logging.WARNING, logger="arraysel.e2e.data"):
        x, _ = load_dataset("mnist", "test", data_dir=tmp_path)
    assert x.shape == (3, 1, 28, 28) and "sample" not in caplog.text


def test_bad_arguments():
    with pytest.raises(ParameterError, match="name"):
        load_dataset("cifar")
    with pytest.raises(ParameterError, match="split"):
        load_dataset("mnist", "val")
    with pytest.raises(ParameterError, match="source"):
        load_dataset("mnist", source="web")


# -- scatterer maps -------------------------------------------------------------

def test_reflectivity_map_shapes_and_values():
    img = torch.rand(3, 1, 28, 28)
    m = reflectivity_map(img, 32)
    assert m.shape == (3, 1, 32, 32) and 0 <= float(m.min()) and float(m.max()) <= 1
    const = torch.full((28, 28), 0.25)
    torch.testing.assert_close(reflectivity_map(const, 64), torch.full((1, 1, 64, 64), 0.25))
    assert torch.equal(reflectivity_map(img, 28), img)
    # a left-right ramp stays a ramp (columns are lateral positions)
    ramp = torch.linspace(0, 1, 28).expand(28, 28)
    m = reflectivity_map(ramp, 40)[0, 0]
    assert torch.all(m[:, 1:] >= m[:, :-1]) and torch.allclose(m[0], m[-1])


def test_grid_coordinates():
    x, z = grid_coordinates(4, (0.01, 0.05))
    torch.testing.assert_close(z, torch.tensor([0.015, 0.025, 0.035, 0.045], dtype=torch.float64))
    torch.testing.assert_close(x, torch.tensor([-0.015, -0.005, 0.005, 0.015], dtype=torch.float64))
    with pytest.raises(ParameterError):
        grid_coordinates(4, (0.05, 0.01))


def test_genscat_positions_and_amplitudes():
    img = torch.zeros(28, 28)
    img[:14] = 1.0  # shallow half bright, deep half dark
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    x, z, rc = genscat(img, generator=g1, depth_range=(0.0, 0.15), n_scatterers=4000, speckle=False)
    x2, z2, rc2 = genscat(img, generator=g2, depth_range=(0.0, 0.15), n_scatterers=4000, speckle=False)
    assert torch.equal(x, x2) and torch.equal(rc, rc2)
    assert x.shape == (4000,) and float(x.abs().max()) <= 0.075
    assert 0 <= float(z.min()) and float(z.max()) <= 0.15
    assert torch.allclose(rc[z < 0.072], torch.tensor(1.0, dtype=rc.dtype))
    assert torch.all(rc[z > 0.078].abs() < 1e-12)
    mid = (z > 13.5 / 28 * 0.15 + 1e-6) & (z < 14.5 / 28 * 0.15 - 1e-6)  # between the centres of rows 13 and 14: interpolated
    assert torch.all((rc[mid] > 0) & (rc[mid] < 1))
    # count from the mean nearest-neighbour distance: area / (4 d^2)
    x, _, _ = genscat(img, generator=g1, depth_range=(0.0, 0.02), mean_distance=1e-3)
    assert x.numel() == round(0.02 * 0.02 / 4e-6)
    # Rayleigh speckle with the image as its mean
    _, z, rc = genscat(torch.ones(8, 8), generator=g1, n_scatterers=20000)
    assert abs(float(rc.mean()) - 1) < 0.03 and float(rc.min()) >= 0


def test_points_to_map_conserves_reflectivity():
    # a point on a pixel centre lands on that pixel only
    x, z = grid_coordinates(8, (0.0, 0.08))
    m = points_to_map(x[[2]], z[[5]], torch.tensor([2.0], dtype=torch.float64), 8,
                      depth_range=(0.0, 0.08), width=0.08)
    assert float(m[5, 2]) == pytest.approx(2.0) and float(m.sum()) == pytest.approx(2.0)
    g = torch.Generator().manual_seed(0)
    xs = (torch.rand(100, generator=g, dtype=torch.float64) - 0.5) * 0.06  # away from the border
    zs = 0.01 + torch.rand(100, generator=g, dtype=torch.float64) * 0.06
    rc = torch.randn(100, generator=g, dtype=torch.float64) + 0j
    m = points_to_map(xs, zs, rc, 16, depth_range=(0.0, 0.08), width=0.08)
    assert m.dtype == torch.complex128
    torch.testing.assert_close(m.sum(), rc.sum())


def test_scene_maker_modes():
    imgs = torch.rand(2, 1, 28, 28)
    i_s, i_ref = SceneMaker(n=32)(imgs)
    assert i_s.shape == (2, 1, 32, 32) and torch.equal(i_s, i_ref)
    maker = SceneMaker(n=16, mode="points", n_scatterers=16 * 16 * 50, speckle=False,
                       random_phase=False)
    i_s, i_ref = maker(torch.full((1, 1, 28, 28), 0.5), torch.Generator().manual_seed(0))
    assert i_s.dtype == torch.float32 and i_s.shape == (1, 1, 16, 16)
    # normalised so that its expectation is the reflectivity map (interior pixels)
    assert abs(float(i_s[..., 2:-2, 2:-2].mean()) - 0.5) < 0.03
    cmaker = SceneMaker(n=16, mode="points", n_scatterers=500, random_phase=True)
    i_s, _ = cmaker(imgs, torch.Generator().manual_seed(1))
    assert i_s.dtype == torch.complex64 and i_s.shape == (2, 1, 16, 16)
    with pytest.raises(ParameterError, match="Generator"):
        cmaker(imgs)
    with pytest.raises(ParameterError):
        SceneMaker(mode="voxels")
