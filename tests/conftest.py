import os
import sys

import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))


@pytest.fixture(scope="session")
def paper_objective():
    """The paper scene's float32 objective, built once per test session (cached on disk)."""
    from arraysel.objective.psf_objective import build_objective

    return build_objective("paper")


@pytest.fixture(scope="session")
def pymust_scene():
    pytest.importorskip("pymust")
    from pymust_pipeline import PyMUSTScene

    return PyMUSTScene()


@pytest.fixture(params=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def device(request):
    return request.param


@pytest.fixture(scope="module")
def one_thread():
    """Tiny tensors: one intra-op thread is far faster on a shared machine (restored afterwards)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(autouse=True)
def _ioh_folders_load_in_iohinspector(request):
    """Every IOHprofiler folder a test writes under its ``tmp_path`` loads whole in the installed
    iohinspector (a reader's view of ``arraysel compare``'s ioh/)."""
    yield
    tmp = request.node.funcargs.get("tmp_path") if hasattr(request.node, "funcargs") else None
    if tmp is not None:
        from support import ioh_folders_load

        ioh_folders_load(tmp)
