"""Evaluation: how any localizer is run over queries and graded.

* :mod:`satloc.evaluation.metrics`: error statistics, block-bootstrap intervals, precision and recall;
* :mod:`satloc.evaluation.plots`: errors along the route, posteriors over the map.

It may import the localizers (their interface and answers), never :mod:`satloc.baselines` nor the pipeline.
"""
