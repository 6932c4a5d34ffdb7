"""Tools that look into trained policies and the env (the logic of ``recipes/analyze/``,
``recipes/render.py`` and the benchmarks): saliency, stage progression, grasp losses,
approach and contact diagnostics, iteration profiles, GIFs, env speed."""
