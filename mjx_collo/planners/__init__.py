"""Planner internals: protocol, objective, solvers, collocation loop, shooting baselines.

The public entry point is :mod:`mjx_collo.planner`.
"""
