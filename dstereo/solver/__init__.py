"""Least-squares solvers: the structured (Schur) batched Levenberg-Marquardt, and optimistix for reference."""

from dstereo.solver.lm import LMOptions, LMResult, STATUS_TEXT, solve_structured, solve_structured_batch

__all__ = ["LMOptions", "LMResult", "STATUS_TEXT", "solve_structured", "solve_structured_batch"]
