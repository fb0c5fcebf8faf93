"""Batch slicing of many models on local worker processes or a Dask cluster."""

from .runner import *  # noqa: F403
from .runner import __all__  # noqa: F401
