"""Experiments: what runs the method and the simulator to produce figures.

* :mod:`~satloc_env.experiments.scene_run`: one scene end to end (record, build, learn, localize, report);
* :mod:`~satloc_env.experiments.tables`: the comparison harness, Tables I and II and the sweep;
* :mod:`~satloc_env.experiments.tune`: settings chosen again on calibration scenes;
* :mod:`~satloc_env.experiments.evaluate`: the method on replayed real sequences (KITTI, Malaga);
* :mod:`~satloc_env.experiments.train_features`: the FCN trained on rendered images;
* :mod:`~satloc_env.experiments.bench`, :mod:`~satloc_env.experiments.soak`,
  :mod:`~satloc_env.experiments.determinism`: benchmarks that print figures, long runs, image digests;
* :mod:`~satloc_env.experiments.scale`: the experiments' units as Ray tasks, environments in Ray actors.

It may import :mod:`satloc` and every layer of :mod:`satloc_env` below it (world, render, envs, agents);
never the command line (an import-linter contract in ``pyproject.toml`` checks it).
"""
