"""Measuring layer settings: timings side by side (``runner.py``), schedule quality (``quality.py``) and the
paper's figures (``plots.py``)."""

from .runner import BenchResult, Setting, parse_settings, run_bench

__all__ = ["BenchResult", "Setting", "parse_settings", "run_bench"]
