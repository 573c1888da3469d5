"""Analysis of sweep results: reads result files only (no SUMO, no torch).

- ``analysis.stats``: ``t_quantile_975`` and ``paired_difference`` (paired t-test by seed, else
  Welch's t-test)
- ``analysis.results``: ``load_results``, ``summarise`` (mean and 95 % t-CI), ``to_parquet``
- ``analysis.tables``: paper-shaped macro/micro tables with safety counts, per-cell table
- ``analysis.figures``: seaborn figures with CIs (penetration, density, micro, weather)
- ``analysis.findings``: short data-driven findings (differences tested with ``paired_difference``)
- ``analysis.pdf``: reportlab building blocks of the report
- ``analysis.report``: ``build_report`` (PDF with reportlab) and the command line
  (``python -m mixed_traffic.report`` or ``python -m analysis.report``)
"""
