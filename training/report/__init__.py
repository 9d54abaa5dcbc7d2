"""Reporting: ``docs/results.md`` and its figures from a run's ``metrics.json``.

``results`` (the entry, :func:`~training.report.results.write_report`), ``metrics`` (loading
``metrics.json``, provenance), ``figures``, ``markdown`` (the tables and text) and ``suite``
(a benchmark suite's report against its targets and the baseline model). Reads the stage
records (``training.stage_records``); flies nothing but the trace figures' episodes.
"""
