"""Helpers shared by the tests (not test modules: pytest collects nothing here).

tests/ is on sys.path while pytest runs (tests/conftest.py is imported in
pytest's default "prepend" import mode, which puts its folder first), so test
modules and conftest.py import these as `from support.<module> import ...`.

    paths            REPO, SHARED_DATA, shared_path (skip when ../shared/data lacks a file)
    fake_datasets    tiny D-NeRF / DyCheck iPhone datasets written on disk
    toy_grouping     hand-made 4D scenes with known trajectories, for the grouping
    tiny_scene       a tiny rendered scene + priors for the reconstruction stage
    forecast_scene   scene, split and refined model with known group motion, for the forecast stage
    forecast_params  small forecaster budgets
    moving_squares   textured squares sliding over a textured background (2D tracking)
"""
