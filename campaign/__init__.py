"""Parallel ensemble campaigns of jammed frictionless disk packings.

Orchestration lives here (spec, tasks, worker, comm, master, store, reduce,
plots, cli); the numerical work lives in the sibling package ``kernels``.
"""

__version__ = "0.1.0"
