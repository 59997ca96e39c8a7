"""The method x scene harness behind evaluate.py: scene recipes, methods, the runner, the report."""

from neuralsurf.evaluation.methods import NotApplicable, fit_and_extract, poisson, tsdf
from neuralsurf.evaluation.report import markdown_table, write_report
from neuralsurf.evaluation.runner import run_benchmark
from neuralsurf.scenes import SceneUnavailable

__all__ = ["NotApplicable", "SceneUnavailable", "fit_and_extract", "markdown_table",
           "poisson", "run_benchmark", "tsdf", "write_report"]
