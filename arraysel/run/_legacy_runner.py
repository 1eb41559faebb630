"""The 0.1 module ``arraysel.runner``: every name it had, from where it lives now. Reached only
through the deprecated path (``arraysel._compat``)."""
from arraysel.report.columns import METRICS, ROW_COLUMNS, TRACE_COLUMNS  # noqa: F401
from arraysel.run.compare import DEFAULT_SEEDS, compare  # noqa: F401
from arraysel.run.experiment import Experiment, config_label, full_row  # noqa: F401
from arraysel.run.outdir import RESULT_FILES, check_out_dir, check_resume, remove_results  # noqa: F401
