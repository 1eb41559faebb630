"""The 0.1 module ``arraysel.executors`` (and the first 0.2 ``arraysel.run.executors``): every name it
had, from where it lives now. Reached only through the deprecated path (``arraysel._compat``)."""
from arraysel.objective.psf_objective import SceneObjectiveFactory  # noqa: F401
from arraysel.objective.toy import ToyObjectiveFactory  # noqa: F401
from arraysel.run.compare_task import _Raise, compare_item, compare_task  # noqa: F401
from arraysel.run.executors import (DASK_INSTALL_HINT, DEFAULT_RETRIES, EXECUTORS, DaskExecutor, Executor,  # noqa: F401
                                    LocalExecutor, ProcessExecutor, make_executor)
from arraysel.run.isolation import DEFAULT_GRACE_S, IsolatedWorker  # noqa: F401
from arraysel.run.random_search import (RandomSearchResult, distributed_evaluate,  # noqa: F401
                                        distributed_random_search, random_subsets)
from arraysel.run.workers import TaskFailed, objective_factory_for  # noqa: F401
