"""Batch slicing: many models, the same options, on local worker processes or an existing Dask cluster.

``discover.py`` finds the models, ``options.py`` holds the options (composed of the pipeline's), ``task.py`` runs one
model through the one pipeline (:func:`gpuslice.pipeline.run_job`), ``runner.py`` hands tasks to workers and
collects records, ``journal.py`` keeps the files each finished model left, ``report.py`` prints the summary.
"""

from ..errors import BatchError
from .discover import MESH_SUFFIXES, Model, discover
from .journal import JOURNAL_NAME
from .options import BatchOptions, typed_raster_options
from .report import format_summary
from .runner import MANIFEST_NAME, BatchRunner, run_batch
from .task import connect, default_workers, init_worker, pocl_thread_env, run_model

__all__ = [
    "BatchError",
    "BatchOptions",
    "BatchRunner",
    "JOURNAL_NAME",
    "MANIFEST_NAME",
    "MESH_SUFFIXES",
    "Model",
    "connect",
    "default_workers",
    "discover",
    "format_summary",
    "init_worker",
    "pocl_thread_env",
    "run_batch",
    "run_model",
    "typed_raster_options",
]
